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
