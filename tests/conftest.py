"""Shared fixtures (one simulated cartpole training run and test run per session) and the
tolerance rule of tests/README.md (:func:`rounding`)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from learnest_codegen import get_system
from learnest_codegen.simulation import simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from figures import load_file  # noqa: E402,F401  (the examples' loader, one for scripts and tests)


def rounding(dtype=np.float64, *, ops: int = 1, cond: float = 1.0) -> float:
    """The relative tolerance between two computations of one quantity that round differently.

    Two implementations of the same formula (numpy against C, LU against Cholesky, another BLAS,
    another summation order, a fused multiply-add or not) each land within ``ops * eps * cond``
    of the exact value: ``ops`` dependent floating-point operations of a backward-stable
    algorithm, each rounding by at most ``eps`` (the unit roundoff's bound ``n u`` of Higham,
    *Accuracy and Stability of Numerical Algorithms*, 2nd ed., sections 3.1-3.5, with ``u`` taken
    as ``eps``), amplified by the condition number ``cond`` of the problem. Two of them differ
    by at most twice that. ``dtype`` is the precision the computation runs in (float32 and
    float64 apart: float32's eps is 1.2e-7, float64's 2.2e-16).
    """
    return 2.0 * ops * float(np.finfo(dtype).eps) * cond


def unscented_rounding(Wm, Wc, dtype=np.float64, *, gain: float = 1.0) -> float:
    """The relative tolerance, to the largest entry of the compared state or covariance, between
    two implementations of one unscented-transform step with weights ``Wm``, ``Wc``.

    Each moment is a weighted sum over the ``2n + 1`` sigma points of values no larger than the
    state's (or covariance's) scale, after a Cholesky factor (``n`` operations into an entry)
    and a few more operations: ``3n + 2`` in all. The weights' absolute sum is the sum's
    condition number (at alpha 0.1 and n = 4: W0 = -99 against 12.5, so 199). ``gain`` is the
    amplification of what follows the transform (a Kalman update's, see tests/test_ukf.py).
    """
    n = (len(Wm) - 1) // 2
    cond = max(np.abs(Wm).sum(), np.abs(Wc).sum()) * gain
    return rounding(dtype, ops=3 * n + 2, cond=cond)


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


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist: without it, never called
def pytest_xdist_make_scheduler(config, log):
    """Under pytest-xdist, every other test goes to whichever worker is free, but the blocks of
    one docs page (tests/test_readme.py) go to one worker, in the page's order: a page's blocks
    build on each other (the files it asks the reader to write, the folder of the block before)."""
    from xdist.scheduler import LoadScopeScheduling

    class PageScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            head, sep, rest = nodeid.partition("test_readme.py::test_block_runs_as_written[")
            return f"{head}{sep}{rest.rsplit(':', 1)[0]}" if sep else nodeid

    return PageScheduling(config, log)
