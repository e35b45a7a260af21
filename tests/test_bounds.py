"""State bounds in the MHEs (``MHESettings.state_bounds``; the kit's ``learnest_bounds.h``).

The cartpole on a rail of +-0.85 m (the simulated cart reaches -0.838 m on this run) with
position outliers of -0.5 m while it is near the end of the rail, and the gate off so that
they reach the estimate: the unbounded MHE then puts the cart past the rail, every bounded
MHE keeps every state of every window inside the box, and the compiled ones equal the bounded
Python MHE (Ipopt's bounded solution). With bounds that are never active the estimates are
those of the unbounded build.

Tolerances: the converged Gauss-Newton MHE and the compiled Ipopt MHE against the Python
Ipopt MHE 1e-6 absolute on every state (both solve the bounded problem to convergence;
measured 1.4e-8 and 1.3e-9); inactive bounds: the Gauss-Newton MHE bit for bit (the same
arithmetic: no variable is held or clamped), the Ipopt MHE 1e-8 (its bounded options change
the barrier's path, not the minimiser).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import learnest_codegen as ln
from learnest_codegen.errors import SettingsError, ShapeError
from learnest_codegen.estimators.gate import GateSettings
from learnest_codegen.estimators.mhe import MHE
from learnest_codegen.estimators.mhe_problem import MHESettings

RAIL = 0.85
OPEN = (None, None)


@pytest.fixture(scope="module")
def stream(cartpole):
    run = ln.simulate(cartpole, seed=1, duration=1.3)
    Y = run.y.copy()
    near = np.where(run.x[:, 0] < -0.75)[0]
    Y[near[::15], 0] -= 0.5  # outliers towards the end of the rail
    assert run.x[:, 0].min() > -RAIL
    return run, Y


def settings(cartpole, bounds=None):
    base = MHESettings.from_system(cartpole, horizon=10, gate=GateSettings(threshold=0))
    return dataclasses.replace(base, state_bounds=bounds)


@pytest.fixture(scope="module")
def model(cartpole):
    return ln.resolve("nominal", cartpole).model


@pytest.fixture(scope="module")
def ipopt(cartpole, model, stream):
    """The Python MHE (Ipopt) unbounded and on the rail: estimates and every window."""
    run, Y = stream
    out = {}
    for key, bounds in (("free", None), ("rail", ((-RAIL, RAIL), OPEN, OPEN, OPEN))):
        est = MHE(model, settings(cartpole, bounds))
        out[key] = windows(est, run, Y, cartpole)
    return out


def windows(est, run, Y, cartpole):
    """``(X (T, nx), the smallest position of any window state)`` of a stepped run."""
    est.reset(cartpole.x0)
    X, lowest = [], np.inf
    for k in range(len(Y)):
        X.append(est.step(run.u[max(k - 1, 0)], Y[k]))
        lowest = min(lowest, float(np.min(est.window[:, 0])))
    return np.array(X), lowest


def test_outliers_push_the_unbounded_estimate_off_the_rail_and_ipopt_keeps_it_on(ipopt):
    assert ipopt["free"][1] < -RAIL - 0.02
    assert ipopt["rail"][1] >= -RAIL


@pytest.mark.parametrize("name, precision, tolerance", [
    ("mhe_gn", "float64", 1e-6), ("mhe", "float64", 1e-6),
    ("mhe_rti", "float64", None), ("mhe_gn", "float32", None), ("mhe_rti", "float32", None)])
def test_compiled_mhes_stay_on_the_rail_and_equal_ipopt(ipopt, cartpole, stream, tmp_path, name,
                                                         precision, tolerance):
    """Every window state of every step inside the box (float32: the nearest floats inside);
    the converged MHEs equal Ipopt's bounded solution."""
    run, Y = stream
    est = ln.compile_estimator("nominal", name, system=cartpole, out=tmp_path, precision=precision,
                               settings=settings(cartpole, ((-RAIL, RAIL), OPEN, OPEN, OPEN)))
    X, lowest = windows(est, run, Y, cartpole)
    assert lowest >= -RAIL
    if tolerance is not None:
        assert np.abs(X - ipopt["rail"][0]).max() <= tolerance, np.abs(X - ipopt["rail"][0]).max(0)


def test_inactive_bounds_change_nothing(cartpole, model, stream, tmp_path):
    run, Y = stream
    wide = ((-100.0, 100.0), (-1e3, 1e3), OPEN, OPEN)
    X = {}
    for key, bounds in (("free", None), ("wide", wide)):
        est = ln.compile_estimator("nominal", "mhe_gn", system=cartpole, out=tmp_path / key,
                                   settings=settings(cartpole, bounds))
        X[key] = est.run(run.u, Y, cartpole.x0)
    np.testing.assert_array_equal(X["wide"], X["free"])
    T = 200
    free = MHE(model, settings(cartpole)).run(run.u[:T], Y[:T], cartpole.x0)
    boxed = MHE(model, settings(cartpole, wide)).run(run.u[:T], Y[:T], cartpole.x0)
    assert np.abs(boxed - free).max() <= 1e-8


def test_bounds_are_checked(cartpole, model):
    with pytest.raises(SettingsError, match="lo < hi"):
        settings(cartpole, ((1.0, -1.0), OPEN, OPEN, OPEN))
    with pytest.raises(ShapeError, match="4 \\(lo, hi\\) pairs"):
        MHE(model, settings(cartpole, ((-1.0, 1.0),)))
    s = settings(cartpole, ((-RAIL, None), OPEN, OPEN, OPEN))
    assert s.to_json()["state_bounds"][0] == [-RAIL, None]
    assert MHESettings.from_json(s.to_json()) == s
