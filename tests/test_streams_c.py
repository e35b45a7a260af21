"""Real sensor streams in the compiled estimators: each C library equals its Python reference.

On a linear-Gaussian model (two rates and a dropout, started 3 standard deviations off with the
initial covariance, so the MHEs carry their first prior's covariance forward) and on the KNODE
cartpole (a fixture model, missing outputs, a wrong start and a few implausible inputs), the
compiled UKF and EKF equal the Python UKF and EKF to 1e-9, the compiled Ipopt MHE and the Gauss-Newton MHE
equal the Python MHE at their solver tolerances, and the float32 builds equal them to what
float32 holds (stated per test). The input check: a non-finite or out-of-range ``u`` is replaced
by the held one in C as in Python (status bit 2), and the per-step statuses agree.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from test_streams import linear_matrices, masked_data, oscillator

from learnest_codegen import get_system
from learnest_codegen.compilation import compile_estimators, estimator_dir, estimator_kind
from learnest_codegen.estimators.ukf import UKF
from learnest_codegen.export import prior_model
from learnest_codegen.pipeline import resolve

MODEL_DIR = Path(__file__).parent / "data" / "model_b12bfa1"
#: (estimator, precision) -> absolute tolerance on every estimate, in units of the largest
#: |x|: UKF and EKF 1e-9 (the same arithmetic in another order); Ipopt MHE C vs Python nlpsol: the
#: same solver and problem; Gauss-Newton vs Ipopt: both converged to their tolerances;
#: float32: its 7 digits through the carried covariance's inverse.
TOLERANCE = {("ukf", "float64"): 1e-9, ("mhe", "float64"): 1e-6, ("mhe_gn", "float64"): 1e-5,
             ("ekf", "float64"): 1e-9, ("ukf", "float32"): 2e-3, ("mhe_gn", "float32"): 2e-3,
             ("ekf", "float32"): 2e-3}
BUILDS = {p: tuple(n for n, q in TOLERANCE if q == p) for p in ("float64", "float32")}


def reference_of(name: str, model, settings=None):
    """The Python estimator the compiled ``name`` is compared with (the table's reference)."""
    python = estimator_kind(estimator_kind(name).reference[0]).python
    return python(model) if settings is None else python(model, dataclasses.replace(settings))


def _steps(est, U, Y, x0, P0):
    """Step through a run (``run``'s convention) recording estimates and statuses."""
    est.reset(x0, P0)
    X, status = np.empty((len(Y), len(x0))), np.empty(len(Y), dtype=int)
    for k in range(len(Y)):
        X[k] = est.step(U[max(k - 1, 0)], Y[k])
        status[k] = est.last_status
    return X, status


@pytest.fixture(scope="module")
def linear(tmp_path_factory):
    system = oscillator()
    model, A, B, C = linear_matrices(system)
    U, Y = masked_data(system, A, B, C)
    out = tmp_path_factory.mktemp("streams_c")
    built = {}
    for precision, names in BUILDS.items():
        compile_estimators(model, out, model_hash="linear", estimators=names, precision=precision)
        for name in names:
            built[name, precision] = estimator_kind(name).compiled(
                estimator_dir(out, model, name, precision))
    return system, model, U, Y, built


@pytest.mark.parametrize("name, precision", list(TOLERANCE))
def test_compiled_equals_python_with_missing_outputs_and_a_wrong_start(linear, name, precision):
    """Missing outputs at two rates, a dropout of every output, a start 3 sigma off with P0 the
    initial covariance: the compiled estimator's estimates equal the Python reference's."""
    system, model, U, Y, built = linear
    std = np.asarray(system.noise.initial_std)
    x0, P0 = np.asarray(system.x0) + 3 * std * np.array([1.0, -1.0]), np.diag(std ** 2)
    reference = reference_of(name, model)
    X_py, s_py = _steps(reference, U, Y, x0, P0)
    X_c, s_c = _steps(built[name, precision], U, Y, x0, P0)
    scale = np.abs(X_py).max()
    assert np.max(np.abs(X_c - X_py)) <= TOLERANCE[name, precision] * scale, \
        np.max(np.abs(X_c - X_py)) / scale
    np.testing.assert_array_equal(s_c, s_py)
    if estimator_kind(name).horizon:  # the first prior's covariance was carried, then settled (Python and C)
        np.testing.assert_allclose(built[name, precision].arrival_weight, reference.arrival_weight,
                                   rtol=1e-6 if precision == "float64" else 2e-2)


def test_compiled_input_check_equals_python(linear):
    """A NaN, an infinite and a finite input in C: replaced by the held one (no limits on this
    system: only finiteness) exactly as in Python, status bit 2, counted."""
    system, model, U, Y, built = linear
    U = U.copy()
    U[10, 0], U[11, 0], U[30, 0] = np.nan, np.inf, -np.inf
    reference = UKF(model)
    X_py, s_py = _steps(reference, U, Y, np.asarray(system.x0, float), None)
    est = built["ukf", "float64"]
    X_c, s_c = _steps(est, U, Y, np.asarray(system.x0, float), None)
    np.testing.assert_allclose(X_c, X_py, rtol=0, atol=1e-9 * np.abs(X_py).max())
    np.testing.assert_array_equal(s_c, s_py)
    assert [k for k in range(len(s_c)) if s_c[k] & 2] == [11, 12, 31]
    assert est.input_rejections == reference.input_rejections == 3


@pytest.fixture(scope="module")
def knode(tmp_path_factory):
    system = get_system("cartpole")
    resolved = resolve(str(MODEL_DIR), system)
    out = tmp_path_factory.mktemp("streams_knode")
    built = {}
    for precision, names in BUILDS.items():
        compile_estimators(resolved.model, out, model_hash=resolved.hash, estimators=names,
                           precision=precision)
        for name in names:
            built[name, precision] = estimator_kind(name).compiled(
                estimator_dir(out, resolved.model, name, precision))
    return system, resolved.model, built


def knode_stream(system, T: int = 250):
    """The cartpole run with the angle at a quarter rate, a 0.05 s dropout of the position and
    three implausible inputs (beyond the +-50 N limits, NaN)."""
    from learnest_codegen.simulation import simulate

    run = simulate(system, seed=1, duration=T * system.dt)
    U, Y = run.u[:T].copy(), run.y[:T].copy()
    Y[np.arange(T) % 4 != 0, 1] = np.nan
    Y[100:125, 0] = np.nan
    U[60, 0], U[61, 0], U[150, 0] = 1e3, np.nan, -1e6
    return U, Y


@pytest.mark.slow  # seven KNODE builds (the Ipopt MHE's takes minutes on a loaded machine)
@pytest.mark.parametrize("name, precision", list(TOLERANCE))
def test_compiled_knode_equals_python_on_a_stream(knode, name, precision):
    """The KNODE cartpole fixture on a multi-rate stream with a dropout, implausible inputs
    and a start 3 sigma off: the compiled estimator equals the Python reference."""
    system, model, built = knode
    U, Y = knode_stream(system)
    std = np.asarray(system.noise.initial_std)
    x0 = np.asarray(system.x0) + 3 * std * np.array([1.0, -1.0, 1.0, -1.0])
    settings = built[name, precision].settings
    reference = reference_of(name, model, settings)
    X_py, s_py = _steps(reference, U, Y, x0, np.diag(std ** 2))
    X_c, s_c = _steps(built[name, precision], U, Y, x0, np.diag(std ** 2))
    scale = np.abs(X_py).max()
    tol = TOLERANCE[name, precision] * (10 if estimator_kind(name).horizon else 1)  # a nonlinear NLP
    assert np.max(np.abs(X_c - X_py)) <= tol * scale, np.max(np.abs(X_c - X_py)) / scale
    np.testing.assert_array_equal(s_c & 2, s_py & 2)  # the same inputs replaced
    assert reference.input_rejections == built[name, precision].input_rejections == 3


def test_nominal_prior_model_has_the_cartpole_limits_compiled_in(tmp_path):
    """The generated header holds the system's input limits; a build without them checks
    only finiteness."""
    system = get_system("cartpole")
    model = prior_model(system)
    gen = compile_estimators(model, tmp_path, model_hash="nominal", estimators=("ukf",))["ukf"]
    header = gen.header_path.read_text()
    P = gen.prefix.upper()
    assert f"#define {P}_INPUT_LO {{-50.0}}" in header and f"#define {P}_INPUT_HI {{50.0}}" in header
    settings = dataclasses.replace(estimator_kind("ukf").default_settings(model), input_limits=None)
    other = compile_estimators(model, tmp_path / "free", model_hash="nominal", estimators=("ukf",),
                               settings={"ukf": settings})["ukf"]
    assert "No input limits" in other.header_path.read_text()
    est = estimator_kind("ukf").compiled(other.directory)
    est.reset(np.asarray(system.x0, float))
    est.step(np.array([1e3]), np.zeros(2) + np.nan)
    assert est.last_status == 0 and est.input_rejections == 0
    bounded = estimator_kind("ukf").compiled(gen.directory)
    bounded.reset(np.asarray(system.x0, float))
    bounded.step(np.array([1e3]), np.zeros(2) + np.nan)
    assert bounded.last_status == 2 and bounded.input_rejected.tolist() == [True]
