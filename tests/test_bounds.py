"""State bounds in the MHEs (``MHESettings.state_bounds``; the kit's ``learnest_bounds.h``).

The cartpole on a rail of +-0.85 m (the simulated cart reaches -0.838 m on this run) with
position outliers of -0.5 m while it is near the end of the rail, and the gate off so that
they reach the estimate: the unbounded MHE then puts the cart past the rail, every bounded
MHE keeps every state of every window inside the box, and the compiled ones equal the bounded
Python MHE (Ipopt's bounded solution). With bounds that are never active the estimates are
those of the unbounded build.

Tolerances: the converged Gauss-Newton MHE and the compiled Ipopt MHE against the Python
Ipopt MHE 1e-6 absolute on every state (both solve the bounded problem to convergence;
measured 1.4e-8 and 1.3e-9). The real-time iteration takes one Gauss-Newton step a sample, so
it is off the converged MHE by its linearisation (1.09e-6 on this run without bounds); its
bounded step solves the step's bounded quadratic program exactly, so with bounds it is as far
from Ipopt's bounded solution as it is without them from Ipopt's unbounded one (measured: the
two differ by 4e-11; asserted 1e-8). float32: the same comparison to 1e-6 (float32's
resolution at these states' size; measured 2e-11). Inactive bounds: the Gauss-Newton MHE bit
for bit (the same arithmetic: no variable is held or clamped), the Ipopt MHE 1e-8 (its
bounded options change the barrier's path, not the minimiser).
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
    the converged MHEs equal Ipopt's bounded solution; the others are as close to it as their
    unbounded builds are to Ipopt's unbounded solution (the bounds add no error of their own)."""
    run, Y = stream
    est = ln.make_estimator("nominal", name, system=cartpole, out=tmp_path / "rail", precision=precision,
                            settings=settings(cartpole, ((-RAIL, RAIL), OPEN, OPEN, OPEN)))
    X, lowest = windows(est, run, Y, cartpole)
    assert lowest >= -RAIL
    off = np.abs(X - ipopt["rail"][0]).max()
    if tolerance is not None:
        assert off <= tolerance, np.abs(X - ipopt["rail"][0]).max(0)
        return
    free = ln.make_estimator("nominal", name, system=cartpole, out=tmp_path / "free", precision=precision,
                             settings=settings(cartpole))
    X_free, lowest_free = windows(free, run, Y, cartpole)
    assert lowest_free < -RAIL  # the bound is active on this run
    own = np.abs(X_free - ipopt["free"][0]).max()
    assert off <= own + (1e-8 if precision == "float64" else 1e-6), (off, own)


def test_inactive_bounds_change_nothing(cartpole, model, stream, tmp_path):
    run, Y = stream
    wide = ((-100.0, 100.0), (-1e3, 1e3), OPEN, OPEN)
    X = {}
    for key, bounds in (("free", None), ("wide", wide)):
        est = ln.make_estimator("nominal", "mhe_gn", system=cartpole, out=tmp_path / key,
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
