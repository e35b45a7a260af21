"""The exact Kalman filter and RTS smoother of a linear prior (``linear_rts``, the quadrotor's)."""

from __future__ import annotations

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy.linalg import expm

from ..data import Run
from ..systems import System
from .base import JERK_GRID, Observations

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

    Raises ``ValueError`` when ``f`` or ``h`` is not linear in ``x`` or depends on ``u``.
    """
    A, C = _linear_prior(system)
    R = np.diag(np.square(system.noise.measurement_std))
    rows = [system.state_names.index(n) for n in system.residual_state_names]
    q = dict.fromkeys(rows, float(np.sqrt(grid[0] * grid[-1])))
    for i in rows:
        q[i] = max(grid, key=lambda v: _linear_kf(run, A, C, R, {**q, i: float(v)})[2])
    means, covs, loglik, kf = _linear_kf(run, A, C, R, q)
    means, covs, _, _ = kf.rts_smoother(means[:, :, None], covs)
    info = {"spectral_density": {system.state_names[i]: float(v) for i, v in q.items()},
            "loglik": float(loglik)}
    return Observations(means[:, :, 0], np.diagonal(covs, axis1=1, axis2=2).copy(), "linear_rts", info)


def _linear_prior(system: System) -> tuple[np.ndarray, np.ndarray]:
    """``(A, C)`` of a prior ``f = A x``, ``h = C x``; ``ValueError`` if it is not of that form."""
    import casadi as cs

    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    out = []
    for what, expr in (("dynamics", system.f(x, u)), ("measurement", system.h(x, u))):
        J = cs.jacobian(expr, x)
        offset = cs.substitute(expr, x, cs.DM.zeros(system.nx))
        nonlinear = cs.depends_on(J, cs.vertcat(x, u)) or cs.depends_on(expr, u)
        if nonlinear or np.any(np.array(cs.DM(cs.evalf(offset))) != 0):
            raise ValueError(f"system {system.name!r}: observer 'linear_rts' needs a prior {what} "
                             "of the form M x (linear in x, no input, no offset); use 'ekf_rts'")
        out.append(np.array(cs.DM(cs.evalf(J))))
    return out[0], out[1]


def _linear_kf(run: Run, A: np.ndarray, C: np.ndarray, R: np.ndarray, q: dict[int, float]):
    """Forward KF with white noise ``q[i]`` on ``xdot_i``; returns means, covs, log-lik, filter."""
    n = len(A)
    van_loan = np.zeros((2 * n, 2 * n))  # exact discrete (F, Q) of dx = A x dt + dW
    van_loan[:n, :n], van_loan[n:, n:] = -A, A.T
    van_loan[list(q), [n + i for i in q]] = list(q.values())
    E = expm(van_loan * run.dt)
    kf = KalmanFilter(dim_x=n, dim_z=len(C))
    kf.F = E[n:, n:].T
    Q = kf.F @ E[:n, n:]
    kf.Q = 0.5 * (Q + Q.T)
    kf.H, kf.R = C, R
    kf.x, kf.P = np.zeros((n, 1)), np.eye(n) * 1e4
    means, covs, means_p, covs_p = kf.batch_filter(run.y[:, :, None])
    innov = run.y - np.einsum("ij,tj->ti", C, means_p[:, :, 0])
    S = np.einsum("ij,tjk,lk->til", C, covs_p, C) + R
    sl = slice(LINEAR_BURN_IN, None)
    white = np.linalg.solve(S[sl], innov[sl, :, None])[..., 0]
    loglik = -0.5 * float(np.sum(np.einsum("ti,ti->t", innov[sl], white)
                                 + np.linalg.slogdet(2 * np.pi * S[sl])[1]))
    return means[:, :, 0], covs, loglik, kf
