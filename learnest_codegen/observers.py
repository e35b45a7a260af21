"""Pre-training observers: measurements and inputs to state observations ``zeta`` (Alg. 1, step 1).

* ``kf``  - the paper's observer for the cartpole: one linear Kalman filter per kinematic chain
  (a measured position and its derivatives, see :class:`~learnest_codegen.systems.KinematicChain`)
  with a constant-acceleration model. It needs no dynamics model, so it does not bake the
  prior's error into the training targets.
* ``rts`` - the same filter followed by the Rauch-Tung-Striebel backward pass (a smoother: each
  ``zeta_i`` uses the whole run, not only the past), through FilterPy.
* ``ukf`` - for systems without kinematic chains: a FilterPy UKF on the RK4-discretised prior.
* ``ekf_rts`` - an extended Kalman filter on the RK4-discretised model plus an RTS backward pass.
  With the prior model its accelerations come from physics plus the data, not from a
  kinematic random walk; with a hybrid model (``residual``) it refines the training targets in
  :func:`~learnest_codegen.training.train_on_run`'s alternating scheme.

The white-jerk intensity of the kinematic filters is chosen per chain by maximising the
innovation log-likelihood over a log grid, so no tuning is needed for a new system.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.linalg import expm

from .data import Run
from .errors import UnknownNameError
from .integrators import rk4_step
from .systems import KinematicChain, System

JERK_GRID = np.logspace(-2, 8, 21)  # white-jerk spectral densities tried [unit^2 / s^5]


@dataclass(frozen=True)
class Observations:
    """State observations for training.

    Attributes
    ----------
    zeta : (T, nx) state observations.
    variance : (T, nx) their marginal variances, as the observer believes them.
    method : which observer produced them.
    info : per-observer details (e.g. the chosen jerk intensities).
    """

    zeta: np.ndarray
    variance: np.ndarray
    method: str
    info: dict


def observe(run: Run, system: System, method: str | None = None) -> Observations:
    """Turn a run's ``(y, u)`` into state observations with the named observer.

    ``method`` defaults to the system's ``default_observer``.
    """
    method = method or system.default_observer
    if method not in OBSERVERS:
        raise UnknownNameError(f"unknown observer {method!r}; choose from {sorted(OBSERVERS)}")
    return OBSERVERS[method](run, system)


def _kinematic(run: Run, system: System, smooth: bool) -> Observations:
    if not system.kinematic_chains:
        raise ValueError(f"system {system.name!r} declares no kinematic chains; use observer 'ukf'")
    T = len(run)
    zeta = np.full((T, system.nx), np.nan)
    var = np.full((T, system.nx), np.nan)
    info = {}
    for chain in system.kinematic_chains:
        means, covs, q = _fit_chain(run, system, chain, smooth)
        for j, name in enumerate(chain.states):
            i = system.state_names.index(name)
            zeta[:, i], var[:, i] = means[:, j], covs[:, j, j]
        info[chain.output] = {"jerk_spectral_density": q}
    uncovered = [n for n, col in zip(system.state_names, zeta.T) if np.isnan(col).any()]
    if uncovered:
        raise ValueError(f"system {system.name!r}: states {uncovered} are in no kinematic chain")
    return Observations(zeta, var, "rts" if smooth else "kf", info)


def _fit_chain(run: Run, system: System, chain: KinematicChain, smooth: bool):
    j = system.output_names.index(chain.output)
    z = run.y[:, j]
    r = system.noise.measurement_std[j] ** 2
    order = len(chain.states) + 1  # one derivative beyond the chain, driven by white noise
    best = max(JERK_GRID, key=lambda q: _chain_filter(z, run.dt, order, q, r)[2])
    means, covs, _, kf, fs = _chain_filter(z, run.dt, order, best, r)
    if smooth:
        means, covs, _, _ = kf.rts_smoother(means, covs, Fs=fs)
    n = len(chain.states)
    return means[:, :n, 0] if means.ndim == 3 else means[:, :n], covs[:, :n, :n], float(best)


def _chain_filter(z: np.ndarray, dt: float, order: int, q: float, r: float):
    """Constant-(order-1)-derivative KF over one measured coordinate; returns the log-likelihood."""
    kf = KalmanFilter(dim_x=order, dim_z=1)
    kf.F = expm(np.diag(np.full(order - 1, dt), 1))  # exact discretisation of an integrator chain
    kf.Q = Q_continuous_white_noise(dim=order, dt=dt, spectral_density=q) if order in (2, 3, 4) \
        else np.eye(order) * q * dt
    kf.H = np.eye(1, order)
    kf.R = np.array([[r]])
    kf.x = np.zeros((order, 1))
    kf.x[0, 0] = z[0]
    kf.P = np.diag([r] + [1e4] * (order - 1))
    means, covs, means_p, covs_p = kf.batch_filter(z[:, None])
    innov = z - means_p[:, 0, 0]
    s = covs_p[:, 0, 0] + r
    loglik = -0.5 * float(np.sum(np.log(2 * np.pi * s) + innov**2 / s))
    return means, covs, loglik, kf, [kf.F] * len(z)


def _model_ukf(run: Run, system: System) -> Observations:
    """Forward UKF on the RK4-discretised prior (for systems without kinematic chains)."""
    step: Callable = lambda x, dt, u: rk4_step(lambda s, v: system.f(s, v), x, u, dt)  # noqa: E731
    points = MerweScaledSigmaPoints(system.nx, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(system.nx, system.ny, run.dt, lambda x: x, step, points)
    ukf.hx = lambda x, u: system.h(x, u)
    ukf.x = np.array(system.x0, dtype=float)
    ukf.P = np.diag(np.square(system.noise.initial_std))
    ukf.Q = np.diag(np.square(system.noise.process_std))
    ukf.R = np.diag(np.square(system.noise.measurement_std))
    zeta, var = np.empty((len(run), system.nx)), np.empty((len(run), system.nx))
    for k in range(len(run)):
        if k:
            ukf.predict(dt=run.t[k] - run.t[k - 1], u=run.u[k - 1])
        ukf.update(run.y[k], u=run.u[k - 1] if k else run.u[0])  # same convention as estimators
        zeta[k], var[k] = ukf.x, np.diag(ukf.P)
    return Observations(zeta, var, "ukf", {})


def ekf_rts(run: Run, system: System, residual: Callable | None = None,
            q_scales: np.ndarray = np.logspace(-1, 3, 9)) -> Observations:
    """EKF + RTS smoother through ``RK4(f_prior + residual)``; Q's scale chosen by likelihood.

    ``residual(x_sx, u_sx) -> SX`` adds a learned term (a net's CasADi form) to the prior.
    """
    F, A = _discrete_with_jacobian(system, residual, run.dt)
    R = np.diag(np.square(system.noise.measurement_std))
    q0 = np.square(system.noise.process_std)
    x0 = run.x[0] if run.x is not None else np.asarray(system.x0, float)
    passes = {float(s): _ekf_forward(run, system, F, A, np.diag(q0 * s), R, x0) for s in q_scales}
    scale = max(passes, key=lambda s: passes[s][-1])
    xs, Ps, xps, Pps, _ = passes[scale]
    zeta, covs = _rts_backward(xs, Ps, xps, Pps, A, run.u)
    return Observations(zeta, np.diagonal(covs, axis1=1, axis2=2).copy(), "ekf_rts",
                        {"q_scale": scale, "refined": residual is not None})


def _discrete_with_jacobian(system: System, residual, dt: float):
    import casadi as cs

    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    f = lambda s, v: system.f(s, v) + (residual(s, v) if residual else 0)  # noqa: E731
    xn = rk4_step(f, x, u, dt)
    F = cs.Function("F", [x, u], [xn])
    A = cs.Function("A", [x, u], [cs.jacobian(xn, x)])
    return F, A


def _ekf_forward(run: Run, system: System, F, A, Q, R, x0):
    """Forward EKF; the measurement is linearised by CasADi too. Returns the log-likelihood."""
    import casadi as cs

    xs_sym, us_sym = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    H = cs.Function("H", [xs_sym, us_sym], [cs.jacobian(system.h(xs_sym, us_sym), xs_sym)])
    T, n = len(run), system.nx
    xs, Ps, xps, Pps = (np.empty((T, n)), np.empty((T, n, n)), np.empty((T, n)), np.empty((T, n, n)))
    x, P = np.asarray(x0, float), np.diag(np.square(system.noise.initial_std))
    loglik = 0.0
    for k in range(T):
        if k:
            Ak = A(x, run.u[k - 1]).full()
            x, P = F(x, run.u[k - 1]).full().ravel(), Ak @ P @ Ak.T + Q
        xps[k], Pps[k] = x, P
        Hk = H(x, run.u[k]).full()
        innov = run.y[k] - system.h(x, run.u[k])
        S = Hk @ P @ Hk.T + R
        K = np.linalg.solve(S, Hk @ P).T
        x, P = x + K @ innov, (np.eye(n) - K @ Hk) @ P
        loglik -= 0.5 * (innov @ np.linalg.solve(S, innov) + np.linalg.slogdet(2 * np.pi * S)[1])
        xs[k], Ps[k] = x, P
    return xs, Ps, xps, Pps, loglik


def _rts_backward(xs, Ps, xps, Pps, A, U):
    """Rauch-Tung-Striebel pass over an extended Kalman filter's estimates."""
    zeta, covs = xs.copy(), Ps.copy()
    for k in range(len(xs) - 2, -1, -1):
        Ak = A(xs[k], U[k]).full()
        G = np.linalg.solve(Pps[k + 1], Ak @ Ps[k]).T
        zeta[k] = xs[k] + G @ (zeta[k + 1] - xps[k + 1])
        covs[k] = Ps[k] + G @ (covs[k + 1] - Pps[k + 1]) @ G.T
    return zeta, covs


OBSERVERS: dict[str, Callable[[Run, System], Observations]] = {
    "kf": lambda run, system: _kinematic(run, system, smooth=False),
    "rts": lambda run, system: _kinematic(run, system, smooth=True),
    "ukf": _model_ukf,
    "ekf_rts": lambda run, system: ekf_rts(run, system),
}
