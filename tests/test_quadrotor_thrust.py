"""The quadrotor's grey-box prior of the true model's form (``quadrotor_thrust_linear``): its
dynamics, the least-squares fit on a simulated flight, and the study's features that use it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from learnest_codegen.experiments import quadrotor as fs
from learnest_codegen.learning.prior_fit import fit_linear_params, fitted_system
from learnest_codegen.simulation import simulate
from learnest_codegen.systems import SYSTEMS
from learnest_codegen.systems.check import check_system
from learnest_codegen.systems.quadrotor import (
    GRAVITY,
    K_DRAG,
    K_T,
    QUADROTOR,
    QUADROTOR_THRUST_LINEAR,
    TAU_MOTOR,
    V_NOM,
    thrust_coefficients,
    thrust_physics,
)

SYS = QUADROTOR_THRUST_LINEAR
SHARED = [n for n in SYS.params if n != "dc_T_z"]


def _points(n=40, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 9))
    u = np.column_stack([0.3 * rng.normal(size=(n, 2)), 0.86 + 0.1 * rng.normal(size=n),
                         rng.uniform(3.3, 3.8, size=n)])
    return x, u


def test_dynamics_against_closed_form():
    """Hand-written rows: kinematics, ``adot = c_T vbat T + c_v v + c_a a`` (+ ``c_0`` on z, the
    vertical gain ``c_T + dc_T_z``); all coefficients 0 is the paper's triple integrator."""
    assert SYSTEMS["quadrotor_thrust_linear"] is SYS
    assert SYS.residual_input_names == ["vx", "vy", "vz", "ax", "ay", "az"]
    x, u = _points()
    np.testing.assert_array_equal(SYS.f(x, u), QUADROTOR.f(x, u))  # registered: all 0
    p = {"c_T": 2.0, "dc_T_z": 0.5, "c_v_xy": -1.5, "c_a_xy": -3.0, "c_v_z": -0.7, "c_a_z": -4.0,
         "c_0_z": -9.0}
    f = fitted_system(SYS, p).f(x, u)
    vbat = u[:, 3]
    expected = np.column_stack([
        x[:, 3:9],
        2.0 * vbat * u[:, 0] - 1.5 * x[:, 3] - 3.0 * x[:, 6],
        2.0 * vbat * u[:, 1] - 1.5 * x[:, 4] - 3.0 * x[:, 7],
        2.5 * vbat * u[:, 2] - 0.7 * x[:, 5] - 4.0 * x[:, 8] - 9.0])
    np.testing.assert_allclose(f, expected, rtol=1e-14, atol=1e-13)


def test_physical_coefficients_are_the_simulation_truth():
    """At ``thrust_coefficients(k_T, tau, k_D)`` the prior is the true dynamics (same form), and
    ``thrust_physics`` inverts it."""
    x, u = _points(seed=1)
    coeffs = thrust_coefficients(K_T, TAU_MOTOR, K_DRAG)
    np.testing.assert_allclose(fitted_system(SYS, coeffs).f(x, u), QUADROTOR.f(x, u, variant="true"),
                               rtol=1e-12, atol=1e-10)
    physics = thrust_physics(coeffs)
    for group in ("xy", "z"):
        assert physics[group]["tau"] == pytest.approx(TAU_MOTOR, rel=1e-12)
        assert physics[group]["k_D"] == pytest.approx(K_DRAG, rel=1e-12)
        assert physics[group]["k_T"] == pytest.approx(K_T, rel=1e-12)
    assert physics["z"]["g_over_tau"] == pytest.approx(GRAVITY / TAU_MOTOR, rel=1e-12)
    # no drag: tau from c_a alone; no real root: NaN rather than a made-up number
    assert thrust_physics(thrust_coefficients(K_T, 0.1, 0.0))["xy"]["tau"] == pytest.approx(0.1, rel=1e-12)
    bad = {**coeffs, "c_v_xy": -200.0}
    assert np.isnan(thrust_physics(bad)["xy"]["tau"])


def test_numpy_torch_casadi_agree_with_fitted_coefficients():
    fitted = fitted_system(SYS, thrust_coefficients(K_T, TAU_MOTOR, K_DRAG) | {"dc_T_z": 0.3})
    check_system(fitted, "fitted quadrotor_thrust_linear")  # the load-time check
    x, u = _points(20, seed=2)
    ref = fitted.f(x, u)
    th = fitted.f(torch.as_tensor(x), torch.as_tensor(u)).numpy()
    F = fitted.casadi_f()
    ca = np.stack([np.asarray(F(xi, ui)).ravel() for xi, ui in zip(x, u)])
    np.testing.assert_allclose(th, ref, rtol=1e-12, atol=1e-11)
    np.testing.assert_allclose(ca, ref, rtol=1e-12, atol=1e-11)


@pytest.mark.parametrize("names", [SHARED, list(SYS.params)], ids=["shared", "per_group"])
def test_fit_recovers_the_truth_on_a_simulated_flight(names):
    """The simulation truth has exactly this form: the one-step RK4 fit on a simulated flight's
    true states recovers k_T, tau and k_D on both axis groups to 1e-4 (the simulator's finer
    integration against one RK4 step is the only difference), and g / tau."""
    run = simulate(QUADROTOR, 2)
    params = fit_linear_params(SYS, names, [run.x], [run.u], QUADROTOR.dt)
    physics = thrust_physics(params)
    for group in ("xy", "z"):
        assert physics[group]["tau"] == pytest.approx(TAU_MOTOR, rel=1e-4), group
        assert physics[group]["k_D"] == pytest.approx(K_DRAG, rel=1e-4), group
        assert physics[group]["k_T"] == pytest.approx(K_T, rel=1e-4), group
    assert physics["z"]["g_over_tau"] == pytest.approx(GRAVITY / TAU_MOTOR, rel=1e-4)
    assert params.get("dc_T_z", 0.0) == pytest.approx(0.0, abs=1e-4 * K_T / (V_NOM * TAU_MOTOR))


def test_features_registered_in_the_study():
    for name in ("thrust_prior", "thrust_prior_axes", "thrust_prior_z", "thrust_linear"):
        assert fs.feature_system(name) is SYS
    assert fs.FEATURES["thrust_prior"].fit_prior == tuple(SHARED)
    assert fs.FEATURES["thrust_prior_axes"].fit_prior == tuple(SYS.params)
    assert "c_T" not in fs.FEATURES["thrust_prior_z"].fit_prior
    assert "dc_T_z" in fs.FEATURES["thrust_prior_z"].fit_prior
    assert not any(fs.FEATURES[n].net for n in ("thrust_prior", "thrust_prior_axes", "thrust_prior_z"))
    assert fs.FEATURES["thrust_linear"].net and fs.FEATURES["thrust_linear"].start_at_prior
