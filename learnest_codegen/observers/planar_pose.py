"""The paper's two-stage observer for a planar vehicle (``ukf_kf``, ``ukf_rts``): a kinematic
UKF for the pose, then a linear KF for the speed."""

from __future__ import annotations

import numpy as np
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.linalg import expm

from ..data import Run
from ..systems import System
from .base import JERK_GRID, Observations

#
# Stage 1 is a UKF on a kinematic model in the world frame, state ``[x, y, vx, vy, psi, r]``: the
# position with a white-acceleration (random-walk) velocity and the heading with a random-walk
# turn rate ``r``. It measures through the system's own ``h`` (the state it hands to ``h`` has
# the speed ``|(vx, vy)|``), so it knows the sensors but nothing of the dynamics: no input and
# no drag, hence no prior model error, enters the training targets. Its two intensities are
# chosen by maximising the innovation log-likelihood, one coordinate at a time over a log grid.
# Stage 2 extracts the speed from the stage-1 positions: one constant-acceleration (white-jerk)
# linear KF per axis, jerk intensity (shared by both axes: the motion has no preferred world
# direction) again by maximum innovation likelihood. Its measurement variance is that of a
# single-sample position fix from the sensors, ``inv(J' R^-1 J)`` with ``J = dh/d(x, y)`` at the
# stage-1 estimate, not the stage-1 filter variance: the stage-1 errors are correlated in time,
# and treating them as white with their (small) filter variance overstates what each sample
# says, which makes the likelihood pick a far too large jerk intensity (on seed 1 of the ground
# robot: speed MSE 3e-3 instead of 3e-4 after smoothing). The speed is the norm of the (vx, vy)
# estimate, which is the bicycle's speed whatever the slip angle (the projection on the heading
# would be v cos(beta)).
ACCEL_GRID = np.logspace(-2, 3, 6)  # white-acceleration densities tried, stage 1 [m^2 / s^3]
TURN_GRID = np.logspace(-3, 2, 6)  # white angular-acceleration densities [rad^2 / s^3]
STAGE1_TUNING_SAMPLES = 1000  # the likelihood grid of stage 1 runs on the first samples only


def planar_pose_indices(system: System) -> tuple[int, int, int, int]:
    """Indices of the states ``(x, y, v, psi)`` named by ``system.planar_pose``."""
    names = system.planar_pose
    if names is None:
        raise ValueError(f"system {system.name!r} declares no planar pose: the 'ukf_kf' and "
                         "'ukf_rts' observers need planar_pose=(x, y, v, psi) "
                         "naming its position, speed and heading states")
    names = tuple(names)
    unknown = [n for n in names if n not in system.state_names]
    if len(names) != 4 or unknown:
        raise ValueError(f"system {system.name!r}: planar_pose must name 4 states "
                         f"(x, y, v, psi) among {system.state_names}, got {names}")
    if len(set(names)) != 4 or system.nx != 4:
        raise ValueError(f"system {system.name!r}: the planar-pose observers estimate exactly "
                         f"the 4 distinct states (x, y, v, psi); the system has {system.state_names}")
    return tuple(system.state_names.index(n) for n in names)


def _pose_to_state(system: System, pose: np.ndarray, indices=None) -> np.ndarray:
    """Stage-1 states ``[x, y, vx, vy, psi, r]`` ``(..., 6)`` as system states ``(..., nx)``."""
    ix, iy, iv, ipsi = indices or planar_pose_indices(system)
    x = np.empty((*pose.shape[:-1], system.nx))
    x[..., ix], x[..., iy], x[..., ipsi] = pose[..., 0], pose[..., 1], pose[..., 4]
    x[..., iv] = np.hypot(pose[..., 2], pose[..., 3])
    return x


def _pose_ukf(run: Run, system: System, q_accel: float, q_turn: float, T: int | None = None):
    """Stage-1 UKF over the first ``T`` samples; returns means, covariances, log-lik, filter."""
    ix, iy, iv, ipsi = planar_pose_indices(system)
    dt = run.dt
    block = np.array([[1.0, dt], [0.0, 1.0]])
    F = np.zeros((6, 6))
    for sl in ((0, 2), (1, 3), (4, 5)):  # (position, rate) pairs of [x, y, vx, vy, psi, r]
        F[np.ix_(sl, sl)] = block
    Q = np.zeros((6, 6))
    for sl, q in (((0, 2), q_accel), ((1, 3), q_accel), ((4, 5), q_turn)):
        Q[np.ix_(sl, sl)] = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=q)

    def to_system(s):
        return _pose_to_state(system, s, (ix, iy, iv, ipsi))

    points = MerweScaledSigmaPoints(6, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(6, system.ny, dt, hx=lambda s, u: system.h(to_system(s), u),
                                fx=lambda s, dt: F @ s, points=points)
    ukf.Q, ukf.R = Q, np.diag(np.square(system.noise.measurement_std))
    x0, std0 = np.asarray(system.x0, float), np.asarray(system.noise.initial_std, float)
    ukf.x = np.array([x0[ix], x0[iy], x0[iv] * np.cos(x0[ipsi]), x0[iv] * np.sin(x0[ipsi]),
                      x0[ipsi], 0.0])
    ukf.P = np.diag([std0[ix] ** 2, std0[iy] ** 2, std0[iv] ** 2 + 1.0, std0[iv] ** 2 + 1.0,
                     std0[ipsi] ** 2, 1.0])  # + (1 m/s)^2, (1 rad/s)^2: the direction is unknown
    T = len(run) if T is None else T
    means, covs = np.empty((T, 6)), np.empty((T, 6, 6))
    loglik = 0.0
    for k in range(T):
        if k:
            ukf.predict()
        else:  # no predict before sample 0: draw the sigma points update() transforms
            ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
        ukf.update(run.y[k], u=run.u[k])  # y[k] = h(x[k], u[k]), the simulator's convention
        loglik -= 0.5 * (ukf.y @ np.linalg.solve(ukf.S, ukf.y) + np.linalg.slogdet(2 * np.pi * ukf.S)[1])
        means[k], covs[k] = ukf.x, ukf.P
    return means, covs, loglik, ukf


def _speed_kf(pos: np.ndarray, var: np.ndarray, dt: float, q: float):
    """Stage 2: constant-acceleration KF on one position coordinate with per-sample variances."""
    kf = KalmanFilter(dim_x=3, dim_z=1)
    kf.F = expm(np.diag(np.full(2, dt), 1))
    kf.Q = Q_continuous_white_noise(dim=3, dt=dt, spectral_density=q)
    kf.H = np.eye(1, 3)
    kf.x = np.array([[pos[0]], [0.0], [0.0]])
    kf.P = np.diag([var[0], 1e4, 1e4])
    Rs = [np.array([[r]]) for r in var]
    means, covs, means_p, covs_p = kf.batch_filter(pos[:, None], Rs=Rs)
    innov = pos - means_p[:, 0, 0]
    s = covs_p[:, 0, 0] + var
    loglik = -0.5 * float(np.sum(np.log(2 * np.pi * s) + innov**2 / s))
    return means[:, :, 0], covs, loglik, kf


def _position_fix_variance(run: Run, system: System, pose: np.ndarray) -> np.ndarray:
    """(T, 2) variances of a one-sample position fix, ``diag(inv(J' R^-1 J))``, J = dh/d(x, y).

    ``pose`` holds stage-1 states ``[x, y, vx, vy, psi, r]`` at which ``J`` is evaluated.
    """
    import casadi as cs

    ix, iy, iv, ipsi = planar_pose_indices(system)
    xs, us = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    J = cs.Function("J", [xs, us], [cs.jacobian(system.h(xs, us), xs)[:, [ix, iy]]])
    X = _pose_to_state(system, pose)
    # map() stacks the (ny, 2) Jacobians side by side: (ny, 2 T), column 2 t + i.
    Js = np.asarray(J.map(len(pose))(X.T, run.u.T)).reshape(system.ny, len(pose), 2)
    Js = Js.transpose(1, 0, 2)  # (T, ny, 2)
    w = 1.0 / np.square(np.asarray(system.noise.measurement_std, float))
    info = np.einsum("tki,k,tkj->tij", Js, w, Js)
    if np.any(np.linalg.det(info) <= 1e-12 * np.einsum("tii->t", info) ** 2):
        raise ValueError(f"system {system.name!r}: the measurements do not fix the position "
                         "(x, y) at some samples; the planar-pose observers need them to")
    return np.diagonal(np.linalg.inv(info), axis1=1, axis2=2).copy()


def _two_stage(run: Run, system: System, smooth: bool) -> Observations:
    """The paper's pre-training observer for a planar robot: a UKF, then a linear KF (see above)."""
    ix, iy, iv, ipsi = planar_pose_indices(system)
    tune = dict(T=min(len(run), STAGE1_TUNING_SAMPLES))
    mid_turn = float(np.sqrt(TURN_GRID[0] * TURN_GRID[-1]))
    q_accel = max(ACCEL_GRID, key=lambda q: _pose_ukf(run, system, q, mid_turn, **tune)[2])
    q_turn = max(TURN_GRID, key=lambda q: _pose_ukf(run, system, q_accel, q, **tune)[2])
    means, covs, _, ukf = _pose_ukf(run, system, q_accel, q_turn)
    if smooth:
        means, covs, _ = ukf.rts_smoother(means, covs)
    dt = run.dt
    pos, pos_var = means[:, :2], covs[:, [0, 1], [0, 1]]
    fix_var = _position_fix_variance(run, system, means)
    q_jerk = max(JERK_GRID[::2], key=lambda q: sum(_speed_kf(pos[:, j], fix_var[:, j], dt, q)[2]
                                                       for j in range(2)))
    vel, vel_var = np.empty((len(run), 2)), np.empty((len(run), 2))
    for j in range(2):
        m, c, _, kf = _speed_kf(pos[:, j], fix_var[:, j], dt, q_jerk)
        if smooth:
            m, c, _, _ = kf.rts_smoother(m[:, :, None], c)
            m = m[:, :, 0]
        vel[:, j], vel_var[:, j] = m[:, 1], c[:, 1, 1]
    speed = np.hypot(vel[:, 0], vel[:, 1])
    speed_var = np.sum(vel**2 * vel_var, axis=1) / np.maximum(speed, 1e-9) ** 2  # delta method
    zeta, var = np.empty((len(run), system.nx)), np.empty((len(run), system.nx))
    zeta[:, ix], zeta[:, iy], zeta[:, iv], zeta[:, ipsi] = means[:, 0], means[:, 1], speed, means[:, 4]
    var[:, ix], var[:, iy], var[:, iv], var[:, ipsi] = pos_var[:, 0], pos_var[:, 1], speed_var, covs[:, 4, 4]
    info = {"accel_spectral_density": float(q_accel), "turn_spectral_density": float(q_turn),
            "jerk_spectral_density": float(q_jerk)}
    return Observations(zeta, var, "ukf_rts" if smooth else "ukf_kf", info)
