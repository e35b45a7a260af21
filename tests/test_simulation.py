"""Integrators and simulation against theory and an independent integrator."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from learnest_codegen.data import DataError, read_run, write_run
from learnest_codegen.integrators import rk4_step
from learnest_codegen.simulation import noisy_states, simulate


def test_rk4_convergence_order_is_four(cartpole):
    """Global error of RK4 over 1 s scales as dt**4: the fitted slope must be close to 4."""
    x0, u = np.array([0.0, 0.0, 0.5, 0.0]), np.array([1.0])
    f = lambda x, v: cartpole.f(x, v)  # noqa: E731
    ref = solve_ivp(lambda _t, x: f(x, u), (0, 1.0), x0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    steps = np.array([40, 80, 160, 320])
    errors = []
    for n in steps:
        x = x0.copy()
        for _ in range(n):
            x = rk4_step(f, x, u, 1.0 / n)
        errors.append(np.linalg.norm(x - ref))
    slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
    assert 3.75 < slope < 4.25  # order 3 or 5 would fail


def test_simulated_truth_matches_independent_integrator(cartpole, cartpole_run):
    """Re-integrate the first 0.5 s with DOP853 and the recorded zero-order-hold inputs."""
    run, n = cartpole_run, 250
    x = run.x[0]
    for k in range(n):
        sol = solve_ivp(lambda _t, s, u=run.u[k]: cartpole.f(s, u, variant="true"), (0, run.dt), x,
                        method="DOP853", rtol=1e-12, atol=1e-12)
        x = sol.y[:, -1]
    np.testing.assert_allclose(run.x[n], x, atol=1e-8)


def test_run_shape_noise_and_boundedness(cartpole, cartpole_run):
    run = cartpole_run
    assert len(run) == 5000 and np.isclose(run.dt, 0.002) and np.isclose(run.t[-1], 9.998)
    residual = run.y - cartpole.h(run.x, run.u)
    np.testing.assert_allclose(residual.std(axis=0), 0.01, rtol=0.05)  # std 0.01 measurement noise
    assert abs(residual.mean()) < 1e-3
    assert np.abs(run.x[:, 0]).max() < 2.0, "the excitation must keep the cart near the origin"
    assert run.x[:, 3].std() > 1.0, "the pole must move (informative data)"


def test_simulation_is_reproducible(cartpole):
    a, b = simulate(cartpole, 3, duration=0.2), simulate(cartpole, 3, duration=0.2)
    np.testing.assert_array_equal(a.y, b.y)
    assert not np.array_equal(a.y, simulate(cartpole, 4, duration=0.2).y)


def test_noisy_states_have_state_noise(cartpole, cartpole_run):
    z = noisy_states(cartpole_run, cartpole, seed=0)
    np.testing.assert_allclose((z - cartpole_run.x).std(axis=0), 0.01, rtol=0.05)


def test_csv_roundtrip_is_exact(cartpole, tmp_path):
    run = simulate(cartpole, 0, duration=0.1)
    back = read_run(write_run(run, cartpole, tmp_path / "r.csv"), cartpole)
    for name in ("t", "u", "y", "x"):
        np.testing.assert_array_equal(getattr(back, name), getattr(run, name))


@pytest.mark.parametrize("mutate, message", [
    (lambda lines: [lines[0].replace("y_alpha", "y_beta")] + lines[1:], "missing columns"),
    (lambda lines: lines[:2] + [lines[2].replace(lines[2].split(",")[2], "inf", 1)] + lines[3:],
     "infinite value"),  # NaN or empty in a y_ column is a missing output (tests/test_streams.py)
    (lambda lines: [lines[0], lines[2], lines[1]] + lines[3:], "increase strictly"),
    (lambda lines: [lines[0]], "at least 2 samples"),
    (lambda lines: lines[:2] + ["0.5,abc,1,2,3,4,5,6"] + lines[3:], "non-numeric"),
])
def test_bad_csv_fails_clearly(cartpole, tmp_path, mutate, message):
    path = write_run(simulate(cartpole, 0, duration=0.02), cartpole, tmp_path / "r.csv")
    path.write_text("\n".join(mutate(path.read_text().splitlines())) + "\n")
    with pytest.raises(DataError, match=message):
        read_run(path, cartpole)


def test_missing_file(cartpole, tmp_path):
    with pytest.raises(FileNotFoundError):
        read_run(tmp_path / "nope.csv", cartpole)


# --- what simulate refuses -------------------------------------------------------------------------

def _pendulum(dyn, x0=(0.5, 0.0)):
    import dataclasses

    from learnest_codegen import get_system

    base = get_system("cartpole")
    from learnest_codegen.systems import NoiseModel, Signal

    return dataclasses.replace(
        base, name="pend", states=(Signal("q", "rad"), Signal("qdot", "rad/s")),
        inputs=(Signal("tau", "N m"),), outputs=(Signal("q", "rad"),), params={}, true_params={},
        dynamics=dyn, measurement=lambda ops, x, u, p: [x[0]], true_dynamics=None,
        noise=NoiseModel((0.01,), (0.01, 0.01), (1e-3, 1e-2), (0.1, 0.1)), dt=0.01, duration=3.0,
        x0=x0, excitation=lambda t, rng: np.sin(2 * t)[:, None], periodic_states=(),
        kinematic_chains=(), residual=dataclasses.replace(base.residual, inputs=None, via=None,
                                                          prior_features=(), prior_gains=False,
                                                          reflection=None))


def test_simulate_stops_with_the_time_where_the_dynamics_went_nan():
    """The state q is a clock (q = t + 0.5); qdot' = sqrt(1.5 - q) is NaN after t = 1 s. Before,
    `learnest simulate` never returned."""
    from learnest_codegen.errors import SolverError

    system = _pendulum(lambda ops, x, u, p: [1.0 + 0 * x[1], ops.sqrt(1.5 - x[0]) + u[0]])
    with pytest.raises(SolverError, match=r"returned \[1.0, nan\] at t = 1.0\d* s"):
        simulate(system, 0)


def test_simulate_has_a_step_limit_per_sample():
    """A spring of 1e14 N/m needs about a million explicit steps per 10 ms sample."""
    from learnest_codegen.errors import SolverError
    from learnest_codegen.simulation import MAX_STEPS_PER_SAMPLE

    system = _pendulum(lambda ops, x, u, p: [x[1], -1e14 * x[0] + u[0]])
    with pytest.raises(SolverError, match=f"more than {MAX_STEPS_PER_SAMPLE} integrator steps in "
                                          r"the sample at t = 0 s"):
        simulate(system, 0)
    blow_up = _pendulum(lambda ops, x, u, p: [x[0] * x[0] + 0 * x[1], 0 * x[0] + u[0]], x0=(1.0, 0.0))
    with pytest.raises(SolverError, match="failed at t = 1 s"):  # q' = q^2 from 1: infinite at 1 s
        simulate(blow_up, 0)


@pytest.mark.parametrize("duration", [-1.0, 0.0, 0.002, float("nan"), float("inf"), 1e12])
def test_simulate_refuses_durations_out_of_range(cartpole, duration):
    with pytest.raises(DataError, match="duration"):
        simulate(cartpole, 0, duration=duration)


def test_the_stepping_is_solve_ivp_s(cartpole):
    """The integrator loop (RK45 with a step limit) gives solve_ivp's numbers bit for bit."""
    run = simulate(cartpole, 3, duration=0.1)
    x = run.x[0]
    for k in range(len(run) - 1):
        x = solve_ivp(lambda _t, s, u=run.u[k]: cartpole.f(s, u, variant="true"), (0.0, run.dt), x,
                      method="RK45", rtol=1e-10, atol=1e-12).y[:, -1]
        np.testing.assert_array_equal(run.x[k + 1], x)


def test_rk4_jacobian_by_stages_equals_casadi_ad_and_finite_differences(cartpole):
    """The chain rule through the four stages gives the step of rk4_step bit for bit and the
    Jacobian CasADi's AD takes over the whole step (to rounding), and both match central
    differences of the numpy step."""
    import casadi as cs

    from learnest_codegen.export import prior_model
    from learnest_codegen.integrators import rk4_step_jacobian

    model = prior_model(cartpole)
    x, u = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    xdot = model.f_continuous(x, u)
    f_jac = cs.Function("f_jac", [x, u], [xdot, cs.jacobian(xdot, x)])
    step, jac = rk4_step_jacobian(f_jac, x, u, model.dt, cs.SX.eye(model.nx))
    chained = cs.Function("c", [x, u], [step, jac])
    whole = cs.Function("w", [x, u], [model.F(x, u), cs.jacobian(model.F(x, u), x)])
    rng = np.random.default_rng(3)
    for _ in range(5):
        xv, uv = rng.normal(size=model.nx), rng.normal(size=model.nu)
        (s1, j1), (s2, j2) = (tuple(np.array(v) for v in fn(xv, uv)) for fn in (chained, whole))
        np.testing.assert_array_equal(s1, s2)
        np.testing.assert_allclose(j1, j2, rtol=1e-12, atol=1e-14)
        h = 1e-6
        fd = np.column_stack([(model.step(xv + h * e, uv) - model.step(xv - h * e, uv)) / (2 * h)
                              for e in np.eye(model.nx)])
        np.testing.assert_allclose(j1, fd, rtol=1e-6, atol=1e-8)
