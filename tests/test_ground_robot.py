"""The ground robot of the paper's eq. (14): model, simulation, two-stage observer, UKF."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from conftest import rounding

from learnest_codegen import get_system
from learnest_codegen.estimators.ukf import UKF, UKFSettings
from learnest_codegen.export import prior_model, true_model
from learnest_codegen.observers import observe
from learnest_codegen.simulation import simulate
from learnest_codegen.systems.ground_robot import BEACONS

L_F, L_R, M, S, RHO, C_D = 0.18, 0.15, 1.5, 0.06, 1.225, 1.05  # the documented values


@pytest.fixture(scope="module")
def robot():
    return get_system("ground_robot")


@pytest.fixture(scope="module")
def run(robot):
    """10 s of seed 0: long enough for the observers' tuning and for two thirds of a loop."""
    return simulate(robot, seed=0, duration=10.0)


@pytest.fixture(scope="module")
def observations(robot, run):
    return {m: observe(run, robot, m) for m in ("ukf_kf", "ukf_rts")}


def random_points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    x = np.c_[rng.uniform(-12, 12, (n, 2)), rng.uniform(-4, 4, n), rng.uniform(-7, 7, n)]
    u = np.c_[rng.uniform(-3, 3, n), rng.uniform(-0.6, 0.6, n)]
    return x, u


@pytest.mark.parametrize("variant", ["prior", "true"])
def test_numpy_torch_casadi_agree(robot, variant):
    x, u = random_points()
    f_np = robot.f(x, u, variant=variant)
    f_torch = robot.f(torch.tensor(x), torch.tensor(u), variant=variant).numpy()
    f_cs = robot.casadi_f(variant).map(len(x))(x.T, u.T).full().T
    np.testing.assert_allclose(f_torch, f_np, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(f_cs, f_np, rtol=1e-12, atol=1e-12)
    h_np = robot.h(x, u)
    np.testing.assert_allclose(robot.h(torch.tensor(x), torch.tensor(u)).numpy(), h_np,
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(robot.casadi_h().map(len(x))(x.T, u.T).full().T, h_np,
                               rtol=1e-12, atol=1e-12)


def test_closed_form_dynamics_and_measurement(robot):
    """Eq. (14) and the ranges written out independently, and the residual is exactly the drag."""
    x, u = random_points(seed=1)
    px, py, v, psi = x.T
    a, delta = u.T
    beta = np.arctan(L_R * np.tan(delta) / (L_F + L_R))
    prior = np.c_[v * np.cos(psi + beta), v * np.sin(psi + beta), a,
                  v * np.cos(beta) * np.tan(delta) / (L_F + L_R)]
    np.testing.assert_allclose(robot.f(x, u), prior, rtol=1e-13, atol=1e-13)
    drag = 0.5 * RHO * S * C_D * v * np.abs(v) / M
    true = robot.f(x, u, variant="true")
    residual = true - robot.f(x, u)
    # (a - drag) - a against -drag: two roundings on the scale of |a| + drag (a cancellation),
    # and the drag's own five factors multiplied in another order
    scale = np.abs(true).max() + np.abs(drag).max()
    np.testing.assert_allclose(residual, np.c_[0 * v, 0 * v, -drag, 0 * v], rtol=0,
                               atol=rounding(ops=2 + 5) * scale)
    assert 0.2 < 0.5 * RHO * S * C_D * 3.0**2 / M < 0.3  # ~0.23 m/s^2 at 3 m/s, as documented
    ranges = np.stack([np.hypot(px - bx, py - by) for bx, by in BEACONS], axis=1)
    np.testing.assert_allclose(robot.h(x, u), np.c_[ranges, psi], rtol=1e-14, atol=1e-14)


def test_constant_steering_drives_a_circle(robot):
    """Constant speed and steering: the centre of gravity moves on a circle of radius
    R = (l_f + l_r) / (cos(beta) tan(delta)) at yaw rate v / R (prior: no drag, a = 0)."""
    v, delta, T = 2.0, 0.3, 400
    beta = np.arctan(L_R * np.tan(delta) / (L_F + L_R))
    radius = (L_F + L_R) / (np.cos(beta) * np.tan(delta))
    steady = dataclasses.replace(robot, excitation=lambda t, rng: np.tile([0.0, delta], (len(t), 1)))
    x = simulate(steady, 0, variant="prior", duration=T * robot.dt, x0=np.array([0, 0, v, 0])).x
    # The velocity points at psi + beta, so the centre lies at angle psi + beta + pi/2.
    centre = np.array([-radius * np.sin(beta), radius * np.cos(beta)])
    np.testing.assert_allclose(np.hypot(*(x[:, :2] - centre).T), radius, rtol=1e-8)
    np.testing.assert_allclose(x[:, 3], v / radius * robot.dt * np.arange(T), rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(x[:, 2], v, rtol=1e-12)


@pytest.mark.parametrize("seed", [3, 11])
def test_simulated_runs_stay_in_the_beacon_area(robot, seed):
    run = simulate(robot, seed)
    assert run.x.shape == (2500, 4) and run.u.shape == (2500, 2) and run.y.shape == (2500, 5)
    assert np.all(np.abs(run.x[:, :2]) < 9.0)  # beacons at +-10 m
    assert 0.7 < run.x[:, 2].min() and run.x[:, 2].max() < 3.7
    assert np.abs(run.u[:, 1]).max() < np.deg2rad(30.0)  # a realistic steering range
    # Measurement noise as documented: 0.05 m on ranges, 1 deg on the heading.
    noise = run.y - robot.h(run.x, run.u)
    np.testing.assert_allclose(noise.std(axis=0), [0.05] * 4 + [np.deg2rad(1.0)], rtol=0.1)


def test_observer_accuracy(run, observations):
    """Thresholds ~2x the errors measured on this run; the smoother must beat the filter."""
    err = {m: np.mean((o.zeta[100:] - run.x[100:]) ** 2, axis=0) for m, o in observations.items()}
    kf, rts = err["ukf_kf"], err["ukf_rts"]
    print(f"observer MSE (x, y, v, psi): ukf_kf {kf}, ukf_rts {rts}")
    assert np.all(rts[:2] < 1.5e-4) and rts[2] < 1e-3 and rts[3] < 3e-5
    assert np.all(kf[:2] < 5e-4) and kf[2] < 5e-2 and kf[3] < 1e-4
    assert np.all(rts < kf)
    assert rts[2] < kf[2] / 10  # speed: the smoother uses the whole run


def test_observer_needs_a_planar_pose(robot, run, cartpole, cartpole_run):
    with pytest.raises(ValueError, match="planar pose"):
        observe(cartpole_run, cartpole, "ukf_kf")
    with pytest.raises(ValueError, match="planar_pose .* must name four states"):
        dataclasses.replace(robot, planar_pose=("x", "y", "speed", "psi"))


def test_ukf_with_true_model_beats_prior(robot):
    """Over 5 s the drag (up to ~0.3 m/s^2 here) is what separates the two models."""
    run = simulate(robot, seed=2, duration=5.0)
    mse = {}
    for model in (prior_model(robot), true_model(robot)):
        x_hat = UKF(model, UKFSettings.from_system(robot)).run(run.u, run.y, robot.x0)
        mse[model.kind] = np.mean((x_hat - run.x) ** 2, axis=0)
    print(f"UKF MSE per state: {mse}")
    assert mse["true"].mean() < 2e-4
    assert mse["true"].mean() * 5 < mse["nominal"].mean()
    assert mse["true"][2] * 5 < mse["nominal"][2]  # the speed, where the drag acts
