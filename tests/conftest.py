"""Shared fixtures: one simulated cartpole training run and test run per session."""

from __future__ import annotations

import pytest

from learnest_codegen import get_system
from learnest_codegen.simulation import simulate


@pytest.fixture(scope="session")
def cartpole():
    return get_system("cartpole")


@pytest.fixture(scope="session")
def cartpole_run(cartpole):
    return simulate(cartpole, seed=0)


@pytest.fixture(scope="session")
def cartpole_test_run(cartpole):
    return simulate(cartpole, seed=1)


# The README's "your own system" example, as a user would write it in their own file.
USER_SYSTEM = '''
import numpy as np
from learnest_codegen import NoiseModel, Signal, System

def dynamics(ops, x, u, p):
    q, qdot = x
    return [qdot, -p["k"] * ops.sin(q) - p["c"] * qdot + u[0]]

SYSTEM = System(
    name="my_pendulum",
    states=(Signal("q", "rad"), Signal("qdot", "rad/s")),
    inputs=(Signal("tau", "N m"),),
    outputs=(Signal("q", "rad"),),
    params={"k": 9.0, "c": 0.0},
    true_params={"k": 9.0, "c": 0.3},
    dynamics=dynamics,
    measurement=lambda ops, x, u, p: [x[0]],
    noise=NoiseModel(measurement_std=(0.01,), state_std=(0.01, 0.01),
                     process_std=(1e-3, 1e-2), initial_std=(0.1, 0.1)),
    dt=0.01, duration=5.0, x0=(0.5, 0.0),
    excitation=lambda t, rng: np.sin(2 * t)[:, None],
    periodic_states=("q",),
)
'''


@pytest.fixture
def user_system_file(tmp_path):
    """The README's pendulum written to ``tmp_path/my_pendulum.py``."""
    path = tmp_path / "my_pendulum.py"
    path.write_text(USER_SYSTEM)
    return path
