"""Parameters estimated online (``systems/params.py``) and the arrival cost that follows the data
(``MHESettings.arrival_update``).

The cartpole whose cart mass is an augmented state with a random-walk model: the true mass
drifts 20 % over the run (1.5 kg to 1.8 kg in 10 s) while every estimator starts from the
prior's 1.0 kg with the system's initial covariance. From 1 s on each tracks it within 5 %
(measured worst: UKF 3.85 %, EKF 3.87 %, ``mhe_gn`` and ``mhe_rti`` with the arrival update
4.19 %). The compiled MHE with the arrival update equals the Python MHE with it (Ipopt) to
1e-6 on a shorter run.

A bound on the parameter (``Estimated.bounds``, here 0.8-1.1 kg while the true mass is 1.5 kg
and more, so the unbounded estimate leaves it) keeps every window state of every MHE in it, in
both precisions. The compiled Ipopt MHE equals the Python one to 1e-6. The converged
Gauss-Newton MHE sits on the bound where Ipopt stops up to 3.7e-6 inside it (the cost is flat
along the weakly observable mass: at that sample the Gauss-Newton window's cost is 5e-15 below
Ipopt's, relative 2e-8), so it is held to 1e-5 of Ipopt.
"""

from __future__ import annotations

import numpy as np
import pytest

import learnest_codegen as ln
from learnest_codegen.errors import SettingsError
from learnest_codegen.estimators.mhe import MHE
from learnest_codegen.estimators.mhe_problem import MHESettings
from learnest_codegen.pipeline import initial_covariance
from learnest_codegen.simulation import simulate
from learnest_codegen.systems.cartpole import CARTPOLE
from learnest_codegen.systems.params import Estimated, estimate_params

SYSTEM = estimate_params(CARTPOLE, {"m_c": Estimated(initial_std=0.5, drift_std=5e-4, true_rate=0.03,
                                                     unit="kg")})
BOUNDED = estimate_params(CARTPOLE, {"m_c": Estimated(initial_std=0.5, drift_std=5e-4, true_rate=0.03,
                                                      unit="kg", bounds=(0.8, 1.1))})


@pytest.fixture(scope="module")
def drifting():
    x0 = np.array(SYSTEM.x0)
    x0[4] = 1.5  # the true mass starts 50 % above the prior's
    run = simulate(SYSTEM, seed=1, x0=x0)
    assert run.x[-1, 4] / run.x[0, 4] == pytest.approx(1.2, rel=1e-3)
    return run


def test_the_declaration_augments_the_system(tmp_path):
    assert SYSTEM.name == "cartpole_m_c" and SYSTEM.state_names[-1] == "m_c"
    assert SYSTEM.x0[-1] == 1.0 and "m_c" not in SYSTEM.params and SYSTEM.nx == 5
    file = tmp_path / "cart_mass.py"
    file.write_text("from learnest_codegen.systems.cartpole import CARTPOLE\n"
                    "from learnest_codegen.systems.params import Estimated, estimate_params\n"
                    "SYSTEM = estimate_params(CARTPOLE, {'m_c': Estimated(0.5, 5e-4)})\n")
    loaded = ln.get_system(str(file))
    assert loaded.state_names == SYSTEM.state_names
    x, u = np.array([0.1, 0.2, 0.3, 0.4, 1.7]), np.array([2.0])
    np.testing.assert_allclose(loaded.f(x, u)[:4], CARTPOLE.f(x[:4], u, params={"m_c": 1.7}))
    assert loaded.f(x, u)[4] == 0
    with pytest.raises(SettingsError, match="not among the parameters"):
        estimate_params(CARTPOLE, {"mass": Estimated(0.5, 5e-4)})


@pytest.mark.parametrize("name", ["ukf", "ekf", "mhe_gn", "mhe_rti"])
def test_a_drifting_parameter_is_tracked_within_5_percent(drifting, tmp_path, name):
    settings = MHESettings.from_system(SYSTEM, arrival_update=True) if name.startswith("mhe") else None
    est = ln.make_estimator("nominal", name, system=SYSTEM, out=tmp_path, settings=settings)
    X = est.run(drifting.u, drifting.y, SYSTEM.x0, initial_covariance(SYSTEM))
    error = np.abs(X[:, 4] - drifting.x[:, 4]) / drifting.x[:, 4]
    assert error[int(1.0 / SYSTEM.dt):].max() <= 0.05


def test_compiled_arrival_update_equals_python(drifting, tmp_path):
    """The arrival carried by the EKF recursion from the start (no P0: from the running
    covariance), in C and in the Python MHE; the fixed weight gives other estimates."""
    T = 300
    U, Y = drifting.u[:T], drifting.y[:T]
    settings = MHESettings.from_system(SYSTEM, horizon=10, arrival_update=True)
    c = ln.make_estimator("nominal", "mhe_gn", system=SYSTEM, out=tmp_path, settings=settings)
    model = ln.resolve("nominal", SYSTEM).model
    X_c, X_py = c.run(U, Y, SYSTEM.x0), MHE(model, settings).run(U, Y, SYSTEM.x0)
    assert np.abs(X_c - X_py).max() <= 1e-6
    fixed = MHE(model, MHESettings.from_system(SYSTEM, horizon=10)).run(U, Y, SYSTEM.x0)
    assert np.abs(fixed - X_py).max() > 1e-3


def _windows(est, U, Y, x0):
    """``(X (T, nx), the largest mass of any window state)`` of a stepped run."""
    est.reset(x0)
    X, top = [], -np.inf
    for k in range(len(Y)):
        X.append(est.step(U[max(k - 1, 0)], Y[k]))
        top = max(top, float(np.max(est.window[:, 4])))
    return np.array(X), top


@pytest.fixture(scope="module")
def bounded_ipopt(drifting):
    T = 300
    model = ln.resolve("nominal", BOUNDED).model
    settings = MHESettings.from_system(BOUNDED, horizon=10)
    assert settings.state_bounds[4] == (0.8, 1.1)  # the system's bound is the settings' default
    free = _windows(MHE(model, MHESettings.from_system(BOUNDED, horizon=10, state_bounds=None)),
                    drifting.u[:T], drifting.y[:T], BOUNDED.x0)
    assert free[1] > 1.2  # unbounded, the mass estimate leaves the box
    return _windows(MHE(model, settings), drifting.u[:T], drifting.y[:T], BOUNDED.x0), settings


@pytest.mark.parametrize("name, precision, tolerance", [
    ("mhe", "float64", 1e-6), ("mhe_gn", "float64", 1e-5), ("mhe_rti", "float64", None),
    ("mhe_gn", "float32", None), ("mhe_rti", "float32", None)])
def test_a_parameter_bound_holds_in_every_mhe(drifting, bounded_ipopt, tmp_path, name, precision,
                                              tolerance):
    (X_ref, top_ref), settings = bounded_ipopt
    assert top_ref <= 1.1
    est = ln.make_estimator("nominal", name, system=BOUNDED, out=tmp_path, precision=precision,
                            settings=settings)
    X, top = _windows(est, drifting.u[:len(X_ref)], drifting.y[:len(X_ref)], BOUNDED.x0)
    assert top <= 1.1 and np.all(X[:, 4] >= 0.8)
    if tolerance is not None:
        assert np.abs(X - X_ref).max() <= tolerance
