"""The C API every generated estimator shares (docs/guide/c_api.md), in all four estimators and both
precisions: missing outputs, predict, run-time tuning, bounded options, the fingerprint, and
two estimators of different precisions, and two horizons of one MHE, in one program.

References: a sample with every output missing is a prediction (the UKF's CasADi predict
function; the MHEs' window then holds F's predictions); a missing output is the references'
masked update (FilterPy's update on the outputs present, the Python MHE with weight 0);
``set_noise`` equals the reference's own ``set_noise`` on the same run.
"""

from __future__ import annotations

import ctypes
import json
import shutil
import subprocess

import numpy as np
import pytest
from conftest import unscented_rounding

import learnest_codegen as ln
from learnest_codegen.codegen.ukf import merwe_weights, ukf_predict_function
from learnest_codegen.compilation import compile_estimators, estimator_kind
from learnest_codegen.errors import DataError, ModelMismatchError, SolverError
from learnest_codegen.export import prior_model
from learnest_codegen.pipeline import load_estimator
from learnest_codegen.runtime.manifest import GeneratedEstimator
from learnest_codegen.runtime.status import STATUS_NAMES

CODES = {name: code for code, name in STATUS_NAMES.items()}
BUILDS = [("ukf", "float64"), ("mhe", "float64"), ("mhe_gn", "float64"), ("mhe_rti", "float64"),
          ("ekf", "float64"), ("ukf", "float32"), ("mhe_rti", "float32"), ("ekf", "float32")]
T = 150
# C against the Python reference of the same estimator: the UKF and the EKF are FilterPy's
# arithmetic; the converged MHEs solve the same NLP; RTI takes one Gauss-Newton step a sample.
REFERENCE_ATOL = {"ukf": 1e-9, "ekf": 1e-9, "mhe": 1e-6, "mhe_gn": 1e-6, "mhe_rti": 1e-4}


@pytest.fixture(scope="module")
def model(cartpole):
    return prior_model(cartpole)


@pytest.fixture(scope="module")
def folders(model, tmp_path_factory):
    root = tmp_path_factory.mktemp("c_api")
    out = {}
    for name, precision in BUILDS:
        out[name, precision] = compile_estimators(model, root, model_hash="nominal", estimators=(name,),
                                                  precision=precision)[name].directory
    return out


@pytest.fixture(scope="module")
def run(cartpole):
    data = ln.simulate(cartpole, seed=5, duration=T * cartpole.dt)
    valid = np.random.default_rng(0).random(data.y.shape) < 0.6
    valid[60:80] = False  # twenty samples without any output
    return data, valid


def reference(name, model, settings):
    """The Python reference of ``name`` (the table's) with the compiled estimator's ``settings``."""
    return estimator_kind(estimator_kind(name).reference[0]).python(model, settings)


@pytest.mark.parametrize("name, precision", BUILDS, ids=lambda v: str(v))
def test_missing_outputs_equal_the_masked_reference(folders, model, run, cartpole, name, precision):
    """Outputs missing at random (NaN in y), and twenty samples without any: the C estimate
    equals the Python reference given the same validity (float32: within its round-off)."""
    data, valid = run
    Y = np.where(valid, data.y, np.nan)
    est = load_estimator(folders[name, precision])
    X_c = est.run(data.u, Y, cartpole.x0, valid=valid)
    X_ref = reference(name, model, est.settings).run(data.u, Y, cartpole.x0, valid=valid)
    atol = REFERENCE_ATOL[name] if precision == "float64" else 5e-3
    np.testing.assert_allclose(X_c, X_ref, rtol=0, atol=atol)
    np.testing.assert_array_equal(est.run(data.u, Y, cartpole.x0), X_c)  # NaN alone marks missing
    with pytest.raises(DataError, match="non-finite"):  # NaN in a valid output is still an error
        est.run(data.u, Y, cartpole.x0, valid=np.ones_like(valid))
    with pytest.raises(DataError, match="non-finite"):  # infinity is never a missing output
        est.run(data.u, np.where(valid, data.y, np.inf), cartpole.x0)


@pytest.mark.parametrize("name, precision", BUILDS, ids=lambda v: str(v))
def test_predict_is_a_step_without_outputs(folders, run, cartpole, name, precision):
    """predict(u) equals step(u, y, none valid) bit for bit, and k of them after a clean start
    leave the estimate where the model's prediction puts it."""
    data, _ = run
    a, b = load_estimator(folders[name, precision]), load_estimator(folders[name, precision])
    for est in (a, b):
        est.reset(cartpole.x0)
        for k in range(30):
            est.step(data.u[max(k - 1, 0)], data.y[k])
    for k in range(30, 40):
        xa = a.predict(data.u[k - 1])
        xb = b.step(data.u[k - 1], np.full(2, np.nan))  # NaN: missing (the run format's convention)
        np.testing.assert_array_equal(xa, xb)
    assert a.samples == b.samples == 40 and a.last_status == 0


def test_ukf_k_missing_samples_are_k_predictions(folders, model, run, cartpole):
    """The compiled UKF's k steps without an output equal k applications of its predict
    (FilterPy's, as a CasADi function) to the state and covariance, to the rounding of k
    unscented transforms (``unscented_rounding``, relative to the largest entry)."""
    data, _ = run
    ukf = load_estimator(folders["ukf", "float64"])
    ukf.reset(cartpole.x0)
    for k in range(20):
        ukf.step(data.u[max(k - 1, 0)], data.y[k])
    predict = ukf_predict_function(model, ukf.settings)
    Wm, Wc, _ = merwe_weights(model.nx, ukf.settings)
    x, P = ukf.x, ukf.P
    for k in range(1, 11):
        x, P = (np.array(v) for v in predict(x, P, data.u[k + 18], ukf.settings.Q()))
        ukf.predict(data.u[k + 18])
        tol = unscented_rounding(Wm, Wc, gain=k)
        np.testing.assert_allclose(ukf.x, x.ravel(), rtol=0, atol=tol * np.abs(x).max())
        np.testing.assert_allclose(ukf.P, P, rtol=0, atol=tol * np.abs(P).max())


@pytest.mark.parametrize("name", ["mhe", "mhe_gn"])
def test_mhe_k_missing_samples_are_k_predictions(folders, model, run, cartpole, name):
    """After k samples without an output the window's last k states are F's predictions of
    their predecessors (those stages carry only their process term, solved to convergence)."""
    data, _ = run
    est = load_estimator(folders[name, "float64"])
    est.reset(cartpole.x0)
    for k in range(30):
        est.step(data.u[max(k - 1, 0)], data.y[k])
    for k in range(30, 36):
        est.predict(data.u[k - 1])
    X = est.window
    for i, k in enumerate(range(30, 36)):
        predicted = model.step(X[-7 + i], data.u[k - 1])
        np.testing.assert_allclose(X[-6 + i], predicted, rtol=0, atol=1e-7)


@pytest.mark.parametrize("name, precision", BUILDS, ids=lambda v: str(v))
def test_set_noise_keeps_the_state_and_equals_the_reference(folders, model, run, cartpole, name,
                                                            precision):
    """Q and R change on a running estimator: its state (and covariance or window) stay, and
    the following estimates equal the reference's that changed them at the same sample."""
    data, _ = run
    est = load_estimator(folders[name, precision])
    ref = reference(name, model, est.settings)
    for e in (est, ref):
        e.reset(cartpole.x0)
        for k in range(40):
            e.step(data.u[max(k - 1, 0)], data.y[k])
    before = est.window if estimator_kind(name).horizon else est.P
    Q, R = np.diag(np.square(cartpole.noise.process_std)) * 4, np.eye(2) * 4e-4
    x = est.x
    est.set_noise(Q, R)
    ref.set_noise(Q, R)
    np.testing.assert_array_equal(est.x, x)
    np.testing.assert_array_equal(est.window if estimator_kind(name).horizon else est.P, before)
    atol = REFERENCE_ATOL[name] if precision == "float64" else 5e-3
    for k in range(40, 80):
        np.testing.assert_allclose(est.step(data.u[k - 1], data.y[k]), ref.step(data.u[k - 1], data.y[k]),
                                   rtol=0, atol=atol)
    with pytest.raises(DataError, match="positive (semi)?definite"):  # the MHEs invert Q
        est.set_noise(Q=-Q)
    with pytest.raises(DataError, match=f"outside the range a covariance takes in {precision}"):
        est.set_noise(R=1e-300 * np.eye(2))  # the UKF drifted to an error of 9-12 on it
    with pytest.raises(DataError, match="positive definite"):
        est.set_noise(R=np.zeros((2, 2)))


def test_set_arrival_on_a_running_mhe(folders, model, run, cartpole):
    """The arrival covariance changes from the next step on, the window stays, and the C
    follows the Python MHE that changed it at the same sample."""
    data, _ = run
    est = load_estimator(folders["mhe_gn", "float64"])
    ref = reference("mhe", model, est.settings)
    for e in (est, ref):
        e.reset(cartpole.x0)
        for k in range(40):
            e.step(data.u[max(k - 1, 0)], data.y[k])
    window = est.window
    P0 = np.diag(np.square(cartpole.noise.initial_std))
    est.set_noise(P_arrival=P0)
    ref.set_noise(P_arrival=P0)
    np.testing.assert_array_equal(est.window, window)
    np.testing.assert_allclose(est.arrival_covariance, P0, rtol=1e-15)
    for k in range(40, 70):
        np.testing.assert_allclose(est.step(data.u[k - 1], data.y[k]), ref.step(data.u[k - 1], data.y[k]),
                                   rtol=0, atol=1e-6)


@pytest.mark.parametrize("name, precision", [b for b in BUILDS if b[0] != "mhe"], ids=lambda v: str(v))
def test_options_out_of_range_are_refused(folders, cartpole, name, precision):
    """Every option is bounded at the C boundary: BAD_ARGUMENT, nothing changed."""
    est = load_estimator(folders[name, precision])
    est.reset(cartpole.x0)
    h, c, bad = est._handle, est._c, CODES["BAD_ARGUMENT"]
    for threshold, k, inflation in ((0.5, 10, 2.0), (-1.0, 10, 2.0), (np.nan, 10, 2.0), (50.8, 0, 2.0),
                                    (50.8, 10**7, 2.0), (50.8, 10, 1.0), (50.8, 10, 1e4)):
        assert c["set_gate"](h, threshold, k, inflation) == bad
    if name.startswith("mhe"):
        for mode, max_iter, tol in ((2, 30, 1e-10), (0, 0, 1e-10), (0, 1001, 1e-10), (0, 30, 1e-15),
                                    (0, 30, 1e-2), (0, 30, np.inf), (0, 30, np.nan)):
            assert c["set_options"](h, mode, max_iter, tol) == bad
        assert c["set_options"](h, 0, 1000, 1e-3) == 0
    flags = np.array([1, 7], dtype=np.uint8)  # not a flag: a caller's mistake
    u, y = est.real_array([0.0]), est.real_array([0.0, 0.0])
    assert c["step"](h, u, y.ctypes.data, flags.ctypes.data) == bad
    assert est.samples == 0


def test_a_swapped_library_is_refused_by_its_fingerprint(model, run, tmp_path):
    """Two builds with the same prefix (other settings): the one library copied over the
    other, with the manifest's digest updated to it (as a re-compile that reused it would),
    is refused at load by its fingerprint, in one line."""
    from learnest_codegen.codegen.ukf import generate_ukf
    from learnest_codegen.estimators.ukf import UKFSettings
    from learnest_codegen.runtime.manifest import library_digest

    first = generate_ukf(model, UKFSettings.from_system(model.system), tmp_path / "a")
    second = generate_ukf(model, UKFSettings.from_system(model.system, alpha=0.3), tmp_path / "b")
    assert first.prefix == second.prefix and first.fingerprint != second.fingerprint
    shutil.copyfile(second.library_path, first.library_path)
    manifest = json.loads(first.manifest_path.read_text())
    manifest.update(library_digest(first.library_path))
    first.manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(ModelMismatchError, match="fingerprint") as info:
        load_estimator(first.directory)
    assert "\n" not in str(info.value) and "recompile" in str(info.value)
    lib = ctypes.CDLL(str(second.library_path))
    lib.cartpole_nominal_ukf_fingerprint.restype = ctypes.c_char_p
    assert lib.cartpole_nominal_ukf_fingerprint().decode() == second.fingerprint


TWO_ESTIMATORS = r"""
#include <stdio.h>
#include "@A@.h"
#include "@B@.h"
static const double U[@T@] = @U@, Y[@T@][2] = @Y@;
static unsigned char mem_a[@AU@_WORKSPACE_BYTES], mem_b[@BU@_WORKSPACE_BYTES];
int main(void) {
  @A@_t* a;
  @B@_t* b;
  @A@_real ua[1], ya[2], xa[4];
  @B@_real ub[1], yb[2], xb[4];
  int k, i;
  if (@A@_init_default(mem_a, sizeof mem_a, &a) != LEARNEST_OK) return 1;
  if (@B@_init_default(mem_b, sizeof mem_b, &b) != LEARNEST_OK) return 1;
  for (k = 0; k < @T@; ++k) {
    ua[0] = (@A@_real)U[k ? k - 1 : 0];
    ub[0] = (@B@_real)U[k ? k - 1 : 0];
    for (i = 0; i < 2; ++i) ya[i] = (@A@_real)Y[k][i], yb[i] = (@B@_real)Y[k][i];
    if (@A@_step(a, ua, ya, NULL) < 0 || @B@_step(b, ub, yb, NULL) < 0) return 2;
    @A@_get_state(a, xa);
    @B@_get_state(b, xb);
    for (i = 0; i < 4; ++i) printf("%.17g %.17g%c", (double)xa[i], (double)xb[i], i < 3 ? ' ' : '\n');
  }
  return 0;
}
"""


def _one_program(a, b, run, cartpole, tmp_path, n: int = 40) -> None:
    """The estimators of folders ``a`` and ``b`` linked into one C program from their folders'
    sources, stepped side by side; each must equal its own library bit for bit."""
    data, _ = run
    pa, pb = (json.loads((f / "manifest.json").read_text())["prefix"] for f in (a, b))
    source = TWO_ESTIMATORS
    for key, value in (("AU", pa.upper()), ("BU", pb.upper()), ("A", pa), ("B", pb), ("T", str(n)),
                       ("U", "{" + ",".join(repr(float(v)) for v in data.u[:n, 0]) + "}"),
                       ("Y", "{" + ",".join("{%r,%r}" % tuple(map(float, r)) for r in data.y[:n]) + "}")):
        source = source.replace(f"@{key}@", value)
    main = tmp_path / "main.c"
    main.write_text(source)
    exe = tmp_path / "main"
    sources = [str(path) for f in (a, b) for path in GeneratedEstimator.read(f).source_paths]
    for cc in ("gcc", "clang"):
        if shutil.which(cc) is None:
            continue
        command = [cc, "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic", str(main),
                   *sources, f"-I{a}", f"-I{b}", "-lm", "-o", str(exe)]
        proc = subprocess.run(command, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        out = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout
        X = np.loadtxt(out.splitlines()).reshape(n, 4, 2)
        for j, folder in enumerate((a, b)):
            expected = load_estimator(folder).run(data.u[:n], data.y[:n], cartpole.x0)
            np.testing.assert_array_equal(X[:, :, j], expected)


def test_two_estimators_of_two_precisions_in_one_program(folders, run, cartpole, tmp_path):
    """A float32 UKF and a float64 embedded MHE linked into one C program from their folders'
    sources (no symbol clash: the kit is static to each), each equal to its own library."""
    _one_program(folders["ukf", "float32"], folders["mhe_rti", "float64"], run, cartpole, tmp_path)


def test_two_horizons_of_one_mhe_in_one_program(model, folders, run, cartpole, tmp_path):
    """The horizon is part of an MHE's prefix and folder (``..._mhe_rti_n10`` beside
    ``..._mhe_rti_n20``): two horizons compiled into one folder keep apart and link into one
    program, each equal to its own library (their estimates differ: they are two estimators)."""
    out = tmp_path / "gen"
    n10 = compile_estimators(model, out, model_hash="nominal", estimators=("mhe_rti",),
                             horizon=10)["mhe_rti"].directory
    n20 = compile_estimators(model, out, model_hash="nominal", estimators=("mhe_rti",))["mhe_rti"].directory
    assert (n10.name, n20.name) == ("cartpole_nominal_mhe_rti_n10", "cartpole_nominal_mhe_rti_n20")
    assert n10.is_dir() and n20.is_dir()
    _one_program(n10, n20, run, cartpole, tmp_path)
    data, _ = run
    x10, x20 = (load_estimator(f).run(data.u[:40], data.y[:40], cartpole.x0) for f in (n10, n20))
    assert not np.array_equal(x10, x20)


def test_errors_name_the_call_and_keep_the_state(folders, cartpole, run):
    data, _ = run
    est = load_estimator(folders["mhe_rti", "float64"])
    est.reset(cartpole.x0)
    for k in range(10):
        est.step(data.u[max(k - 1, 0)], data.y[k])
    window = est.window
    with pytest.raises(DataError, match="valid"):
        est.step(data.u[9], data.y[10], valid=[1, 2])
    y = est.real_array([np.nan, 0.0])  # NaN in an output marked valid (NULL: all valid)
    with pytest.raises(SolverError, match="NONFINITE_INPUT"):
        est.check_status("step", est._c["step"](est._handle, est.real_array([0.0]), y.ctypes.data,
                                                None))
    np.testing.assert_array_equal(est.window, window)
