"""Pre-training observers: the kinematic KF/RTS and the model UKF."""

from __future__ import annotations

import numpy as np
import pytest

from learnest_codegen.errors import UnknownNameError
from learnest_codegen.observers import _chain_filter, observe
from learnest_codegen.simulation import simulate


def test_kf_on_exact_constant_acceleration_recovers_velocity():
    """A noise-free constant-acceleration track is inside the KF's model: after convergence the
    filtered velocity must equal the closed form v(t) = v0 + a t."""
    dt, t = 0.01, np.arange(2000) * 0.01
    z = 1.0 + 0.5 * t + 0.5 * 0.8 * t**2
    means, _, _, _, _ = _chain_filter(z, dt, order=3, q=1e-6, r=1e-6)
    v = means[:, 1, 0]
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
    from filterpy.common import Q_continuous_white_noise
    from scipy.linalg import expm

    rng = np.random.default_rng(3)
    T, dt, q, r = 120, 0.01, 50.0, np.array([1e-4, 4e-2])
    t = np.arange(T) * dt
    truth = np.column_stack([np.sin(3 * t), 3 * np.cos(3 * t)])
    z = truth + rng.normal(size=truth.shape) * np.sqrt(r)
    means, covs, _, kf, fs = _chain_filter(z, dt, 3, q, r, rows=(0, 1))
    smoothed = kf.rts_smoother(means, covs, Fs=fs)[0][:, :, 0]
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
    with pytest.raises(ValueError, match="neither continues the other"):
        chain_groups(bad)
