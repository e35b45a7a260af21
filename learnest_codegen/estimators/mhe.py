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
"""

from __future__ import annotations

import numpy as np

from ..errors import SolverError
from ..export import DiscreteModel
from . import validation
from .mhe_problem import MHESettings, ParamLayout, build_problem

NO_COVARIANCE = ("MHE has no state covariance: it solves a least-squares problem per sample and "
                 "propagates no P. The arrival-cost weight is `arrival_weight`.")


class MHE:
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
    """

    def __init__(self, model: DiscreteModel, settings: MHESettings | None = None):
        self.model = model
        self.settings = settings or MHESettings.from_system(model.system)
        self.problem = build_problem(model, self.settings, f"{model.system.name}_{model.kind}_mhe")
        self.layout: ParamLayout = self.problem.layout
        self.iterations = 0
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
        """(nx, nx) the weight ``P`` of the arrival cost in use."""
        self._started()
        return self._p[self.layout.slice("P")].reshape(self.model.nx, self.model.nx).T.copy()

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

    def step(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Take the sample ``y (ny,)`` with ``u (nu,)``, the input applied since the previous one.

        The first step after :meth:`reset` takes sample 0: there is no transition and ``u``
        only enters ``h``. Returns the estimate ``x (nx,)``.
        """
        self._started()
        u = validation.vector("MHE.step: u", u, self.model.nu)
        y = validation.vector("MHE.step: y", y, self.model.ny)
        p, guess = self._advance(u, y)
        try:
            solution = self.problem.solver(x0=guess.ravel(), p=p)
        except RuntimeError as exc:  # error_on_fail: nlpsol raises when Ipopt did not succeed
            status = self.problem.solver.stats().get("return_status", "unknown")
            raise SolverError(f"MHE.step (sample {self._count}): Ipopt returned {status}") from exc
        self.iterations = int(self.problem.solver.stats()["iter_count"])
        self._p, self._window = p, np.asarray(solution["x"]).reshape(self.layout.horizon + 1, -1)
        self._count += 1
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

    def _advance(self, u: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Parameters and warm start for the next sample (mirrored by ``<prefix>_step`` in C)."""
        lay = self.layout
        p, guess = self._p.copy(), self._window.copy()
        U, Y = p[lay.slice("U")].reshape(-1, lay.nu), p[lay.slice("Y")].reshape(-1, lay.ny)
        mask = p[lay.slice("mask")]
        if self._count > 0:
            if mask[0] == 1.0:  # window was full: the arrival moves on to the next sample
                p[lay.slice("xbar")] = self._window[1]
            for block in (U, Y, mask, guess):
                block[:-1] = block[1:]
            guess[-1] = self.model.step(self._window[-1], u)
        U[-1], Y[-1], mask[-1] = u, y, 1.0
        return p, guess

    def _started(self) -> np.ndarray:
        if self._window is None:
            raise RuntimeError("MHE: call reset(x0) before step() or reading the state")
        return self._window


def arrival_weight_from_covariance(P0: np.ndarray, nx: int) -> np.ndarray:
    """``inv(P0)`` for a symmetric positive-definite ``P0 (nx, nx)``, with clear errors."""
    P0 = validation.covariance("MHE.reset: P0", P0, nx, definite=True)
    L = np.linalg.cholesky(P0)
    L_inv = np.linalg.inv(L)
    return L_inv.T @ L_inv
