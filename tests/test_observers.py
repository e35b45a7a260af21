"""Pre-training observers: the kinematic KF/RTS, the model UKF, the EKF-RTS smoother, the
planar-pose and linear observers; each against an independent reference (FilterPy, a batch
least-squares solution, a step-by-step numpy filter), with and without missing samples."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import rounding
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter
from scipy.linalg import expm

from learnest_codegen.errors import ObserverError, UnknownNameError
from learnest_codegen.observers import JERK_GRID, chain_passes, observe
from learnest_codegen.observers.kalman import rts_smoother
from learnest_codegen.simulation import simulate


def _chain_filter(z, dt, order, q, r, rows=(0,)):
    """One filter of :func:`chain_passes` (means, covariances, log-likelihood, model)."""
    passes, model = chain_passes(z, dt, order, [q], r, rows)
    return passes.means[:, 0], passes.covs[:, 0], float(passes.loglik[0]), model, passes


def filterpy_chain(z, dt, order, q, r, rows):
    """FilterPy's Kalman filter and RTS smoother of the same chain, step by step; a sample
    missing every output is ``z=None`` (predict only), one missing some outputs updates with
    the rows of H and R of those present."""
    m = len(rows)
    kf = KalmanFilter(dim_x=order, dim_z=m)
    kf.F = expm(np.diag(np.full(order - 1, dt), 1))
    kf.Q = Q_continuous_white_noise(dim=order, dt=dt, spectral_density=q)
    kf.H, kf.R = np.eye(order)[list(rows)], np.diag(r)
    kf.x, P0 = np.zeros((order, 1)), np.full(order, 1e4)
    for col, k in enumerate(rows):
        if np.isfinite(z[0, col]):
            kf.x[k, 0], P0[k] = z[0, col], r[col]
    kf.P = np.diag(P0)
    T = len(z)
    means, covs, means_p, covs_p = (np.empty((T, order)), np.empty((T, order, order)),
                                    np.empty((T, order)), np.empty((T, order, order)))
    loglik = 0.0
    for k in range(T):
        kf.predict()
        means_p[k], covs_p[k] = kf.x[:, 0], kf.P
        here = np.flatnonzero(np.isfinite(z[k]))
        if len(here):
            H, R = kf.H[here], kf.R[np.ix_(here, here)]
            S = H @ kf.P @ H.T + R
            e = z[k, here] - H @ kf.x[:, 0]
            loglik -= 0.5 * (e @ np.linalg.solve(S, e) + np.linalg.slogdet(2 * np.pi * S)[1])
            kf.update(z[k, here][:, None], R=R, H=H)
        means[k], covs[k] = kf.x[:, 0], kf.P
    smoothed, smoothed_covs, _, _ = kf.rts_smoother(means[:, :, None], covs)
    return means, covs, smoothed[:, :, 0], smoothed_covs, loglik


MISSING = {
    "none": lambda T: np.zeros(T, bool),
    "dropout_0.25s": lambda T: (np.arange(T) >= T // 3) & (np.arange(T) < T // 3 + 125),
    "quarter_rate": lambda T: np.arange(T) % 4 != 0,
    "first_sample": lambda T: np.arange(T) == 0,
}


@pytest.mark.parametrize("pattern", sorted(MISSING))
@pytest.mark.parametrize("q", [JERK_GRID[0], 30.0, JERK_GRID[-1]])
def test_chain_filter_and_smoother_equal_filterpy_with_missing_samples(cartpole_run, pattern, q):
    """The batched kinematic KF/RTS equals FilterPy's, sample by sample: a missing sample is a
    prediction only (FilterPy's ``z=None``), and the likelihood counts the samples present. The
    steady-state shortcut and the slowest-converging intensity of the grid are inside."""
    z = cartpole_run.y[:2000, :1].copy()
    z[MISSING[pattern](len(z))] = np.nan
    r = np.array([1e-4])
    means, covs, loglik, model, passes = _chain_filter(z, cartpole_run.dt, 3, q, r)
    smoothed, smoothed_covs = rts_smoother(model.F, passes)
    ref = filterpy_chain(z, cartpole_run.dt, 3, q, r, (0,))
    scale = np.abs(ref[0]).max(axis=0)
    np.testing.assert_allclose(means / scale, ref[0] / scale, rtol=0, atol=1e-9)
    np.testing.assert_allclose(smoothed[:, 0] / scale, ref[2] / scale, rtol=0, atol=1e-9)
    # covariances in units of sqrt(P_ii P_jj): the update and the smoother subtract predicted
    # covariances F P F' (large after a dropout at the largest intensity) down to the result,
    # and the two implementations round differently: n-term products to rounding of the largest
    # predicted entry over the smallest variance (the cancellation's condition number). The
    # smoothed ones from the second sample after the first measurement on: before, the diffuse
    # start's 1e4 leaves both five digits.
    settled = int(np.flatnonzero(np.isfinite(z[:, 0]))[0]) + 2
    F = np.asarray(model.F)
    predicted = np.abs(np.einsum("ij,kjl,ml->kim", F, ref[1], F)).max(axis=(1, 2))
    for got, want, first in ((covs, ref[1], 0), (smoothed_covs[settled:, 0], ref[3][settled:], settled)):
        d = np.sqrt(np.diagonal(want, axis1=1, axis2=2))
        cond = np.max(predicted[first:] / d.min(axis=1) ** 2)
        np.testing.assert_allclose(got / (d[:, :, None] * d[:, None, :]),
                                   want / (d[:, :, None] * d[:, None, :]), rtol=0,
                                   atol=rounding(ops=F.shape[0], cond=cond))
    assert loglik == pytest.approx(ref[4], rel=1e-10)


def test_two_outputs_of_one_chain_missing_one_at_a_time_equal_filterpy():
    """A chain measured at two derivative orders (angle and rate), each output missing at its
    own samples: an update with the outputs present, against FilterPy with the rows of H and R
    of those outputs."""
    rng = np.random.default_rng(4)
    T, dt, q, r = 600, 0.01, 50.0, np.array([1e-4, 4e-2])
    t = np.arange(T) * dt
    z = np.column_stack([np.sin(3 * t), 3 * np.cos(3 * t)]) + rng.normal(size=(T, 2)) * np.sqrt(r)
    z[::3, 0] = np.nan  # the angle at two thirds of the rate
    z[100:180, 1] = np.nan  # a gyro dropout
    z[400:410] = np.nan  # both
    means, covs, loglik, model, passes = _chain_filter(z, dt, 3, q, r, rows=(0, 1))
    smoothed, _ = rts_smoother(model.F, passes)
    ref = filterpy_chain(z, dt, 3, q, r, (0, 1))
    np.testing.assert_allclose(means, ref[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(smoothed[:, 0], ref[2], rtol=0, atol=1e-9)
    assert loglik == pytest.approx(ref[4], rel=1e-10)


def test_missing_everything_for_k_samples_is_k_predictions():
    """No output for k samples: the filtered means are the model's predictions, F^j x."""
    dt, T = 0.01, 300
    z = np.sin(np.arange(T) * dt)[:, None]
    z[100:140] = np.nan
    means, _, _, model, _ = _chain_filter(z, dt, 3, 10.0, np.array([1e-4]))
    x = means[99]
    for k in range(100, 140):
        x = model.F @ x
        np.testing.assert_allclose(means[k], x, rtol=1e-12, atol=1e-15)


def test_kf_on_exact_constant_acceleration_recovers_velocity():
    """A noise-free constant-acceleration track is inside the KF's model: after convergence the
    filtered velocity must equal the closed form v(t) = v0 + a t."""
    dt, t = 0.01, np.arange(2000) * 0.01
    z = 1.0 + 0.5 * t + 0.5 * 0.8 * t**2
    means, _, _, _, _ = _chain_filter(z, dt, order=3, q=1e-6, r=1e-6)
    v = means[:, 1]
    np.testing.assert_allclose(v[500:], 0.5 + 0.8 * t[500:], atol=1e-4)


def test_smoother_beats_filter(cartpole, cartpole_run):
    """RTS uses the whole run: its velocity observations must be several times more accurate."""
    kf, rts = observe(cartpole_run, cartpole, "kf"), observe(cartpole_run, cartpole, "rts")
    err = {o.method: np.mean((o.zeta - cartpole_run.x) ** 2, axis=0) for o in (kf, rts)}
    assert np.all(err["rts"] < err["kf"])
    assert err["rts"][1] < err["kf"][1] / 10  # cart velocity
    assert err["rts"][1] < 1e-3 and err["rts"][0] < 1e-5


def test_observer_variances_are_calibrated(cartpole, cartpole_run):
    """The observer's own variance must predict its actual error within a factor of a few."""
    obs = observe(cartpole_run, cartpole, "rts")
    ratio = np.mean((obs.zeta - cartpole_run.x) ** 2, axis=0) / np.mean(obs.variance, axis=0)
    assert np.all((ratio > 0.2) & (ratio < 5)), ratio


def test_model_ukf_observer(cartpole):
    """With a correct model (truth = prior) the model-based UKF removes most of the measurement
    noise (variance 1e-4) and recovers the unmeasured velocities."""
    exact = cartpole.with_true_params(m_c=cartpole.params["m_c"])
    run = simulate(exact, 0, duration=1.0)
    obs = observe(run, exact, "ukf")
    assert obs.zeta.shape == (len(run), 4)
    err = np.mean((obs.zeta[100:] - run.x[100:]) ** 2, axis=0)
    assert err[[0, 2]].mean() < 1e-5 and err[[1, 3]].max() < 1e-4


def test_unknown_observer(cartpole, cartpole_run):
    with pytest.raises(UnknownNameError, match="rts"):
        observe(cartpole_run, cartpole, "magic")


def test_chain_filter_with_angle_and_rate_is_the_batch_map_estimate():
    """Angle and rate measured together: the RTS smoother of the fused kinematic filter must equal
    the maximum a posteriori trajectory of the same linear-Gaussian model, solved as one weighted
    least-squares problem over the whole run (independent of FilterPy)."""
    rng = np.random.default_rng(3)
    T, dt, q, r = 120, 0.01, 50.0, np.array([1e-4, 4e-2])
    t = np.arange(T) * dt
    truth = np.column_stack([np.sin(3 * t), 3 * np.cos(3 * t)])
    z = truth + rng.normal(size=truth.shape) * np.sqrt(r)
    _, _, _, model, passes = _chain_filter(z, dt, 3, q, r, rows=(0, 1))
    smoothed = rts_smoother(model.F, passes)[0][:, 0]
    F = expm(np.diag([dt, dt], 1))
    Q = Q_continuous_white_noise(dim=3, dt=dt, spectral_density=q)
    P0 = np.diag([r[0], r[1], 1e4])
    x0 = np.array([z[0, 0], z[0, 1], 0.0])
    rows, rhs = [], []  # whitened equations in the stacked trajectory X (3 T)

    def add(block_cols, mats, value, cov):
        W = np.linalg.cholesky(np.linalg.inv(cov)).T
        row = np.zeros((len(value), 3 * T))
        for c, M in zip(block_cols, mats):
            row[:, 3 * c:3 * c + 3] = M
        rows.append(W @ row)
        rhs.append(W @ value)

    add([0], [np.eye(3)], F @ x0, F @ P0 @ F.T + Q)  # FilterPy predicts before the first update
    for k in range(T - 1):
        add([k + 1, k], [np.eye(3), -F], np.zeros(3), Q)
    for k in range(T):
        add([k], [np.eye(3)[:2]], z[k], np.diag(r))
    X = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0].reshape(T, 3)
    np.testing.assert_allclose(smoothed, X, rtol=0, atol=1e-8 * np.abs(X).max())


def test_rate_output_is_fused_not_substituted():
    """A gyro's chain continuing the encoder's is a second measurement of the same filter."""
    import dataclasses

    from learnest_codegen.diagnosis.selftest_systems import pendulum
    from learnest_codegen.observers import chain_groups
    from learnest_codegen.systems import KinematicChain, NoiseModel, Signal

    base = pendulum()
    gyro = dataclasses.replace(
        base, outputs=(Signal("q", "rad"), Signal("qdot", "rad/s")),
        measurement=lambda ops, x, u, p: [x[0], x[1]],
        noise=NoiseModel(measurement_std=(0.002, 0.05), state_std=(0.002, 0.02), process_std=(1e-3, 5e-2),
                         initial_std=(0.05, 0.2)),
        kinematic_chains=(KinematicChain("q", ("q", "qdot")), KinematicChain("qdot", ("qdot",))))
    ((chain, measured),) = chain_groups(gyro)
    assert chain.output == "q" and measured == [(0, 0), (1, 1)]
    run = simulate(gyro, 2, duration=6.0)
    fused = observe(run, gyro, "rts")
    angle_only = observe(dataclasses.replace(run, y=run.y[:, :1]), base, "rts")
    err = lambda o: np.sqrt(np.mean((o.zeta[:, 1] - run.x[:, 1]) ** 2))  # noqa: E731
    gyro_raw = np.sqrt(np.mean((run.y[:, 1] - run.x[:, 1]) ** 2))
    assert err(fused) < 0.8 * err(angle_only) and err(fused) < 0.5 * gyro_raw
    bad = dataclasses.replace(gyro, kinematic_chains=(KinematicChain("q", ("q", "qdot")),
                                                      KinematicChain("qdot", ("qdot", "q"))))
    with pytest.raises(ObserverError, match="neither continues the other"):
        chain_groups(bad)


def _filterpy_pose_ukf(run, system, q_accel, q_turn, T):
    """Stage 1 of the planar-pose observer as FilterPy's UKF, step by step (the implementation
    before the batched one); a missing output is left out of the update (FilterPy's ``hx`` and
    ``R`` of the outputs present)."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    from learnest_codegen.observers.planar_pose import _pose_to_state, planar_pose_indices

    ix, iy, iv, ipsi = planar_pose_indices(system)
    dt = run.dt
    F = np.zeros((6, 6))
    Q = np.zeros((6, 6))
    for sl, q in (((0, 2), q_accel), ((1, 3), q_accel), ((4, 5), q_turn)):
        F[np.ix_(sl, sl)] = [[1.0, dt], [0.0, 1.0]]
        Q[np.ix_(sl, sl)] = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=q)
    points = MerweScaledSigmaPoints(6, alpha=0.1, beta=2.0, kappa=0.0)
    h = lambda s, u: system.h(_pose_to_state(system, s), u)  # noqa: E731
    ukf = UnscentedKalmanFilter(6, system.ny, dt, hx=h, fx=lambda s, dt: F @ s, points=points)
    ukf.Q, ukf.R = Q, np.diag(np.square(system.noise.measurement_std))
    x0, std0 = np.asarray(system.x0, float), np.asarray(system.noise.initial_std, float)
    ukf.x = np.array([x0[ix], x0[iy], x0[iv] * np.cos(x0[ipsi]), x0[iv] * np.sin(x0[ipsi]), x0[ipsi], 0.0])
    ukf.P = np.diag([std0[ix] ** 2, std0[iy] ** 2, std0[iv] ** 2 + 1.0, std0[iv] ** 2 + 1.0,
                     std0[ipsi] ** 2, 1.0])
    means, loglik = np.empty((T, 6)), 0.0
    for k in range(T):
        if k:
            ukf.predict()
        else:
            ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
        rows = np.flatnonzero(np.isfinite(run.y[k]))
        if len(rows):
            ukf.update(run.y[k, rows], R=ukf.R[np.ix_(rows, rows)],
                       hx=lambda s, u, rows=rows: h(s, u)[rows], u=run.u[k])
            loglik -= 0.5 * (ukf.y @ np.linalg.solve(ukf.S, ukf.y) + np.linalg.slogdet(2 * np.pi * ukf.S)[1])
        means[k] = ukf.x
    return means, loglik


@pytest.mark.parametrize("missing", [False, True])
def test_planar_pose_ukf_equals_filterpy(missing):
    """The batched stage-1 UKF of the planar-pose observer equals FilterPy's UKF for every grid
    intensity (to rounding: 1e-10 of the track), with an output missing at some samples and
    every output at others."""
    from learnest_codegen.observers.planar_pose import _pose_ukf
    from learnest_codegen.systems import get_system

    system = get_system("ground_robot")
    run = simulate(system, 3, duration=4.0)
    if missing:
        y = run.y.copy()
        y[::2, 1] = np.nan  # one beacon at half the rate
        y[150:170] = np.nan  # everything
        run = dataclasses.replace(run, y=y)
    grid = np.array([0.1, 1.0, 10.0])
    means, _, loglik, _, _ = _pose_ukf(run, system, grid, 0.1, T=300)
    for b, q in enumerate(grid):
        ref, ref_loglik = _filterpy_pose_ukf(run, system, q, 0.1, 300)
        np.testing.assert_allclose(means[:, b], ref, rtol=0, atol=1e-10 * np.abs(ref).max())
        assert loglik[b] == pytest.approx(ref_loglik, rel=1e-10)


def test_every_observer_accepts_missing_samples():
    """A sensor at a quarter of the rate (NaN between its samples) and a dropout of every output:
    each observer of the cartpole and the ground robot still returns finite states, and on the
    cartpole the smoother's states stay close to those of the full run."""
    from learnest_codegen.systems import get_system

    for name, methods in (("cartpole", ("kf", "rts", "ukf", "ekf_rts")),
                          ("ground_robot", ("ukf_rts", "ukf_kf"))):
        system = get_system(name)
        run = simulate(system, 0, duration=3.0)
        y = run.y.copy()
        y[np.arange(len(y)) % 4 != 0, 0] = np.nan
        y[500:560] = np.nan
        gappy = dataclasses.replace(run, y=y)
        for method in methods:
            obs = observe(gappy, system, method)
            assert np.isfinite(obs.zeta).all() and np.isfinite(obs.variance).all(), (name, method)
    cartpole = get_system("cartpole")
    run = simulate(cartpole, 0, duration=3.0)
    y = run.y.copy()
    y[np.arange(len(y)) % 4 != 0, 0] = np.nan
    full, gappy = observe(run, cartpole, "rts"), observe(dataclasses.replace(run, y=y), cartpole, "rts")
    err = lambda o: np.sqrt(np.mean((o.zeta - run.x) ** 2, axis=0))  # noqa: E731
    assert np.all(err(gappy) < 3 * err(full))


def test_the_default_observer_reads_kinematic_chains_from_the_equations(user_system_file):
    """The README's pendulum declares no kinematic chains: its measurement ``y = q`` and its
    kinematics ``qdot`` are read from the equations, so the default is the kinematic smoother,
    the same one as with the chain declared; a system whose outputs are no states gets the
    EKF-RTS smoother. Each choice says why."""
    from learnest_codegen.observers import choose_observer, inferred_chains
    from learnest_codegen.systems import KinematicChain, get_system

    pendulum = get_system(str(user_system_file))
    assert inferred_chains(pendulum) == (KinematicChain("q", ("q", "qdot")),)
    name, why = choose_observer(pendulum)
    assert name == "rts" and "q -> qdot" in why
    run = simulate(pendulum, 0, duration=2.0)
    obs = observe(run, pendulum)
    declared = dataclasses.replace(pendulum, kinematic_chains=(KinematicChain("q", ("q", "qdot")),))
    np.testing.assert_array_equal(obs.zeta, observe(run, declared, "rts").zeta)
    assert obs.method == "rts" and "q -> qdot" in obs.info["chosen_because"]
    assert choose_observer(get_system("cartpole"))[0] == "rts"
    assert choose_observer(get_system("ground_robot"))[0] == "ukf_rts"
    sine = dataclasses.replace(pendulum, measurement=lambda ops, x, u, p: [ops.sin(x[0])])
    assert inferred_chains(sine) == ()
    assert choose_observer(sine)[0] == "ekf_rts"
    with pytest.raises(ObserverError, match="ekf_rts"):
        observe(run, sine, "rts")


def test_chains_with_the_same_filter_run_in_one_batch_with_the_numbers_of_separate_passes(cartpole):
    """The cartpole's two chains (cart and pole, both measured at position with the same
    variance) are filtered in one batch; each chain's states, variances and jerk intensity are
    bit for bit those of its own pass. A sample missing in one output only gives the chains
    different covariance recursions: then they are filtered apart."""
    from learnest_codegen.observers.kinematic import _fit_chains, _same_filters, chain_groups

    run = simulate(cartpole, 0, duration=2.0)
    groups = chain_groups(cartpole)
    assert _same_filters(run, cartpole, groups) == [[0, 1]]
    for smooth in (False, True):
        together = _fit_chains(run, cartpole, groups, smooth)
        for group, (means, covs, q) in zip(groups, together):
            alone = _fit_chains(run, cartpole, [group], smooth)[0]
            np.testing.assert_array_equal(means, alone[0])
            np.testing.assert_array_equal(covs, alone[1])
            assert q == alone[2]
        assert together[0][2] != together[1][2] or not np.array_equal(together[0][0], together[1][0])
    y = run.y.copy()
    y[50, 1] = np.nan
    assert _same_filters(dataclasses.replace(run, y=y), cartpole, groups) == [[0], [1]]
