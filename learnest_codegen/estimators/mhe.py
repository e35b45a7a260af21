"""Moving horizon estimator (paper section IV-A, eq. (2)) solved by CasADi nlpsol + Ipopt.

This is the reference the compiled MHEs (``codegen/mhe.py``, ``codegen/mhe_gn.py``) are
tested against; its window (:mod:`.mhe_window`) and :meth:`MHE._advance` are the C kit's
``learnest_window.h`` and ``learnest_mhe.h`` line by line, so a change here must be made there
too (``tests/test_ckit.py`` compares them).

Per sample: the window moves by one stage; the arrival prior becomes the previous solution's
estimate of the new first state (``xbar_{k-N|k} <- xhat*_{k-N|k-1}``) once the window is full
(before, the arrival term stays on sample 0 with ``xbar = x0``); Ipopt is warm-started from the
previous solution shifted by one stage, its new last state predicted by ``F``; the estimate is
the last window state. A step Ipopt does not solve raises :class:`SolverError` and leaves the
estimator as it was: silently keeping a poor estimate would hide the problem, and the caller
can still decide to go on.

Innovation gate (:mod:`.gate`): before a sample enters the window, each valid output's
innovation ``y_j - h_j(xpred, u)`` at the prediction ``xpred`` (the warm start's last state) is
normalised by ``S_jj = rho (C P0 C^T)_jj + R_jj`` (``C = dh/dx`` at ``xpred``, ``P0`` and ``R``
the arrival and measurement covariances, ``rho`` the gate's inflation); a rejected or missing
output gets a 0 in the window's weights ``G`` and never enters the cost while the sample is in
the window; the rest of its stage stays.
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

from ..errors import ShapeError, SolverError
from ..export import DiscreteModel
from . import validation
from .gate import GateReport, GateState
from .mhe_problem import MHESettings, ParamLayout, build_problem, measurement_function
from .mhe_window import Window

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
        self._weights: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # Q, R, P
        self._P_cov = self._R_cov = None
        self._now: Window | None = None
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
        """(nx, nx) the weight ``P`` of the arrival cost in use (the inverse of its covariance)."""
        self._started()
        return self._weights[2].copy()

    def reset(self, x0: np.ndarray, P0: np.ndarray | None = None) -> None:
        """Start over from the prior ``x0 (nx,)``, the first arrival ``xbar``.

        ``P0 (nx, nx)``, if given, is the covariance of that prior: the arrival weight becomes
        ``inv(P0)`` for the whole run (otherwise the settings' arrival covariance).
        """
        x0 = validation.vector("MHE.reset: x0", x0, self.model.nx)
        Q, R, P = self.settings.weights()
        Q_cov, R_cov, P_cov = self.settings.covariances()
        if P0 is not None:
            P, P_cov = arrival_weight_from_covariance(P0, self.model.nx), np.array(P0, dtype=float)
        self._weights, self._P_cov, self._R_cov = (Q, R, P), P_cov, R_cov
        self._now = Window.empty(self.layout, x0)
        self._window, self._count = np.tile(x0, (self.layout.horizon + 1, 1)), 0
        self._gate = GateState(self.settings.gate, self.model.ny)  # settings as of this reset
        self._restart = False
        self.rejections = 0

    def set_noise(self, Q: np.ndarray | None = None, R: np.ndarray | None = None,
                  P_arrival: np.ndarray | None = None) -> None:
        """New covariances (None keeps one) from the next step on: process ``Q``, measurement
        ``R`` and the arrival cost's ``P_arrival``; the window, its solution and the gate stay
        (the C ``set_noise`` and ``set_arrival``)."""
        self._started()
        weights = list(self._weights)
        if Q is not None:
            weights[0] = arrival_weight_from_covariance(Q, self.model.nx, "MHE.set_noise: Q")
        if R is not None:
            weights[1] = arrival_weight_from_covariance(R, self.model.ny, "MHE.set_noise: R")
        if P_arrival is not None:
            weights[2] = arrival_weight_from_covariance(P_arrival, self.model.nx,
                                                        "MHE.set_noise: P_arrival")
            self._P_cov = np.array(P_arrival, dtype=float)
        if R is not None:
            self._R_cov = np.array(R, dtype=float)
        self._weights = tuple(weights)

    def step(self, u: np.ndarray, y: np.ndarray, valid=None) -> np.ndarray:
        """Take the sample ``y (ny,)`` with ``u (nu,)``, the input applied since the previous one.

        NaN in ``y`` is a missing output, or ``valid (ny,)`` says which outputs ``y`` holds; a
        missing output contributes nothing (its weight in the window is 0). The first step after
        :meth:`reset` takes sample 0: there is no transition and ``u`` only enters ``h``.
        Returns the estimate ``x (nx,)``.
        """
        self._started()
        u = validation.vector("MHE.step: u", u, self.model.nu)
        y, mask = validation.measurements("MHE.step: y", y, valid, self.model.ny)
        if y.shape != (self.model.ny,):
            raise ShapeError(f"MHE.step: y: expected shape ({self.model.ny},), got {y.shape}")
        valid = np.ones(self.model.ny, dtype=bool) if mask is None else mask
        window, guess, rejected = self._advance(u, y, valid)
        p = window.parameters(self.layout, *self._weights)
        try:
            solution = self.problem.solver(x0=guess.ravel(), p=p)
        except RuntimeError as exc:  # error_on_fail: nlpsol raises when Ipopt did not succeed
            self._restart = True  # the same window would fail again: restart it next step
            status = self.problem.solver.stats().get("return_status", "unknown")
            raise SolverError(f"MHE.step (sample {self._count}): Ipopt returned {status}") from exc
        self.iterations = int(self.problem.solver.stats()["iter_count"])
        self._now, self._window = window, np.asarray(solution["x"]).reshape(self.layout.horizon + 1, -1)
        self._count += 1
        self._gate.record(rejected, valid)
        self._restart = False
        self.rejections += int(rejected.sum())
        return self.x

    def predict(self, u: np.ndarray) -> np.ndarray:
        """A sample without measurement: ``step(u, y, valid=all False)``."""
        return self.step(u, np.zeros(self.model.ny), np.zeros(self.model.ny, dtype=bool))

    def run(self, U: np.ndarray, Y: np.ndarray, x0: np.ndarray,
            P0: np.ndarray | None = None, valid=None) -> np.ndarray:
        """Estimate a whole run: ``U (T, nu)``, ``Y (T, ny)`` (``valid (T, ny)`` or None) ->
        ``X_hat (T, nx)``. Sample ``k`` is ``step(U[max(k-1, 0)], Y[k])``: sample 0 uses ``U[0]``
        only in ``h``, and ``U[T-1]`` is not used.
        """
        Y, mask = validation.measurements("MHE.run", Y, valid, self.model.ny)
        U, Y = validation.run_arrays("MHE.run", U, Y, self.model.nu, self.model.ny)
        self.reset(x0, P0)
        X_hat = np.empty((len(Y), self.model.nx))
        for k in range(len(Y)):
            X_hat[k] = self.step(U[max(k - 1, 0)], Y[k], None if mask is None else mask[k])
        return X_hat

    def _advance(self, u: np.ndarray, y: np.ndarray, valid: np.ndarray):
        """The window, warm start and rejected outputs of the next sample (the C kit's
        ``learnest_mhe_advance`` and ``learnest_mhe_gate``, line by line)."""
        has_previous = self._count > 0
        window, guess = self._now.copy(), self._window.copy()
        if has_previous:
            window.shift(self._window)
            guess[:-1] = guess[1:]
            guess[-1] = self.model.step(self._window[-1], u)
        window.open(u)
        rho = self._gate.inflation
        h, C = (np.asarray(v) for v in self._meas(guess[-1], u))
        h = h.ravel()
        S = rho * np.einsum("ij,jk,ik->i", C, self._P_cov, C) + np.diag(self._R_cov)
        innovation = np.where(valid, y - h, 0.0)
        with np.errstate(over="ignore"):  # an absurd y gives d2 = inf: rejected
            rejected = self._gate.test(innovation ** 2 / S, valid)
        keep = valid & ~rejected
        if has_previous and (self._restart or self._gate.ends_episode(rejected, valid)):
            xbar = restart_prior(guess[-1], C, rho * self._P_cov, self._R_cov, innovation, ~keep)
            window = Window.empty(self.layout, xbar)
            window.open(u)
            guess = np.tile(xbar, (self.layout.horizon + 1, 1))
            keep = np.zeros_like(keep)  # the sample is in the prior
        window.weigh(y, keep)
        return window, guess, rejected

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


def arrival_weight_from_covariance(P0: np.ndarray, nx: int, where: str = "MHE.reset: P0") -> np.ndarray:
    """``inv(P0)`` for a symmetric positive-definite ``P0 (nx, nx)``, with clear errors."""
    P0 = validation.covariance(where, P0, nx, definite=True)
    L = np.linalg.cholesky(P0)
    L_inv = np.linalg.inv(L)
    return L_inv.T @ L_inv
