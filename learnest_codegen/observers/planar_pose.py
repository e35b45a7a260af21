"""The paper's two-stage observer for a planar vehicle (``ukf_kf``, ``ukf_rts``): a kinematic
UKF for the pose, then a linear KF for the speed."""

from __future__ import annotations

import numpy as np

from ..data import Run
from ..errors import ObserverError
from ..systems import System
from .base import JERK_GRID, Observations
from .kalman import FilterPasses, integrator_chain, kalman_filter, rts_smoother

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
        raise ObserverError(f"system {system.name!r} declares no planar pose: the 'ukf_kf' and "
                         "'ukf_rts' observers need planar_pose=(x, y, v, psi) "
                         "naming its position, speed and heading states")
    names = tuple(names)
    unknown = [n for n in names if n not in system.state_names]
    if len(names) != 4 or unknown:
        raise ObserverError(f"system {system.name!r}: planar_pose must name 4 states "
                         f"(x, y, v, psi) among {system.state_names}, got {names}")
    if len(set(names)) != 4 or system.nx != 4:
        raise ObserverError(f"system {system.name!r}: the planar-pose observers estimate exactly "
                         f"the 4 distinct states (x, y, v, psi); the system has {system.state_names}")
    return tuple(system.state_names.index(n) for n in names)


def _pose_to_state(system: System, pose: np.ndarray, indices=None) -> np.ndarray:
    """Stage-1 states ``[x, y, vx, vy, psi, r]`` ``(..., 6)`` as system states ``(..., nx)``."""
    ix, iy, iv, ipsi = indices or planar_pose_indices(system)
    x = np.empty((*pose.shape[:-1], system.nx))
    x[..., ix], x[..., iy], x[..., ipsi] = pose[..., 0], pose[..., 1], pose[..., 4]
    x[..., iv] = np.hypot(pose[..., 2], pose[..., 3])
    return x


def _stage1_model(system: System, dt: float, q_accel: np.ndarray, q_turn: np.ndarray):
    """Stage-1 transition ``F`` and process noises ``Q (B, 6, 6)`` of the intensity pairs."""
    block = np.array([[1.0, dt], [0.0, 1.0]])
    F = np.zeros((6, 6))
    for sl in ((0, 2), (1, 3), (4, 5)):  # (position, rate) pairs of [x, y, vx, vy, psi, r]
        F[np.ix_(sl, sl)] = block
    unit = integrator_chain(2, dt)[1]
    Q = np.zeros((len(q_accel), 6, 6))
    for sl, q in (((0, 2), q_accel), ((1, 3), q_accel), ((4, 5), q_turn)):
        Q[np.ix_(np.arange(len(q)), sl, sl)] = np.asarray(q, float)[:, None, None] * unit
    return F, Q


def _pose_ukf(run: Run, system: System, q_accel, q_turn, T: int | None = None):
    """Stage-1 UKF over the first ``T`` samples, one filter per pair ``(q_accel[b], q_turn[b])``
    (one pass for all). Returns means ``(T, B, 6)``, covariances ``(T, B, 6, 6)`` and the
    log-likelihoods ``(B,)``; and ``F``, ``Q`` of the kinematic model.

    The filter is FilterPy's ``UnscentedKalmanFilter`` with ``MerweScaledSigmaPoints(6,
    alpha=0.1, beta=2, kappa=0)`` (a test holds them equal to rounding), with the sigma points'
    measurements evaluated all at once and the prediction in closed form (the model is
    linear). An output missing at a sample (NaN) is left out of its update; a sample with no
    output is a prediction only.
    """
    indices = planar_pose_indices(system)
    q_accel, q_turn = np.atleast_1d(np.asarray(q_accel, float)), np.atleast_1d(np.asarray(q_turn, float))
    q_accel, q_turn = np.broadcast_arrays(q_accel, q_turn)
    B, n = len(q_accel), 6
    F, Q = _stage1_model(system, run.dt, q_accel, q_turn)
    alpha, beta = 0.1, 2.0
    lam = alpha**2 * n - n
    Wm = np.full(2 * n + 1, 0.5 / (n + lam))
    Wc = Wm.copy()
    Wm[0] = lam / (n + lam)
    Wc[0] = lam / (n + lam) + (1 - alpha**2 + beta)
    R = np.diag(np.square(system.noise.measurement_std))
    ix, iy, iv, ipsi = indices
    x0, std0 = np.asarray(system.x0, float), np.asarray(system.noise.initial_std, float)
    x = np.broadcast_to(np.array([x0[ix], x0[iy], x0[iv] * np.cos(x0[ipsi]), x0[iv] * np.sin(x0[ipsi]),
                                  x0[ipsi], 0.0]), (B, n)).copy()
    P = np.broadcast_to(np.diag([std0[ix] ** 2, std0[iy] ** 2, std0[iv] ** 2 + 1.0, std0[iv] ** 2 + 1.0,
                                 std0[ipsi] ** 2, 1.0]), (B, n, n)).copy()  # + (1 m/s)^2, (1 rad/s)^2
    T = len(run) if T is None else T
    means, covs = np.empty((T, B, n)), np.empty((T, B, n, n))
    loglik = np.zeros(B)

    def sigma_points(x, P):  # (B, 13, 6): x, x + rows of chol((n + lam) P), x - rows
        U = np.linalg.cholesky((n + lam) * P).transpose(0, 2, 1)  # upper: P = U' U, as scipy's
        return np.concatenate([x[:, None], x[:, None] + U, x[:, None] - U], axis=1)

    def transform(sig, mean_w, cov_w, noise):
        mean = np.einsum("s,bsi->bi", mean_w, sig)
        d = sig - mean[:, None]
        return mean, np.einsum("bsi,s,bsj->bij", d, cov_w, d) + noise

    present = np.isfinite(run.y)
    for k in range(T):
        if k:  # predict; the model is linear, so its unscented transform is exactly this
            x, P = x @ F.T, F @ P @ F.T + Q
        sig_f = sigma_points(x, P)  # no predict before sample 0
        rows = np.flatnonzero(present[k])
        if len(rows):  # y[k] = h(x[k], u[k]), the simulator's convention
            sig_h = np.asarray(system.h(_pose_to_state(system, sig_f, indices), run.u[k]))[..., rows]
            zp, S = transform(sig_h, Wm, Wc, R[np.ix_(rows, rows)])
            Pxz = np.einsum("bsi,s,bsj->bij", sig_f - x[:, None], Wc, sig_h - zp[:, None])
            S_inv = np.linalg.inv(S)
            K = Pxz @ S_inv
            innov = run.y[k, rows] - zp
            x = x + np.einsum("bij,bj->bi", K, innov)
            P = P - K @ S @ K.transpose(0, 2, 1)
            loglik -= 0.5 * (np.einsum("bi,bij,bj->b", innov, S_inv, innov)
                             + np.linalg.slogdet(2 * np.pi * S)[1])
        means[k], covs[k] = x, P
    return means, covs, loglik, F, Q


def _speed_kf(pos: np.ndarray, var: np.ndarray, dt: float, q) -> FilterPasses:
    """Stage 2: constant-acceleration KFs on position coordinates with per-sample variances, one
    per member: ``pos``, ``var`` (T, B) (NaN: no position fix), ``q`` (B,) jerk intensities."""
    q = np.asarray(q, float)
    B = len(q)
    F = integrator_chain(3, dt)[0]
    Q = q[:, None, None] * integrator_chain(3, dt)[1]
    x0 = np.zeros((B, 3))
    P0 = np.broadcast_to(np.diag([1.0, 1e4, 1e4]), (B, 3, 3)).copy()
    first = np.isfinite(pos[0])
    x0[first, 0], P0[first, 0, 0] = pos[0, first], var[0, first]
    P0[~first, 0, 0] = 1e4
    R = np.where(np.isfinite(var), var, 1.0)[:, :, None, None]
    return kalman_filter(F, np.eye(1, 3), Q, R, pos[:, :, None], x0, P0)


def _position_fix_variance(run: Run, system: System, pose: np.ndarray) -> np.ndarray:
    """(T, 2) variances of a one-sample position fix, ``diag(inv(J' R^-1 J))``, J = dh/d(x, y),
    from the outputs present at each sample; NaN where they do not fix the position.

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
    present = np.isfinite(run.y[:len(pose)])
    w = np.where(present, 1.0 / np.square(np.asarray(system.noise.measurement_std, float)), 0.0)
    info = np.einsum("tki,tk,tkj->tij", Js, w, Js)
    singular = np.linalg.det(info) <= 1e-12 * np.einsum("tii->t", info) ** 2
    if np.any(singular & present.all(axis=1)):
        raise ObserverError(f"system {system.name!r}: the measurements do not fix the position "
                            "(x, y) at some samples; the planar-pose observers need them to")
    out = np.full((len(pose), 2), np.nan)
    out[~singular] = np.diagonal(np.linalg.inv(info[~singular]), axis1=1, axis2=2)
    return out


def _two_stage(run: Run, system: System, smooth: bool) -> Observations:
    """The paper's pre-training observer for a planar robot: a UKF, then a linear KF (see above)."""
    ix, iy, iv, ipsi = planar_pose_indices(system)
    tune = dict(T=min(len(run), STAGE1_TUNING_SAMPLES))
    mid_turn = float(np.sqrt(TURN_GRID[0] * TURN_GRID[-1]))
    q_accel = ACCEL_GRID[int(np.argmax(_pose_ukf(run, system, ACCEL_GRID, mid_turn, **tune)[2]))]
    q_turn = TURN_GRID[int(np.argmax(_pose_ukf(run, system, q_accel, TURN_GRID, **tune)[2]))]
    means, covs, _, F, _ = _pose_ukf(run, system, q_accel, q_turn)
    if smooth:  # the stage-1 model is linear: its RTS smoother is the Kalman one
        means_p = np.empty_like(means)
        means_p[0], means_p[1:] = means[0], means[:-1] @ F.T
        covs_p = np.empty_like(covs)
        Q = _stage1_model(system, run.dt, [q_accel], [q_turn])[1]
        covs_p[0], covs_p[1:] = covs[0], F @ covs[:-1] @ F.T + Q
        stage1 = FilterPasses(means, covs, means_p, covs_p, np.zeros(1))
        means, covs = rts_smoother(F, stage1)
    means, covs = means[:, 0], covs[:, 0]
    dt = run.dt
    pos, pos_var = means[:, :2], covs[:, [0, 1], [0, 1]]
    fix_var = _position_fix_variance(run, system, means)
    pos_fix = np.where(np.isfinite(fix_var), pos, np.nan)
    grid = JERK_GRID[::2]
    G = len(grid)
    # both axes with every grid intensity at once: member j * G + g
    passes = _speed_kf(np.repeat(pos_fix, G, axis=1), np.repeat(fix_var, G, axis=1), dt, np.tile(grid, 2))
    best = int(np.argmax(passes.loglik.reshape(2, G).sum(axis=0)))
    q_jerk = float(grid[best])
    chosen = [best, G + best]
    axes = FilterPasses(*(a[:, chosen] for a in (passes.means, passes.covs, passes.means_p, passes.covs_p)),
                        passes.loglik[chosen])
    if smooth:
        m, c = rts_smoother(integrator_chain(3, dt)[0], axes)
    else:
        m, c = axes.means, axes.covs
    vel, vel_var = m[:, :, 1], c[:, :, 1, 1]
    speed = np.hypot(vel[:, 0], vel[:, 1])
    speed_var = np.sum(vel**2 * vel_var, axis=1) / np.maximum(speed, 1e-9) ** 2  # delta method
    zeta, var = np.empty((len(run), system.nx)), np.empty((len(run), system.nx))
    zeta[:, ix], zeta[:, iy], zeta[:, iv], zeta[:, ipsi] = means[:, 0], means[:, 1], speed, means[:, 4]
    var[:, ix], var[:, iy], var[:, iv], var[:, ipsi] = pos_var[:, 0], pos_var[:, 1], speed_var, covs[:, 4, 4]
    info = {"accel_spectral_density": float(q_accel), "turn_spectral_density": float(q_turn),
            "jerk_spectral_density": q_jerk}
    return Observations(zeta, var, "ukf_rts" if smooth else "ukf_kf", info)
