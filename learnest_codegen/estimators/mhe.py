"""Moving horizon estimator (paper section IV-A, eq. (2)) solved by CasADi nlpsol + Ipopt.

This is the reference the compiled MHE (``codegen/mhe.py``, ``runtime/mhe.py``) is tested
against; the C API re-implements :meth:`MHE.step`'s bookkeeping line by line, so a change here
must be made there too (the parity test will say so).

Per sample: the window moves by one stage; the arrival prior becomes the previous solution's
estimate of the new first state (``xbar_{k-N|k} <- xhat*_{k-N|k-1}``) once the window is full
(before, the arrival term stays on sample 0 with ``xbar = x0``); Ipopt is warm-started from the
previous solution shifted by one stage, its new last state predicted by ``F``; the estimate is
the last window state. A step Ipopt does not solve raises :class:`SolverError` and leaves the
estimator as it was: silently keeping a poor estimate would hide the problem, and the caller
can still decide to go on.

Innovation gate (:mod:`.gate`): before a sample enters the window, each output's innovation
``y_j - h_j(xpred, u)`` at the prediction ``xpred`` (the warm start's last state) is normalised
by ``S_jj = (C P_arr C^T)_jj + (R^-1)_jj`` (``C = dh/dx`` at ``xpred``, ``P_arr`` the inverse of
the arrival weight times the gate's inflation ``rho``); a rejected output gets a 0 in the
window's gate block ``G`` and never enters the cost while the sample is in the window.
Recovery: ``rho`` is 1 normally and multiplied by ``inflation`` at each rejecting step from the
``recover_after``-th consecutive one on, so the gate widens until the new measurements pass.
The first step that then rejects nothing ends the episode and restarts the window: it is emptied,
its prior ``xbar`` is the Kalman update of the prediction ``xpred ~ (., rho diag(P^-1))`` by the
sample (:func:`restart_prior`), the sample itself is folded into that prior (gate weight 0)
and the step is taken as the first after a reset, with the arrival weight ``P`` as given.
``rho`` then shrinks by ``inflation`` per step without rejection, so the gate stays wide while
the window re-learns what the restart could not set (measured: resetting ``rho`` to 1 at the
restart made a wrap of the whole cartpole state, velocities included, lose the track again
for 1,500 samples). A step the solver fails on also restarts the window at the next
step (the estimate stays as it was; the prior is updated by the outputs the gate keeps), so a
window the solver cannot solve is not retried forever.

Why a restart and not a relaxed arrival weight (the first design): a window that keeps its
old samples must explain a real jump by one huge process-noise step, and an arrival weight
``P / rho`` with ``rho ~ 1e5`` makes the Gauss-Newton normal equations so ill-conditioned that
its absolute step tolerance is never met; both locked the embedded MHE with MAX_ITERATIONS
after a 45 rad jump of the measured cartpole angle (measured).
"""

from __future__ import annotations

import numpy as np

from ..errors import SolverError
from ..export import DiscreteModel
from . import validation
from .gate import GateReport, GateState
from .mhe_problem import MHESettings, ParamLayout, build_problem, gate_variances, measurement_function

NO_COVARIANCE = ("MHE has no state covariance: it solves a least-squares problem per sample and "
                 "propagates no P. The arrival-cost weight is `arrival_weight`.")


class MHE(GateReport):
    """Moving horizon estimator over any :class:`DiscreteModel` (reference implementation).

    Parameters
    ----------
    model : the discrete model ``x+ = F(x, u)``, ``y = h(x, u)`` (nominal, true or KNODE).
    settings : horizon and weights; default ``MHESettings.from_system(model.system)``.

    Attributes
    ----------
    x : (nx,) current estimate, the last window state.
    window : (N+1, nx) current window solution, oldest first.
    iterations : Ipopt iterations of the last step.
    rejected : (ny,) bool, the outputs the gate rejected in the last step.
    last_status : 0 (OK) or 1 (MEASUREMENT_REJECTED), the C status of the last step.
    rejections : outputs rejected since :meth:`reset`.
    """

    def __init__(self, model: DiscreteModel, settings: MHESettings | None = None):
        self.model = model
        self.settings = settings or MHESettings.from_system(model.system)
        self.problem = build_problem(model, self.settings, f"{model.system.name}_{model.kind}_mhe")
        self.layout: ParamLayout = self.problem.layout
        self.iterations = 0
        self.rejections = 0
        self._gate = GateState(self.settings.gate, model.ny)
        self._meas = measurement_function(model, "meas")
        self._P_given = self._P_cov = self._R_weight = None
        self._p: np.ndarray | None = None
        self._window: np.ndarray | None = None
        self._count = 0

    @property
    def P(self):
        """Not available: an MHE has no state covariance (raises AttributeError)."""
        raise AttributeError(NO_COVARIANCE)

    @property
    def x(self) -> np.ndarray:
        return self._started()[-1].copy()

    @property
    def window(self) -> np.ndarray:
        return self._started().copy()

    @property
    def arrival_weight(self) -> np.ndarray:
        """(nx, nx) the weight ``P`` of the arrival cost given at :meth:`reset` (the gate's
        recovery divides it by its inflation while a track is being recovered)."""
        self._started()
        return self._P_given.copy()

    def reset(self, x0: np.ndarray, P0: np.ndarray | None = None) -> None:
        """Start over from the prior ``x0 (nx,)``, the first arrival ``xbar``.

        ``P0 (nx, nx)``, if given, is the covariance of that prior: the arrival weight becomes
        ``inv(P0)`` for the whole run (otherwise ``diag(1/arrival_std**2)`` from the settings).
        """
        x0 = validation.vector("MHE.reset: x0", x0, self.model.nx)
        Q, R, P = self.settings.weights()
        if P0 is not None:
            P = arrival_weight_from_covariance(P0, self.model.nx)
        lay, n1 = self.layout, self.layout.horizon + 1
        p = np.zeros(lay.size)
        p[lay.slice("xbar")] = x0
        for name, W in (("Q", Q), ("R", R), ("P", P)):
            p[lay.slice(name)] = W.ravel(order="F")
        self._p, self._window, self._count = p, np.tile(x0, (n1, 1)), 0
        self._P_given, self._P_cov, self._R_weight = P, np.linalg.inv(P), R
        self._R_cov = np.linalg.inv(R)
        self._gate = GateState(self.settings.gate, self.model.ny)  # settings as of this reset
        self._restart = False
        self.rejections = 0

    def step(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Take the sample ``y (ny,)`` with ``u (nu,)``, the input applied since the previous one.

        The first step after :meth:`reset` takes sample 0: there is no transition and ``u``
        only enters ``h``. Returns the estimate ``x (nx,)``.
        """
        self._started()
        u = validation.vector("MHE.step: u", u, self.model.nu)
        y = validation.vector("MHE.step: y", y, self.model.ny)
        p, guess, rejected, restart = self._advance(u, y)
        try:
            solution = self.problem.solver(x0=guess.ravel(), p=p)
        except RuntimeError as exc:  # error_on_fail: nlpsol raises when Ipopt did not succeed
            self._restart = True  # the same window would fail again: restart it next step
            status = self.problem.solver.stats().get("return_status", "unknown")
            raise SolverError(f"MHE.step (sample {self._count}): Ipopt returned {status}") from exc
        self.iterations = int(self.problem.solver.stats()["iter_count"])
        self._p, self._window = p, np.asarray(solution["x"]).reshape(self.layout.horizon + 1, -1)
        self._count += 1
        self._gate.record(rejected)
        self._restart = False
        self.rejections += int(rejected.sum())
        return self.x

    def run(self, U: np.ndarray, Y: np.ndarray, x0: np.ndarray,
            P0: np.ndarray | None = None) -> np.ndarray:
        """Estimate a whole run: ``U (T, nu)``, ``Y (T, ny)`` -> ``X_hat (T, nx)``.

        Sample 0 uses ``Y[0]`` only (with a zero input in ``h``); sample ``k >= 1`` is
        ``step(U[k-1], Y[k])``, so ``U[T-1]`` is not used.
        """
        U, Y = validation.run_arrays("MHE.run", U, Y, self.model.nu, self.model.ny)
        self.reset(x0, P0)
        X_hat = np.empty((len(Y), self.model.nx))
        X_hat[0] = self.step(np.zeros(self.model.nu), Y[0])
        for k in range(1, len(Y)):
            X_hat[k] = self.step(U[k - 1], Y[k])
        return X_hat

    def _advance(self, u: np.ndarray, y: np.ndarray):
        """Parameters, warm start, rejected outputs and whether the window restarts, for the
        next sample (mirrored by ``<prefix>_step`` in C)."""
        lay = self.layout
        p, guess = self._p.copy(), self._window.copy()
        U, Y = p[lay.slice("U")].reshape(-1, lay.nu), p[lay.slice("Y")].reshape(-1, lay.ny)
        mask, G = p[lay.slice("mask")], p[lay.slice("G")].reshape(-1, lay.ny)
        if self._count > 0:
            if mask[0] == 1.0:  # window was full: the arrival moves on to the next sample
                p[lay.slice("xbar")] = self._window[1]
            for block in (U, Y, mask, G, guess):
                block[:-1] = block[1:]
            guess[-1] = self.model.step(self._window[-1], u)
        rho = self._gate.inflation
        h, C = (np.asarray(v) for v in self._meas(guess[-1], u))
        h = h.ravel()
        S = gate_variances(C, rho * self._P_cov, self._R_weight)
        with np.errstate(over="ignore"):  # an absurd y gives d2 = inf: rejected
            rejected = self._gate.test((y - h) ** 2 / S)
        recovering = self._gate.streak >= self.settings.gate.recover_after
        restart = self._count > 0 and (self._restart or (recovering and not rejected.any()))
        if restart:
            xbar = restart_prior(guess[-1], C, rho * self._P_cov, self._R_cov, y - h, rejected)
            p, guess = self._restarted(p, xbar)
            U, Y = p[lay.slice("U")].reshape(-1, lay.nu), p[lay.slice("Y")].reshape(-1, lay.ny)
            mask, G = p[lay.slice("mask")], p[lay.slice("G")].reshape(-1, lay.ny)
        U[-1], Y[-1], mask[-1] = u, y, 1.0
        G[-1] = 0.0 if restart else ~rejected  # a restart folds the sample into the prior
        return p, guess, rejected, restart

    def _restarted(self, p: np.ndarray, xbar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The parameters and guess of an empty window with prior ``xbar`` (the recovery's
        restart: the sample is then taken as the first after a reset)."""
        lay = self.layout
        fresh = np.zeros_like(p)
        for name in ("Q", "R", "P"):
            fresh[lay.slice(name)] = p[lay.slice(name)]
        fresh[lay.slice("xbar")] = xbar
        return fresh, np.tile(xbar, (lay.horizon + 1, 1))

    def _started(self) -> np.ndarray:
        if self._window is None:
            raise RuntimeError("MHE: call reset(x0) before step() or reading the state")
        return self._window


def restart_prior(x_pred: np.ndarray, C: np.ndarray, P: np.ndarray, R: np.ndarray,
                  innovation: np.ndarray, rejected: np.ndarray) -> np.ndarray:
    """The recovery's new prior: the Kalman update of ``x_pred ~ (., diag(P))`` by the outputs
    the gate kept (``C = dh/dx``, ``R`` the measurement covariance); ``x_pred`` if none is kept.

    The correlations of ``P`` are dropped: the innovation of a re-acquired track is gross, and
    through a correlation it would throw the unmeasured states (measured on the cartpole: a
    45 rad jump of the measured angle moved the angular rate by tens of rad/s and the track
    was lost again); with ``diag(P)`` only the states the outputs see move.
    """
    keep = ~np.asarray(rejected, dtype=bool)
    if not keep.any():
        return x_pred.copy()
    P = np.diag(np.diag(P))
    Ck = C[keep]
    S = Ck @ P @ Ck.T + R[np.ix_(keep, keep)]
    return x_pred + P @ Ck.T @ np.linalg.solve(S, innovation[keep])


def arrival_weight_from_covariance(P0: np.ndarray, nx: int) -> np.ndarray:
    """``inv(P0)`` for a symmetric positive-definite ``P0 (nx, nx)``, with clear errors."""
    P0 = validation.covariance("MHE.reset: P0", P0, nx, definite=True)
    L = np.linalg.cholesky(P0)
    L_inv = np.linalg.inv(L)
    return L_inv.T @ L_inv
