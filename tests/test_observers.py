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
