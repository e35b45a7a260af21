"""The exact Kalman filter and RTS smoother of a linear prior (``linear_rts``, the quadrotor's)."""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from ..data import Run
from ..errors import ObserverError
from ..systems import System
from .base import JERK_GRID, Observations
from .kalman import FilterPasses, LinearGaussian, kalman_filter, rts_smoother

LINEAR_BURN_IN = 10  # first innovations left out of the likelihood (diffuse start)


def linear_rts(run: Run, system: System, grid: np.ndarray = JERK_GRID) -> Observations:
    """Kalman filter + RTS smoother of a linear prior ``xdot = A x``, ``y = C x`` (all outputs).

    White noise of spectral density ``q_i`` drives the derivative of each residual state
    (``system.residual_state_names``: where the prior is least sure, and what the residual
    will learn), discretised exactly (Van Loan); each ``q_i`` is chosen on ``grid`` by
    maximising the innovation log-likelihood, one residual state after the other. Unlike the
    per-chain ``rts`` observer, which sees only a chain's measured coordinate, this uses every
    output: for the quadrotor the accelerometer fixes the acceleration that ``rts`` can only
    get from second differences of position. The filter starts diffuse (``x = 0``, ``P = 1e4
    I``), so no ``x0`` is assumed.

    Raises :class:`~learnest_codegen.errors.ObserverError` when ``f`` or ``h`` is not linear in
    ``x`` or depends on ``u``.
    """
    A, C = _linear_prior(system)
    R = np.diag(np.square(system.noise.measurement_std))
    rows = [system.state_names.index(n) for n in system.residual_state_names]
    grid = np.asarray(grid, float)
    q = dict.fromkeys(rows, float(np.sqrt(grid[0] * grid[-1])))
    F, units = _van_loan(A, rows, run.dt)
    for i in rows:  # the whole grid of q_i in one pass, the other intensities as chosen so far
        others = sum(q[j] * units[j] for j in rows if j != i)
        passes = _linear_passes(run, F, C, R, others + grid[:, None, None] * units[i])
        q[i] = float(grid[int(np.argmax(passes.loglik))])
    Q = sum(q[j] * units[j] for j in rows)[None]
    passes = _linear_passes(run, F, C, R, Q)
    means, covs = rts_smoother(F, passes)
    info = {"spectral_density": {system.state_names[i]: float(v) for i, v in q.items()},
            "loglik": float(passes.loglik[0])}
    return Observations(means[:, 0], np.diagonal(covs[:, 0], axis1=1, axis2=2).copy(), "linear_rts", info)


def _linear_prior(system: System) -> tuple[np.ndarray, np.ndarray]:
    """``(A, C)`` of a prior ``f = A x``, ``h = C x``; :class:`ObserverError` if it is not of that
    form."""
    import casadi as cs

    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    out = []
    for what, expr in (("dynamics", system.f(x, u)), ("measurement", system.h(x, u))):
        J = cs.jacobian(expr, x)
        offset = cs.substitute(expr, x, cs.DM.zeros(system.nx))
        nonlinear = cs.depends_on(J, cs.vertcat(x, u)) or cs.depends_on(expr, u)
        if nonlinear or np.any(np.array(cs.DM(cs.evalf(offset))) != 0):
            raise ObserverError(f"system {system.name!r}: observer 'linear_rts' needs a prior {what} "
                             "of the form M x (linear in x, no input, no offset); use 'ekf_rts'")
        out.append(np.array(cs.DM(cs.evalf(J))))
    return out[0], out[1]


def _van_loan(A: np.ndarray, rows: list[int], dt: float) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Exact discretisation of ``dx = A x dt + dW``: the transition ``F`` and, per state ``i`` of
    ``rows``, the process noise of unit white noise on ``xdot_i`` (``Q`` is linear in the
    intensities: ``Q = sum_i q_i Q_i``)."""
    n = len(A)
    units = {}
    for i in rows:
        van_loan = np.zeros((2 * n, 2 * n))
        van_loan[:n, :n], van_loan[n:, n:] = -A, A.T
        van_loan[i, n + i] = 1.0
        E = expm(van_loan * dt)
        F = E[n:, n:].T
        Q = F @ E[:n, n:]
        units[i] = 0.5 * (Q + Q.T)
    if not rows:
        F = expm(A * dt)
    return F, units


def _linear_passes(run: Run, F: np.ndarray, C: np.ndarray, R: np.ndarray, Q: np.ndarray) -> FilterPasses:
    """Kalman filters of ``(F, Q[b], C, R)`` over the run, one per member of ``Q (B, n, n)``,
    from a diffuse start (``x = 0``, ``P = 1e4 I``)."""
    B, n = len(Q), len(F)
    return kalman_filter(F, C, Q, R, run.y, np.zeros((B, n)), np.broadcast_to(np.eye(n) * 1e4, (B, n, n)),
                         burn_in=LINEAR_BURN_IN)


def _linear_kf(run: Run, A: np.ndarray, C: np.ndarray, R: np.ndarray, q: dict[int, float]):
    """Forward KF with white noise ``q[i]`` on ``xdot_i``; returns means, covs, log-lik and the
    discrete model (:class:`~.kalman.LinearGaussian`)."""
    F, units = _van_loan(A, list(q), run.dt)
    Q = sum(v * units[i] for i, v in q.items())
    passes = _linear_passes(run, F, C, R, Q[None])
    return passes.means[:, 0], passes.covs[:, 0], float(passes.loglik[0]), LinearGaussian(F, Q, C, R)
