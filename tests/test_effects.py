"""The effect library: coverage of the required kinds, backend parity, closed forms, exact features."""

from __future__ import annotations

import casadi as cs
import numpy as np
import pytest
import torch

from learnest_codegen import get_system
from learnest_codegen.diagnosis.cv import FitData, block_bootstrap, box_solve, cv_sse, grams
from learnest_codegen.diagnosis.effects import (
    Effect,
    corrected_dynamics,
    corrected_system,
    describe_library,
    library,
    velocity_states,
)
from learnest_codegen.diagnosis.fit import FitSettings, Pairs, one_step
from learnest_codegen.errors import ShapeError, UnknownNameError

REQUIRED = {"mass", "viscous_friction", "coulomb_friction", "quadratic_drag", "actuator_gain",
            "actuator_offset", "bias"}
ACTUATOR = {"dead_zone", "saturation", "back_emf", "input_delay", "actuator_lag"}


def test_cartpole_library_covers_the_required_kinds():
    lib = library(get_system("cartpole"))
    assert REQUIRED <= {e.kind for e in lib}
    names = {e.name for e in lib}
    # a cart friction is a force entering where the motor force does, and a direct term
    assert {"viscous_friction(pdot via F)", "viscous_friction(pdot)", "mass(pdot via m_c)"} <= names
    assert len(names) == len(lib)
    assert "actuator_gain(pdot via F)" in describe_library(lib)


def test_ground_robot_and_quadrotor_libraries():
    ground = get_system("ground_robot")
    assert velocity_states(ground) == {"v": "v"}  # psi is an angle, not a velocity
    kinds = {e.kind for e in library(ground)}
    assert REQUIRED - {"mass"} <= kinds  # the robot's mass enters only through the prior's zero drag
    quad = get_system("quadrotor")
    lib = {e.name: e for e in library(quad)}
    assert velocity_states(quad) == {"vx": "ax", "vy": "ay", "vz": "az"}  # drag on v acts on a'
    assert {"battery_thrust_loss(vbat on az)", "quadratic_drag(vx on ax)", "motor_lag(az)"} <= set(lib)
    assert not any(e.kind == "actuator_gain" for e in lib.values())  # its prior ignores the inputs
    with pytest.raises(UnknownNameError, match="unknown effect kinds"):
        library(quad, kinds=("wind_shear",))


def test_corrected_dynamics_agree_in_numpy_torch_casadi():
    system = get_system("cartpole")
    lib = library(system)
    rng = np.random.default_rng(0)
    thetas = rng.normal(0, 0.1, len(lib))
    fixed = corrected_system(system, lib, thetas)
    x, u = rng.normal(size=(7, 4)), rng.normal(size=(7, 1))
    f_np = fixed.f(x, u)
    f_torch = fixed.f(torch.as_tensor(x), torch.as_tensor(u)).numpy()
    F = fixed.casadi_f()
    f_cs = np.stack([np.asarray(F(a, b)).ravel() for a, b in zip(x, u)])
    np.testing.assert_allclose(f_torch, f_np, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(f_cs, f_np, rtol=1e-12, atol=1e-12)


def test_input_channel_effects_are_the_prior_at_the_perturbed_input():
    system = get_system("cartpole")
    lib = {e.name: e for e in library(system)}
    c, gain, offset = 0.7, -0.2, 0.3
    effects = [lib["viscous_friction(pdot via F)"], lib["actuator_gain(pdot via F)"],
               lib["actuator_offset(pdot via F)"]]
    fixed = corrected_system(system, effects, [c, gain, offset])
    rng = np.random.default_rng(1)
    x, u = rng.normal(size=(5, 4)), rng.normal(size=(5, 1))
    force = u * (1 + gain) + offset - c * x[:, 1:2]  # closed form: F_eff = (1+g) F + b - c pdot
    np.testing.assert_allclose(fixed.f(x, u), system.f(x, force), rtol=1e-13, atol=1e-13)
    mass = corrected_system(system, [lib["mass(pdot via m_c)"]], [0.5])
    np.testing.assert_allclose(mass.f(x, u), system.f(x, u, variant="true"), rtol=1e-13)
    assert system.f(x, u).shape == mass.f(x, u).shape
    np.testing.assert_allclose(mass.f(x, u, variant="true"), system.f(x, u, variant="true"))


def test_features_are_the_derivative_of_the_rk4_residual():
    system = get_system("ground_robot")
    lib = library(system)
    rng = np.random.default_rng(2)
    z = np.column_stack([rng.normal(size=40), rng.normal(size=40), rng.uniform(1, 3, 40),
                         rng.normal(size=40)])
    pairs = Pairs.from_states([(np.arange(40) * 0.01, z, rng.normal(0, 0.2, (40, 2)))])
    theta = rng.normal(0, 0.01, len(lib))
    r, J = one_step(system, lib, theta, pairs)
    h = 1e-6
    for j in range(len(lib)):
        up, down = theta.copy(), theta.copy()
        up[j] += h
        down[j] -= h
        numeric = -(one_step(system, lib, up, pairs, False)[0]
                    - one_step(system, lib, down, pairs, False)[0]) / (2 * h)
        scale = max(1.0, np.abs(numeric).max())
        np.testing.assert_allclose(J[:, :, j], numeric, rtol=1e-5, atol=1e-6 * scale)
    casadi_residual = (z[1:] - np.stack([
        np.asarray(cs.Function("F", *_rk4(system, 0.01))(a, b)).ravel() for a, b in zip(z[:-1], pairs.u)
    ])) / 0.01
    r0 = one_step(system, lib, np.zeros(len(lib)), pairs, False)[0]
    psi = system.state_names.index("psi")
    np.testing.assert_allclose(np.delete(r0, psi, 1), np.delete(casadi_residual, psi, 1), rtol=1e-9,
                               atol=1e-9)


def _rk4(system, dt):
    from learnest_codegen.export import prior_model

    model = prior_model(system)
    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    return [x, u], [model.F(x, u)]


def test_block_bootstrap_matches_least_squares_theory_on_white_noise():
    rng = np.random.default_rng(0)
    n = 8000
    phi = rng.normal(size=(n, 1, 1))
    R = 2.0 * phi[:, :, 0] + rng.normal(size=(n, 1))
    data = FitData(R, phi, np.ones(1), np.zeros(1))
    draws = block_bootstrap(data, FitSettings(bootstrap=1000, blocks=100))
    theory = 1.0 / np.sqrt(np.sum(phi**2))  # OLS std with unit noise
    # 100 blocks: the bootstrap's own std estimate scatters by about 1/sqrt(200) = 7 %
    assert abs(draws.std() / theory - 1) < 0.2
    assert abs(draws.mean() - 2.0) < 4 * theory


def test_pairs_check_shapes():
    with pytest.raises(ShapeError, match="expected t"):
        Pairs.from_states([(np.arange(3.0), np.zeros((4, 2)), np.zeros((4, 1)))])
    with pytest.raises(ShapeError, match="finite"):
        Pairs.from_states([(np.arange(3.0), np.full((3, 2), np.nan), np.zeros((3, 1)))])
    # a missing sample leaves out the two pairs it belongs to, nothing else
    z = np.arange(12.0).reshape(6, 2)
    z[2, 1] = np.nan
    pairs = Pairs.from_states([(np.arange(6.0), z, np.zeros((6, 1)))])
    assert pairs.k.tolist() == [0, 3, 4] and np.isfinite(pairs.x).all() and np.isfinite(pairs.x_next).all()
    with pytest.raises(ValueError, match="2 effects but 1"):
        corrected_dynamics(get_system("cartpole"), library(get_system("cartpole"))[:2], [0.1])


def test_quadrotor_thrust_response_is_the_true_dynamics():
    """thrust_response (k_T/tau, 1/tau + k_D, k_D/tau) plus bias(az) = k_D g is, algebraically,
    the quadrotor's true motor-lag / battery-thrust / rotor-drag dynamics; and the physical
    parameters are recovered from the fitted ones."""
    from learnest_codegen.diagnosis.effects import DERIVED
    from learnest_codegen.systems.quadrotor import GRAVITY, K_DRAG, K_T, TAU_MOTOR

    quad = get_system("quadrotor")
    lib = {e.name: e for e in library(quad)}
    group = [e for e in lib.values() if e.group == "thrust_response"]
    assert [e.param for e in group] == ["k/tau", "1/tau", "k_D/tau"]
    thetas = [K_T / TAU_MOTOR, 1 / TAU_MOTOR + K_DRAG, K_DRAG / TAU_MOTOR, K_DRAG * GRAVITY]
    corrected = corrected_system(quad, [*group, lib["bias(az)"]], thetas)
    rng = np.random.default_rng(3)
    x = rng.normal(size=(50, 9))
    u = np.hstack([rng.uniform(0, 1, (50, 3)), rng.uniform(3.3, 3.8, (50, 1))])
    np.testing.assert_allclose(corrected.f(x, u), quad.f(x, u, variant="true"), rtol=1e-12, atol=1e-9)
    phys = DERIVED["thrust_response"](dict(zip(["k/tau", "1/tau", "k_D/tau"], thetas)))
    np.testing.assert_allclose([phys["tau"], phys["k_T"], phys["k_D"]], [TAU_MOTOR, K_T, K_DRAG], rtol=1e-12)


def test_actuator_kinds_and_physical_ranges():
    """Every driving input gets the actuator dynamics; frictions, drags, delays and lags are >= 0,
    and a friction acts "through an input" only where that input pushes the velocity one way."""
    import math

    from learnest_codegen.diagnosis.effects import input_orientation

    car = {e.name: e for e in library(get_system("rc_car"))}
    assert ACTUATOR <= {e.kind for e in car.values()}
    assert {"input_delay(v via throttle)", "actuator_lag(psi via steering)", "back_emf(v via throttle)",
            "dead_zone(v via throttle)", "saturation(psi via steering)"} <= set(car)
    for e in car.values():
        if e.kind in ("viscous_friction", "coulomb_friction", "quadratic_drag", "back_emf", "dead_zone",
                      "input_delay", "actuator_lag"):
            assert e.lower == 0.0 and not e.physical(-1e-3), e.name
    assert car["actuator_gain(v via throttle)"].lower == pytest.approx(-1.0, abs=2e-3)
    assert math.isinf(car["bias(v)"].lower)
    cartpole = get_system("cartpole")
    sign = input_orientation(cartpole)
    assert sign[("pdot", "F")] == 1 and sign[("alphadot", "F")] == 0  # cos(alpha) changes sign
    names = {e.name for e in library(cartpole)}
    assert "viscous_friction(pdot via F)" in names and "viscous_friction(alphadot via F)" not in names
    quad = {e.name: e for e in library(get_system("quadrotor"))}
    assert all(e.lower == 0.0 for e in quad.values() if e.group == "thrust_response")


def test_delay_and_lag_filters_against_closed_forms():
    """A delay of n + a samples is the linear interpolation of the held input between samples
    k - n and k - n - 1; a lag is the exact first-order response to the held input, averaged
    over each step: for a unit step at t = 0, s(t) = 1 - exp(-t / tau), whose mean over
    [k dt, (k+1) dt] is 1 - tau (exp(-k dt/tau) - exp(-(k+1) dt/tau)) / dt."""
    from learnest_codegen.diagnosis.actuator_effects import delay, lag

    dt = 0.01
    u = np.array([0.0, 0.0, 1.0, 3.0, 2.0, 2.0, 5.0])
    np.testing.assert_allclose(delay(u, dt, 0.0), u)
    np.testing.assert_allclose(delay(u, dt, 2 * dt), [0, 0, 0, 0, 1, 3, 2])
    np.testing.assert_allclose(delay(u, dt, 1.5 * dt), [0, 0, 0, 0.5, 2, 2.5, 2])
    step = np.r_[0.0, np.ones(200)]
    tau = 0.05
    k = np.arange(200)
    exact = 1 - tau * (np.exp(-k * dt / tau) - np.exp(-(k + 1) * dt / tau)) / dt
    np.testing.assert_allclose(lag(step, dt, tau)[1:], exact, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(lag(step, dt, 0.0), step)


def test_filter_features_are_derivatives_of_the_residual():
    """A delay's and a lag's features (input Jacobian times the filtered input's derivative) match
    central differences of the one-step residual, away from the delay's sample boundaries."""
    system = get_system("rc_car")
    lib = {e.name: e for e in library(system)}
    effects = [lib["input_delay(v via throttle)"], lib["actuator_lag(psi via steering)"],
               lib["back_emf(v via throttle)"], lib["dead_zone(v via throttle)"]]
    rng = np.random.default_rng(4)
    T = 60
    z = np.column_stack([rng.normal(size=T), rng.normal(size=T), rng.uniform(1, 3, T), rng.normal(size=T)])
    u = np.column_stack([np.repeat(rng.uniform(0.2, 0.5, T // 10), 10),
                         np.repeat(rng.uniform(-1, 1, T // 10), 10)])
    pairs = Pairs.from_states([(np.arange(T) * 0.01, z, u)])
    theta = np.array([0.0234, 0.07, 0.1, 0.05])
    _, J = one_step(system, effects, theta, pairs)
    for j in range(len(effects)):
        h = 1e-7
        up, down = theta.copy(), theta.copy()
        up[j] += h
        down[j] -= h
        numeric = -(one_step(system, effects, up, pairs, False)[0]
                    - one_step(system, effects, down, pairs, False)[0]) / (2 * h)
        scale = max(1.0, np.abs(numeric).max())
        np.testing.assert_allclose(J[:, :, j], numeric, rtol=1e-4, atol=1e-5 * scale)


def test_bounded_solves_match_scipy_and_never_leave_the_box():
    """box_solve is the bounded least-squares optimum (scipy's lsq_linear on the stacked rows), and
    a cross-validated fit of a coefficient the data want negative stays at its bound of 0."""
    from scipy.optimize import lsq_linear

    rng = np.random.default_rng(5)
    A = rng.normal(size=(200, 3))
    y = A @ np.array([1.0, -2.0, 0.5]) + 0.1 * rng.normal(size=200)
    lo, hi = np.array([0.0, 0.0, -np.inf]), np.array([np.inf, 1.0, np.inf])
    ref = lsq_linear(A, y, bounds=(lo, hi)).x
    got = box_solve(A.T @ A, A.T @ y, lo, hi)
    np.testing.assert_allclose(got, ref, atol=1e-8)
    np.testing.assert_allclose(box_solve(A.T @ A, A.T @ y), np.linalg.lstsq(A, y, rcond=None)[0], atol=1e-10)
    phi = rng.normal(size=(400, 1, 1))
    data = FitData(-0.7 * phi[:, :, 0] + rng.normal(size=(400, 1)), phi, np.ones(1), np.zeros(1),
                   lo=np.zeros(1))
    G, b, c = grams(data, settings=FitSettings())
    assert np.allclose(cv_sse(G, b, c, [0], data.lo, data.hi), c)  # theta = 0 in every fold
    assert (cv_sse(G, b, c, [0]) < c).all()  # unbounded, the negative coefficient would fit


def test_one_step_uses_each_librarys_own_terms():
    """Two libraries of one system whose effects share names but not terms (a Coulomb smoothing
    set from the data's speeds) give each its own residual: the compiled step is not reused
    across them."""
    from learnest_codegen.diagnosis.effects import default_context

    system = get_system("ground_robot")
    rng = np.random.default_rng(2)
    z = np.column_stack([rng.normal(size=40), rng.normal(size=40), rng.uniform(1, 3, 40),
                         rng.normal(size=40)])
    pairs = Pairs.from_states([(np.arange(40) * 0.01, z, rng.normal(0, 0.2, (40, 2)))])
    residuals = []
    for speed in (1.0, 100.0):  # v_s = 0.02 m/s and 2 m/s
        lib = library(system, default_context(system, {"v": speed}))
        theta = np.zeros(len(lib))
        theta[[e.name for e in lib].index("coulomb_friction(v)")] = 0.3
        residuals.append(one_step(system, lib, theta, pairs, False)[0])
    v = z[:-1, 2]
    vdot = system.state_names.index("v")
    # the friction -0.3 tanh(v / v_s) on v': r(theta) = r(0) + 0.3 tanh(v / v_s) (to RK4's accuracy)
    diff = residuals[1][:, vdot] - residuals[0][:, vdot]
    np.testing.assert_allclose(diff, 0.3 * (np.tanh(v / 2.0) - np.tanh(v / 0.02)), rtol=0.05)


def test_an_effect_that_differs_between_runs_is_not_consistent():
    """Per-run bounded fits: a coefficient of +1 on two runs and -0.5 on a third is not the same on
    every run (the sign differs), one of 1.0, 1.1 and 0.9 is; and the summary says so in words."""
    from learnest_codegen.diagnosis import summary
    from learnest_codegen.diagnosis.search import consistent, per_run_values

    rng = np.random.default_rng(7)
    runs = np.repeat([0, 1, 2], 300)
    phi = rng.normal(size=(900, 1, 1))
    values = {}
    for label, per_run in (("differs", [1.0, 1.0, -0.5]), ("same", [1.0, 1.1, 0.9])):
        R = np.take(per_run, runs)[:, None] * phi[:, :, 0] + 0.01 * rng.normal(size=(900, 1))
        data = FitData(R, phi, np.ones(1), np.zeros(1), runs=runs)
        got, se = (a[:, 0] for a in per_run_values(data, [0], np.zeros(1)))
        np.testing.assert_allclose(got, per_run, atol=0.01)
        pooled = float(np.linalg.lstsq(phi[:, 0, :], R[:, 0], rcond=None)[0][0])
        values[label] = consistent(got, pooled, se)
    assert not values["differs"]["consistent"] and values["differs"]["sign_agreement"] == pytest.approx(2 / 3)
    assert values["same"]["consistent"]
    report = {"system": "s", "verdict": "partly explained", "verdict_reason": "r", "source": "truth",
              "explained_in_sample": 0.5, "heldout_gap_closed": 0.4, "basis": "3 runs fitted together",
              "where": [], "effects": [], "rejected_effects": [],
              "consistency": [{"effect": "gain", "param": "g", "consistent": False,
                               "per_run": values["differs"]["per_run"], "sign_agreement": 2 / 3}],
              "selection": {"blocked": [{"effect": "lag"}]},
              "shrink": {"one_step": {"before": 2.0, "after": 1.2, "closed": 0.4}}}
    text = summary(report)
    assert "gain (g): NOT the same on every run" in text and "sign agrees on 67%" in text
    assert "lag: not entered, its parameter differs between runs" in text


def test_bounded_solves_keep_columns_of_very_different_scales():
    """A delay in seconds next to an inertia in kg m^2: columns whose norms differ by 1e8. The
    solve is the least-squares optimum to working precision (numpy's lstsq on the column-scaled
    problem), bounded or not; unscaled, the small column was lost to the large one's rounding."""
    rng = np.random.default_rng(11)
    A = rng.normal(size=(500, 3)) * np.array([1e8, 1.0, 1e-2])
    truth = np.array([2e-9, 0.7, 30.0])
    y = A @ truth + 1e-3 * rng.normal(size=500)
    scale = np.linalg.norm(A, axis=0)
    ref = np.linalg.lstsq(A / scale, y, rcond=None)[0] / scale
    np.testing.assert_allclose(box_solve(A.T @ A, A.T @ y), ref, rtol=1e-8)
    lo, hi = np.array([0.0, 0.0, -np.inf]), np.array([np.inf, 0.5, np.inf])
    from scipy.optimize import lsq_linear
    bounded = lsq_linear(A / scale, y, bounds=(lo * scale, hi * scale)).x / scale
    np.testing.assert_allclose(box_solve(A.T @ A, A.T @ y, lo, hi), bounded, rtol=1e-6)


def test_saturation_at_cut_zero_leaves_the_input_slope_alone():
    """At cut 0 the saturation term is zero with zero slope in the input even where the command
    sits exactly at its largest value (a torque limit): the input-filter features there (a delay)
    are not halved, so they stay the derivative of the residual."""
    from learnest_codegen.diagnosis.effects import default_context

    system = get_system("rc_car")
    T = 40
    rng = np.random.default_rng(2)
    z = np.column_stack([rng.normal(size=T), rng.normal(size=T), rng.uniform(1, 3, T), rng.normal(size=T)])
    u = np.column_stack([np.where(np.arange(T) % 7 < 4, 0.5, -0.5), np.full(T, 0.2)])  # at +-max
    lib = {e.name: e for e in library(system, default_context(system, input_max={"throttle": 0.5,
                                                                                 "steering": 0.2}))}
    effects = [lib["saturation(v via throttle)"], lib["input_delay(v via throttle)"]]
    pairs = Pairs.from_states([(np.arange(T) * 0.01, z, u)])
    theta = np.zeros(2)
    r0, J = one_step(system, effects, theta, pairs)
    r_alone, J_alone = one_step(system, effects[1:], theta[1:], pairs)
    np.testing.assert_allclose(r0, r_alone, atol=1e-12)
    np.testing.assert_allclose(J[:, :, 1], J_alone[:, :, 0], rtol=1e-12, atol=1e-12)
    step = 0.3 * 0.01  # a delay of 0.3 samples: the feature predicts the change (halved, it would not)
    r1 = one_step(system, effects, np.array([0.0, step]), pairs, False)[0]
    change = np.abs(r1 - r0).max()
    assert change > 0 and np.abs(r1 - (r0 - J[:, :, 1] * step)).max() < 1e-3 * change


def test_blur_is_the_observers_smoother_applied_to_the_chain():
    """The smoothed-increment map of a kinematic chain (blur.ChainBlur) equals the observer's own
    filter and RTS pass (observers.kinematic.chain_passes, rts_smoother) run on the chain that the
    increments build, integrated exactly: a different computation (fixed-gain linear filters
    after the gains settle) of the same linear map, to rounding."""
    from learnest_codegen.diagnosis.blur import chain_blur
    from learnest_codegen.observers.kalman import rts_smoother
    from learnest_codegen.observers.kinematic import chain_passes

    T, dt, q, r = 700, 0.006, 316.0, np.array([2.5e-7])
    rng = np.random.default_rng(3)
    increments = rng.normal(size=(T - 1, 3)) * 0.05
    for smooth in (True, False):
        blur = chain_blur(1, T, dt, 2, (0,), q, r, smooth)
        got = blur.apply(increments)
        for b in range(3):  # the angle of a chain whose rate moves by the increments, ramped in each step
            v = np.r_[0.0, np.cumsum(increments[:, b])]
            angle = np.r_[0.0, np.cumsum(dt * (v[:-1] + 0.5 * increments[:, b]))]
            passes, model = chain_passes(angle, dt, 3, [q], r, (0,))
            means = rts_smoother(model.F, passes)[0] if smooth else passes.means
            np.testing.assert_allclose(got[:, b], np.diff(means[:, 0, 1]), rtol=0,
                                       atol=1e-9 * np.abs(got).max())


def test_a_poorly_excited_run_cannot_block_an_effect():
    """Per-run intervals from each run's own fit: a run that barely excites a coefficient (feature
    100 times weaker, same noise) gives a far-off value with a wide interval, and the coefficient
    stays consistent; on white noise the sandwich standard error is the least-squares one
    (sigma / |phi|) to within its sampling error (8 blocks: about 25 %)."""
    from learnest_codegen.diagnosis.search import consistent, per_run_values

    rng = np.random.default_rng(9)
    runs = np.repeat([0, 1, 2], 800)
    phi = rng.normal(size=(2400, 1, 1)) * np.where(runs == 2, 0.01, 1.0)[:, None, None]
    R = 1.0 * phi[:, :, 0] + 0.1 * rng.normal(size=(2400, 1))
    data = FitData(R, phi, np.ones(1), np.zeros(1), runs=runs)
    values, se = (a[:, 0] for a in per_run_values(data, [0], np.zeros(1)))
    ols = np.array([0.1 / np.linalg.norm(phi[runs == k]) for k in range(3)])
    np.testing.assert_allclose(se, ols, rtol=0.5)
    assert abs(values[2] - 1.0) > 0.2 and se[2] > 10 * se[0]
    check = consistent(values, 1.0, se)
    assert check["consistent"] and check["common"][0] <= 1.0 <= check["common"][1]
    # runs that each fix it well and disagree by more than half the pooled value each way do block it
    assert not consistent(np.array([1.0, 1.1, 2.4]), 1.2, np.full(3, 0.01))["consistent"]
    assert consistent(np.array([1.0, 1.1, 1.6]), 1.2, np.full(3, 0.01))["consistent"]


def test_wald_statistic_is_calibrated_on_noise_correlated_in_time():
    """The whole data's Wald statistic (search.wald): with one stretch per row its covariance is
    White's HC0 (written out here) times n / (n - 1); on AR(1) noise and an AR(1) feature (both
    0.9 per sample: the i.i.d. standard error is about 3x too small) with no effect, it exceeds 2
    about as often as a t statistic with 23 degrees of freedom (5.7 %) and 4 almost never, where
    the i.i.d. statistic exceeds 4 about one time in ten; with an effect of 6 true standard
    errors its median is near 6."""
    from learnest_codegen.diagnosis.search import sandwich, wald

    rng = np.random.default_rng(5)
    n = 600
    P = rng.normal(size=(n, 1, 2))
    e = rng.normal(size=(n, 1)) * (1 + np.abs(P[:, :, 0]))
    G = np.einsum("ksi,ksj->ij", P, P)
    X, inv = P[:, 0, :], np.linalg.inv(G)
    hc0 = inv @ (X.T * e[:, 0] ** 2) @ X @ inv
    np.testing.assert_allclose(sandwich(P, e, G, np.arange(n)), hc0 * n / (n - 1), rtol=1e-10)

    def ar1(size, phi=0.9):
        w = rng.normal(size=size)
        out = np.empty(size)
        out[0] = w[0] / np.sqrt(1 - phi ** 2)
        for k in range(1, size):
            out[k] = phi * out[k - 1] + w[k]
        return out * np.sqrt(1 - phi ** 2)

    n, draws = 2400, 300
    z, naive, betas = np.empty(draws), np.empty(draws), np.empty(draws)
    for i in range(draws):
        phi = ar1(n)[:, None, None]
        R = ar1(n)[:, None]
        data = FitData(R, phi, np.ones(1), np.zeros(1))
        z[i] = wald(data, [0], np.zeros(1), np.ones(1), 24)
        beta = float(phi[:, 0, 0] @ R[:, 0] / (phi[:, 0, 0] @ phi[:, 0, 0]))
        naive[i] = beta * np.linalg.norm(phi) / np.std(R[:, 0] - beta * phi[:, 0, 0])
        betas[i] = beta
    assert 0.02 < np.mean(np.abs(z) > 2) < 0.11 and np.mean(z > 4) <= 0.01
    assert np.mean(naive > 4) > 0.05
    se = float(np.std(betas))  # the estimate's own spread over the draws: its true standard error
    hits = []
    for _ in range(60):
        phi = ar1(n)[:, None, None]
        R = 6 * se * phi[:, :, 0] + ar1(n)[:, None]
        hits.append(wald(FitData(R, phi, np.ones(1), np.zeros(1)), [0], np.zeros(1), np.ones(1), 24))
    assert 4.5 < np.median(hits) < 7.5


def test_a_candidate_in_the_span_of_the_chosen_set_never_ends_the_selection():
    """A candidate whose feature is a combination of the chosen ones (an actuator gain beside the
    inertia and the gravity torque it scales together) adds nothing: held out it ties with the set
    itself, ahead of a real candidate that fits held out a little worse. It is no candidate: the
    selection stops on (and reports) the best candidate that could add something."""
    from learnest_codegen.diagnosis.cv import baseline
    from learnest_codegen.diagnosis.search import Search

    rng = np.random.default_rng(3)
    n = 600
    t = np.arange(n) / n
    a, b = np.sin(12 * t), np.cos(5 * t) + t
    spanned, unrelated = 2.0 * a - 0.5 * b, rng.normal(size=n)
    Phi = np.stack([a, b, spanned, unrelated], axis=1)[:, None, :]
    R0 = (3.0 * a + 2.0 * b)[:, None] + rng.normal(size=(n, 1))
    effects = [Effect("viscous_friction", "v", f"direct:v{i}", "c", "-", None) for i in range(4)]

    def data(theta):
        return FitData(R0 - np.einsum("nsm,m->ns", Phi, theta), Phi, np.ones(1), np.zeros(4))

    def refit(theta, chosen):
        full = np.zeros(4)
        full[chosen] = np.linalg.lstsq(Phi[:, 0, chosen], R0[:, 0], rcond=None)[0]
        return full, "converged"

    settings = FitSettings()
    first = baseline(data(np.zeros(4)), settings)
    search = Search(effects, data, None, refit, [0, 1, 2, 3], [[0], [1], [2], [3]], first, settings)
    assert search._apply([0, 1], np.zeros(4))
    G, b_, c = grams(search.data, settings=settings)
    base = cv_sse(G, b_, c, [0, 1]).sum()
    assert cv_sse(G, b_, c, [0, 1, 2]).sum() == pytest.approx(base, rel=1e-9)  # ties with the set
    assert cv_sse(G, b_, c, [0, 1, 3]).sum() > base  # the real candidate fits held out worse
    step = search.candidates()
    assert step["index"] == 3 and not step["accept"], step
    assert search._spanned(search.data, 2) and not search._spanned(search.data, 3)
