"""The MHE's steady-state arrival cost: theory, and its effect on estimation."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from learnest_codegen.estimators.mhe import MHE
from learnest_codegen.estimators.mhe_problem import MHESettings, steady_state_arrival
from learnest_codegen.export import prior_model, true_model
from learnest_codegen.simulation import simulate


def test_arrival_covariance_is_the_converged_kalman_prior(cartpole):
    """For the linearised model, FilterPy's KF prior covariance converges to the DARE solution."""
    model = prior_model(cartpole)
    settings = steady_state_arrival(model, MHESettings.from_system(cartpole))
    x0, u0 = np.array(cartpole.x0), np.zeros(1)
    eps = 1e-6  # finite-difference Jacobians: independent of CasADi's
    A = np.column_stack([(model.step(x0 + eps * e, u0) - model.step(x0 - eps * e, u0)) / (2 * eps)
                         for e in np.eye(4)])
    kf = KalmanFilter(dim_x=4, dim_z=2)
    kf.F, kf.H = A, np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    kf.Q = np.diag(np.square(settings.process_std))
    kf.R = np.diag(np.square(settings.measurement_std))
    for _ in range(3000):
        kf.predict()
        kf.update(np.zeros(2))
    np.testing.assert_allclose(np.asarray(settings.arrival_covariance), kf.P_prior, rtol=1e-5)


def test_settings_roundtrip_and_validation(cartpole):
    settings = steady_state_arrival(prior_model(cartpole), MHESettings.from_system(cartpole))
    assert MHESettings.from_json(settings.to_json()) == settings
    P = settings.weights()[2]
    np.testing.assert_allclose(P @ np.asarray(settings.arrival_covariance), np.eye(4), atol=1e-8)
    with pytest.raises(ValueError, match="positive definite"):
        MHESettings.from_system(cartpole, arrival_covariance=-np.eye(4))


def test_steady_state_arrival_lets_the_mhe_use_its_model(cartpole):
    """With the true model, the MHE must beat the nominal MHE by a wide margin once the arrival
    cost carries past information (with a fixed initial-uncertainty weight it did not)."""
    run = simulate(cartpole, 1, duration=0.8)
    mse = {}
    for model in (prior_model(cartpole), true_model(cartpole)):
        settings = steady_state_arrival(model, MHESettings.from_system(cartpole))
        x_hat = MHE(model, settings).run(run.u, run.y, np.array(cartpole.x0))
        mse[model.kind] = np.mean((x_hat - run.x) ** 2)
    assert mse["true"] < mse["nominal"] / 10, mse
