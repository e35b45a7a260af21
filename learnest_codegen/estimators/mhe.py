"""Moving horizon estimator (paper section IV-A, eq. (2)) solved by CasADi nlpsol + Ipopt.

This is the reference the compiled MHEs (``codegen/mhe.py``, ``codegen/mhe_gn.py``) are
tested against; its window (:mod:`.mhe_window`) and :meth:`MHE._advance` are the C kit's
``learnest_window.h`` and ``learnest_mhe.h`` line by line, so a change here must be made there
too (``tests/test_ckit.py`` compares them).

Per sample: the window moves by one stage; the arrival prior becomes the previous solution's
estimate of the new first state (``xbar_{k-N|k} <- xhat*_{k-N|k-1}``) once the window is full
(until then, the arrival term stays on sample 0 with ``xbar = x0``); Ipopt is warm-started from the
previous solution shifted by one stage, its new last state predicted by ``F``; the estimate is
the last window state. A step Ipopt does not solve raises :class:`SolverError` and leaves the
estimator as it was: silently keeping a poor estimate would hide the problem, and the caller
can still decide to go on.

Arrival weights. The *running* weight ``P`` (the settings', by default the inverse of the
steady-state Kalman prior covariance, or :meth:`MHE.set_noise`'s) summarises the samples that
left the window. The first prior of a window that starts empty has its own weight:
``inv(P0)`` after ``reset(x0, P0)`` (``P`` itself without ``P0``), and after a recovery restart
the inverse of the restart prior's covariance (below). Once the window is full and slides, that
covariance is carried forward (:mod:`.arrival`) until it is no larger than the running one.

Missing outputs (NaN in ``y``, or ``valid``): the output's gate weight in ``G`` is 0 for that
stage (its ``Y`` entry is stored as 0), so the rest of the stage stays in the cost; a sample
without any output keeps only its process term (a pure prediction, :meth:`MHE.predict`).
Exact for a diagonal ``R`` (the default); with a full ``R`` the remaining outputs keep their
rows of the full weight.

Inputs pass the plausibility check of :mod:`.inputs` before they enter the window.

Innovation gate (:mod:`.gate`): before a sample enters the window, each valid output's
innovation ``y_j - h_j(xpred, u)`` at the prediction ``xpred`` (the warm start's last state) is
normalised by ``S_jj = rho (C P_arr C^T)_jj + R_jj`` (``C = dh/dx`` at ``xpred``, ``P_arr`` the
arrival covariance in force -- the carried first prior's, else the running one --, ``R`` the
measurement covariance, ``rho`` the gate's inflation); a rejected or missing output gets a 0
in the window's weights ``G`` and never enters the cost while the sample is in the window.

Recovery: ``rho`` is 1 normally and multiplied by ``inflation`` at each rejecting step from the
``recover_after``-th consecutive one on, so the gate widens until the new measurements pass.
The first step that then rejects nothing (and has an output) ends the episode and restarts the
window: it is emptied, its prior ``xbar`` is the Kalman update of the prediction ``xpred ~ (.,
diag(min(rho P_arr_ii, cap P_run_ii)))`` by the sample (:func:`restart_prior`; ``cap`` is
:data:`~.gate.MAX_INFLATION`, ``P_run`` the running arrival covariance), the sample itself is
folded into that prior (gate weight 0), and the prior's weight is the inverse of that update's
covariance, its variances capped at :attr:`MHE.ceiling` (:data:`~.arrival.ARRIVAL_CEILING`
times the running ones), until the window is full again. A lost estimate (:mod:`.gate`) re-
seeds the same way from the variances ``cap P_run_ii`` with every valid output of the sample,
and a carried arrival covariance keeps its variances below the ceiling. A lost track means the
whole state is in doubt: with the running weight instead, states the outputs do not see (the
cartpole's rates after a few samples of a wrong input) stayed pinned to their wrong values,
each restart was followed by new rejections, and the MHE rejected 73 % of the clean samples for
good (measured, ``docs/reports/reliability.md``). ``rho`` then shrinks by ``inflation`` per
step without rejection, so the gate stays wide while the window re-learns (resetting ``rho`` to
1 at the restart made a wrap of the whole cartpole state lose the track again for 1,500
samples). A step the solver fails on also restarts the window at the next step (the estimate
stays as it was; the prior is updated by the outputs the gate keeps), so a window the solver
cannot solve is not retried forever.

Why a restart and not a relaxed arrival weight on the old window: a window
that keeps its old samples must explain a real jump by one huge process-noise step, and an
arrival weight ``P / rho`` with ``rho ~ 1e5`` makes the Gauss-Newton normal equations so
ill-conditioned that its absolute step tolerance is never met; both locked the embedded MHE
with MAX_ITERATIONS after a 45 rad jump of the measured cartpole angle (measured).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError, SolverError
from ..export import DiscreteModel
from . import arrival, validation
from .gate import MAX_INFLATION, GateReport, GateState, cap_variances
from .inputs import InputCheck
from .mhe_problem import MHESettings, ParamLayout, build_problem, measurement_function, mhe_settings
from .mhe_window import Window

NO_COVARIANCE = ("MHE has no state covariance: it solves a least-squares problem per sample and "
                 "propagates no P. The arrival-cost weight is `arrival_weight`.")


@dataclass
class _Next:
    """What one step changes, committed only when the solve succeeds."""

    window: Window
    guess: np.ndarray
    rejected: np.ndarray
    observed: np.ndarray
    u: np.ndarray
    u_rejected: np.ndarray
    P: np.ndarray  # the arrival weight in force
    arrival_cov: np.ndarray | None  # covariance of the first prior in force; None: the running one


class MHE(GateReport):
    """Moving horizon estimator over any :class:`DiscreteModel` (reference implementation).

    Parameters
    ----------
    model : the discrete model ``x+ = F(x, u)``, ``y = h(x, u)`` (nominal, true or KNODE).
    settings : horizon and weights; default ``MHESettings.from_system(model.system)``; the
        steady-state arrival covariance of ``model`` is filled in (:func:`mhe_settings`).

    Attributes
    ----------
    x : (nx,) current estimate, the last window state.
    window : (N+1, nx) current window solution, oldest first.
    iterations : Ipopt iterations of the last step.
    rejected : (ny,) bool, the outputs the gate rejected in the last step.
    missing : (ny,) bool, the outputs the last step had no sample of.
    input_rejected : (nu,) bool, the input components the last step replaced (:mod:`.inputs`).
    last_status : status bits of the last step (0 OK, 1 output rejected, 2 input replaced).
    rejections, input_rejections : outputs / input components rejected since :meth:`reset`.
    """

    def __init__(self, model: DiscreteModel, settings: MHESettings | None = None):
        self.model = model
        self.settings = mhe_settings(model, settings)
        self.problem = build_problem(model, self.settings, f"{model.system.name}_{model.kind}_mhe")
        self.layout: ParamLayout = self.problem.layout
        self.iterations = 0
        self.rejections = 0
        self._gate = GateState(self.settings.gate, model.ny)
        self._inputs = InputCheck(self.settings.input_limits, model.nu)
        self._missing = np.zeros(model.ny, dtype=bool)
        self._meas = measurement_function(model, "meas")
        self._bounds = self.settings.bounds(model.nx)  # the box of every window state
        n = self.layout.horizon + 1
        self._box = ({} if self.settings.state_bounds is None else
                     {"lbx": np.tile(self._bounds[0], n), "ubx": np.tile(self._bounds[1], n)})
        self._jac = arrival.transition_jacobian(model)
        self._weights: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # Q, R, P in force
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
        """(nx, nx) the weight of the arrival cost in force: the running weight, or the inverse
        of a first prior's covariance carried forward (:mod:`.arrival`) after ``reset(x0, P0)``
        or a restart."""
        self._started()
        return self._weights[2].copy()

    def reset(self, x0: np.ndarray, P0: np.ndarray | None = None) -> None:
        """Start over from the prior ``x0 (nx,)``, the first arrival ``xbar``.

        ``P0 (nx, nx)``, if given, is the covariance of that prior: its inverse weighs the
        arrival, and, when it is larger than the running arrival covariance, once the window
        slides it is carried forward until it is no larger (:mod:`.arrival`); it is also the
        gate's covariance meanwhile. Without ``P0`` the running weight applies from the start.
        ``Q``, ``R`` and the running weight go back to the settings' (undoing :meth:`set_noise`).
        """
        x0 = validation.vector("MHE.reset: x0", x0, self.model.nx)
        Q, R, P = self.settings.weights()
        P_first = P if P0 is None else arrival_weight_from_covariance(P0, self.model.nx)
        carried = P0 is not None and not arrival.settled(np.asarray(P0, dtype=float), P)
        first = np.linalg.inv(P) if P0 is None else np.asarray(P0, dtype=float)
        self._arrival_cov = first.copy() if carried or self.settings.arrival_update else None
        self._weights = (Q, R, P_first)
        self._P_run, self._P_run_cov = P, np.linalg.inv(P)
        self._R_cov = np.linalg.inv(R)
        self._now = Window.empty(self.layout, x0)
        self._window, self._count = np.tile(x0, (self.layout.horizon + 1, 1)), 0
        self._gate = GateState(self.settings.gate, self.model.ny)  # settings as of this reset
        self._inputs = InputCheck(self.settings.input_limits, self.model.nu)
        self._missing = np.zeros(self.model.ny, dtype=bool)
        self._restart = False
        self.rejections = 0

    def set_noise(self, Q=None, R=None, P_arrival=None) -> None:
        """Change the weights of the running estimator; its window, estimate and gate are kept
        (the C ``set_noise`` and ``set_arrival``).

        ``Q (nx, nx)`` and ``R (ny, ny)`` are the process- and measurement-noise covariances
        (the weights become their inverses, for every stage of the window from the next step
        on, and ``R`` also sets the gate's); ``P_arrival (nx, nx)`` is the running arrival
        covariance (in force from the next step, or, while a first prior's covariance is being
        carried forward, once that has settled below it). All must be symmetric positive
        definite. The next :meth:`reset` returns to the settings' values.
        """
        self._started()
        nx, ny = self.model.nx, self.model.ny
        weights = {name: None if cov is None else
                   arrival_weight_from_covariance(cov, n, where=f"MHE.set_noise: {name}")
                   for name, cov, n in (("Q", Q, nx), ("R", R, ny), ("P_arrival", P_arrival, nx))}
        Qw, Rw, Pw = self._weights
        if weights["Q"] is not None:
            Qw = weights["Q"]
        if weights["R"] is not None:
            Rw, self._R_cov = weights["R"], np.linalg.inv(weights["R"])
        if weights["P_arrival"] is not None:
            self._P_run, self._P_run_cov = weights["P_arrival"], np.linalg.inv(weights["P_arrival"])
            if self._arrival_cov is None:
                Pw = self._P_run
        self._weights = (Qw, Rw, Pw)

    def step(self, u: np.ndarray, y: np.ndarray, valid=None) -> np.ndarray:
        """Take the sample ``y (ny,)`` with ``u (nu,)``, the input applied since the previous one.

        NaN in ``y`` is a missing output, or ``valid (ny,)`` says which outputs ``y`` holds; a
        missing output contributes nothing (its weight in the window is 0). The first step after
        :meth:`reset` takes sample 0: there is no transition and ``u`` only enters ``h``.
        Returns the estimate ``x (nx,)``.
        """
        self._started()
        u = validation.input_vector("MHE.step: u", u, self.model.nu)
        y, mask = validation.measurements("MHE.step: y", y, valid, self.model.ny)
        if y.shape != (self.model.ny,):
            raise ShapeError(f"MHE.step: y: expected shape ({self.model.ny},), got {y.shape}")
        observed = np.ones(self.model.ny, dtype=bool) if mask is None else mask
        try:
            with np.errstate(over="ignore", invalid="ignore"):
                nxt = self._advance(u, y, observed)
        except (np.linalg.LinAlgError, SolverError) as exc:  # the bookkeeping of an absurd state
            self._restart = True
            raise SolverError(f"MHE.step (sample {self._count}): {exc} (estimator left as it "
                              "was; the window restarts at the next step)") from exc
        p = nxt.window.parameters(self.layout, self._weights[0], self._weights[1], nxt.P)
        try:
            solution = self.problem.solver(x0=nxt.guess.ravel(), p=p, **self._box)
        except RuntimeError as exc:  # error_on_fail: nlpsol raises when Ipopt did not succeed
            self._restart = True  # the same window would fail again: restart it next step
            status = self.problem.solver.stats().get("return_status", "unknown")
            raise SolverError(f"MHE.step (sample {self._count}): Ipopt returned {status}") from exc
        self.iterations = int(self.problem.solver.stats()["iter_count"])
        X = np.asarray(solution["x"]).reshape(self.layout.horizon + 1, -1)
        self._commit(nxt, np.clip(X, *self._bounds))  # an interior point's last 1e-12 (learnest_box_clamp)
        return self.x

    def predict(self, u: np.ndarray) -> np.ndarray:
        """A sample without any measurement: ``step(u, y)`` with every output missing."""
        return self.step(u, np.full(self.model.ny, np.nan))

    def run(self, U: np.ndarray, Y: np.ndarray, x0: np.ndarray,
            P0: np.ndarray | None = None, valid=None) -> np.ndarray:
        """Estimate a whole run: ``U (T, nu)``, ``Y (T, ny)`` (NaN: missing; or ``valid (T, ny)``)
        -> ``X_hat (T, nx)``. Sample ``k`` is ``step(U[max(k-1, 0)], Y[k])``: sample 0 uses ``U[0]``
        only in ``h``, and ``U[T-1]`` is not used.
        """
        Y, mask = validation.measurements("MHE.run", Y, valid, self.model.ny)
        U, Y = validation.run_arrays("MHE.run", U, Y, self.model.nu, self.model.ny, missing=True)
        self.reset(x0, P0)
        X_hat = np.empty((len(Y), self.model.nx))
        for k in range(len(Y)):
            X_hat[k] = self.step(U[max(k - 1, 0)], Y[k], None if mask is None else mask[k])
        return X_hat

    def _advance(self, u: np.ndarray, y: np.ndarray, valid: np.ndarray) -> _Next:
        """The window, warm start, gate masks, input and arrival of the next sample (the C kit's
        ``learnest_mhe_advance`` and ``learnest_mhe_gate``, line by line)."""
        has_previous = self._count > 0
        window, guess = self._now.copy(), self._window.copy()
        u, u_rejected = self._inputs.apply(u)
        arrival_cov, P = self._arrival_cov, self._weights[2]
        if has_previous:
            if window.mask[0] == 1.0:  # the window was full: the arrival moves on
                arrival_cov = self._carried(window, arrival_cov)
                P = self._P_run if arrival_cov is None else _inverse(arrival_cov)
            window.shift(self._window)
            guess[:-1] = guess[1:]
            guess[-1] = self.model.step(self._window[-1], u)
        guess = np.clip(guess, *self._bounds)  # the warm start inside the box (learnest_box_clamp)
        window.open(u)
        rho = self._gate.inflation
        h, C = (np.asarray(v) for v in self._meas(guess[-1], u))
        h = h.ravel()
        cov = self._P_run_cov if arrival_cov is None else arrival_cov
        S = rho * np.einsum("ij,jk,ik->i", C, cov, C) + np.diag(self._R_cov)
        innovation = np.where(valid, y - h, 0.0)
        rejected = self._gate.test(innovation ** 2 / S, valid)  # absurd y: d2 = inf, rejected
        reseed = has_previous and self._gate.reseeds(rejected)
        if reseed:  # lost: every valid output, from the ceiling's variances
            rejected = np.zeros_like(rejected)
        keep = valid & ~rejected
        if has_previous and (self._restart or reseed or self._gate.ends_episode(rejected, valid)):
            widest = MAX_INFLATION * np.diag(self._P_run_cov)
            pd = widest if reseed else np.minimum(rho * np.diag(cov), widest)
            xbar, arrival_cov = restart_prior(guess[-1], C, np.diag(pd), self._R_cov, innovation, ~keep)
            arrival_cov = cap_variances(arrival_cov, self.ceiling)
            P = _inverse(arrival_cov)
            window = Window.empty(self.layout, xbar)
            window.open(u)
            guess = np.clip(np.tile(xbar, (self.layout.horizon + 1, 1)), *self._bounds)
            keep = np.zeros_like(keep)  # the sample is in the prior
        window.weigh(y, keep)
        return _Next(window, guess, rejected, valid, u, u_rejected, P, arrival_cov)

    def _commit(self, nxt: _Next, X: np.ndarray) -> None:
        """The solved sample ``nxt`` with window solution ``X`` becomes the current one."""
        self._now, self._window = nxt.window, X
        self._weights = (self._weights[0], self._weights[1], nxt.P)
        self._arrival_cov = nxt.arrival_cov
        self._count += 1
        self._gate.record(nxt.rejected, nxt.observed)
        self._inputs.record(nxt.u, nxt.u_rejected)
        self._missing = ~nxt.observed
        self._restart = False
        self.rejections += int(nxt.rejected.sum())

    def _carried(self, window: Window, cov: np.ndarray | None) -> np.ndarray | None:
        """The arrival covariance of the window's second stage from that of its first (the
        one leaving), or ``None`` once it has settled below the running one (:mod:`.arrival`)."""
        if cov is None:
            return None
        x0 = self._window[0]
        _, C = self._meas(x0, window.U[0])
        A = np.asarray(self._jac(x0, window.U[1]))
        cov = arrival.propagate(cov, A, np.asarray(C), window.G[0] == 1.0,
                                _inverse(self._weights[0]), self._R_cov)
        cov = cap_variances(cov, self.ceiling)
        if self.settings.arrival_update:  # the arrival follows the data: carried on and on
            return cov
        return None if arrival.settled(cov, self._P_run) else cov

    @property
    def ceiling(self) -> np.ndarray:
        """(nx,) the largest variance a covariance that becomes the arrival weight (a restart
        prior's posterior, a carried one) may hold: :data:`~.arrival.ARRIVAL_CEILING` times the
        running arrival covariance's (the C's ``LEARNEST_ARRIVAL_CEILING``)."""
        return arrival.ARRIVAL_CEILING * np.diag(self._P_run_cov)

    def _started(self) -> np.ndarray:
        if self._window is None:
            raise RuntimeError("MHE: call reset(x0) before step() or reading the state")
        return self._window


def _inverse(M: np.ndarray) -> np.ndarray:
    """The symmetric inverse of a symmetric positive-definite matrix; :class:`SolverError` if
    it has none (a covariance carried through an absurd state)."""
    inv = np.linalg.inv(M)
    if not np.all(np.isfinite(inv)):
        raise SolverError("an arrival covariance is not invertible")
    return 0.5 * (inv + inv.T)


def restart_prior(x_pred: np.ndarray, C: np.ndarray, P: np.ndarray, R: np.ndarray,
                  innovation: np.ndarray, left_out: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The recovery's new prior and its covariance: the Kalman update of
    ``x_pred ~ (., diag(P))`` by the outputs not ``left_out`` (rejected or missing; ``C = dh/dx``,
    ``R`` the measurement covariance); ``(x_pred, diag(P))`` if none is left.

    The correlations of ``P`` are dropped: the innovation of a re-acquired track is gross, and
    through a correlation it would throw the unmeasured states (measured on the cartpole: a
    45 rad jump of the measured angle moved the angular rate by tens of rad/s and the track
    was lost again); with ``diag(P)`` only the states the outputs see move, and the others keep
    their inflated variance, so the restarted window re-learns them from its samples.
    """
    keep = ~np.asarray(left_out, dtype=bool)
    P = np.diag(np.diag(P))
    if not keep.any():
        return x_pred.copy(), P
    Ck = C[keep]
    S = Ck @ P @ Ck.T + R[np.ix_(keep, keep)]
    K = np.linalg.solve(S, Ck @ P).T
    cov = P - K @ Ck @ P
    return x_pred + K @ innovation[keep], 0.5 * (cov + cov.T)


def arrival_weight_from_covariance(P0: np.ndarray, nx: int, where: str = "MHE.reset: P0") -> np.ndarray:
    """``inv(P0)`` for a symmetric positive-definite ``P0 (nx, nx)``, with clear errors."""
    P0 = validation.covariance(where, P0, nx, definite=True)
    L = np.linalg.cholesky(P0)
    L_inv = np.linalg.inv(L)
    return L_inv.T @ L_inv
