"""UKF: theory (UKF == KF on a linear model), symbolic == FilterPy, compiled C == FilterPy, errors.

Parity measure: for each sample k, ``max_i |x_c[k, i] - x_ref[k, i]| / max(max_i |x_ref[k, i]|,
1e-6)``, i.e. the difference relative to the size of the state at that sample (states that
cross zero make a per-component ratio meaningless); covariances likewise with ``max |P_ref|``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import casadi as cs
import numpy as np
import pytest
import torch
from conftest import rounding, unscented_rounding
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints

from learnest_codegen import NoiseModel, Signal, System, get_system, simulation
from learnest_codegen.codegen.ukf import (
    generate_ukf,
    merwe_weights,
    ukf_gated_update_function,
    ukf_step_function,
    ukf_update_function,
)
from learnest_codegen.errors import BuildError, DataError, ModelMismatchError, ShapeError
from learnest_codegen.estimators.gate import GateSettings
from learnest_codegen.estimators.ukf import UKF, UKFSettings
from learnest_codegen.export import hybrid_model, prior_model
from learnest_codegen.learning.network import ResidualNet
from learnest_codegen.runtime.ukf import CompiledUKF

REPO = Path(__file__).resolve().parents[1]
T_RUN = 1000
PARITY_RTOL = 1e-9


def relative_difference(a: np.ndarray, ref: np.ndarray, floor: float = 1e-6) -> np.ndarray:
    """Per sample (first axis): max |a - ref| / max(max |ref|, floor)."""
    diff = np.abs(a - ref).reshape(len(ref), -1).max(axis=1)
    return diff / np.maximum(np.abs(ref).reshape(len(ref), -1).max(axis=1), floor)


def simulate(system: System, T: int) -> dict[str, np.ndarray]:
    """``T`` samples of the true system (seed 0) as ``{"U", "Y", "X"}`` arrays."""
    run = simulation.simulate(system, seed=0, duration=T * system.dt)
    return {"U": run.u, "Y": run.y, "X": run.x}


def mass_spring_damper() -> System:
    """A linear system: RK4 of it is linear, so the UKF must equal the Kalman filter."""
    def dynamics(ops, x, u, p):
        return [x[1], (-p["k"] * x[0] - p["c"] * x[1] + u[0]) / p["m"]]

    return System(
        name="msd", states=(Signal("q", "m"), Signal("v", "m/s")), inputs=(Signal("F", "N"),),
        outputs=(Signal("q", "m"),), params={"m": 2.0, "k": 3.0, "c": 0.4},
        true_params={"m": 2.0, "k": 3.0, "c": 0.4}, dynamics=dynamics,
        measurement=lambda ops, x, u, p: [x[0]],
        noise=NoiseModel(measurement_std=(0.05,), state_std=(0.01, 0.01),
                         process_std=(1e-3, 1e-2), initial_std=(0.5, 0.5)),
        dt=0.05, duration=10.0, x0=(1.0, 0.0),
        excitation=lambda t, rng: np.sin(t + rng.uniform())[:, None])


@pytest.fixture(scope="session")
def cartpole() -> System:
    return get_system("cartpole")


@pytest.fixture(scope="session")
def data(cartpole) -> dict[str, np.ndarray]:
    return simulate(cartpole, T_RUN)


@pytest.fixture(scope="session")
def models(cartpole):
    torch.manual_seed(0)
    return {"nominal": prior_model(cartpole), "knode": hybrid_model(cartpole, ResidualNet(4, 1))}


@pytest.fixture(scope="session")
def built(models, tmp_path_factory):
    """Each model generated and compiled once for the whole session."""
    root = tmp_path_factory.mktemp("ukf")
    return {kind: generate_ukf(m, UKFSettings.from_system(m.system), root / kind,
                               model_hash=f"test-{kind}")
            for kind, m in models.items()}


@pytest.fixture(scope="session")
def reference(models, data):
    """FilterPy UKF runs: ``{kind: (X_hat (T, nx), final P (nx, nx))}``."""
    out = {}
    for kind, model in models.items():
        ukf = UKF(model)
        out[kind] = ukf.run(data["U"], data["Y"], model.system.x0), ukf.P
    return out


# -- theory --------------------------------------------------------------------------------

def update_gain(kf, Z: np.ndarray, P_prior: np.ndarray) -> tuple[float, float]:
    """How much FilterPy's last update ``kf.update`` amplified the rounding of its transform,
    relative to the scale of its results (see ``unscented_rounding``): the state ``x + K (y -
    zp)`` moves by ``|K|`` times an error of ``zp`` (on the scale of the measurement sigma points
    ``Z``) or of the innovation; the covariance ``P - K S K'`` cancels down from ``max|P|`` and
    ``|K|^2 max|S|`` to ``max|P_post|``."""
    if not hasattr(kf, "K") or kf.K.size == 0:
        return 1.0, 1.0
    K = np.abs(kf.K).max()
    gain_x = 1.0 + K * (np.abs(Z).max() + np.abs(kf.y).max()) / np.abs(kf.x).max()
    gain_P = (np.abs(P_prior).max() + K**2 * np.abs(kf.S).max()) / np.abs(kf.P).max()
    return gain_x, gain_P


def d2_bound(Wm, Wc, Z, zp, S, y) -> np.ndarray:
    """The relative rounding bound of ``d2 = (y - zp)^2 / S_jj`` between two implementations:
    ``zp`` and ``S`` are weighted sums over the sigma points (:func:`rounding` of ``3n + 2``
    operations times the summands' absolute sum), and ``y - zp`` loses digits to cancellation
    when ``zp`` is close to ``y`` (the error of ``zp`` over ``|y - zp|``, squared: twice it)."""
    r = rounding(ops=3 * (len(Wm) - 1) // 2 + 2)
    e_zp = r * (np.abs(Wm) @ np.abs(Z)) + r * np.abs(y)
    dev = Z - zp
    e_S = r * (np.abs(Wc) @ dev**2 + np.diag(S)) + 2 * e_zp * (np.abs(Wc) @ np.abs(dev))
    return 2 * e_zp / np.abs(y - zp) + e_S / np.diag(S)


def test_merwe_weights_match_filterpy():
    settings = UKFSettings(process_std=(1.0,) * 4, measurement_std=(1.0,), initial_std=(1.0,) * 4,
                           alpha=0.3, beta=2.0, kappa=1.0)
    Wm, Wc, scale = merwe_weights(4, settings)
    points = MerweScaledSigmaPoints(4, 0.3, 2.0, 1.0)
    np.testing.assert_array_equal(Wm, points.Wm)
    np.testing.assert_array_equal(Wc, points.Wc)
    assert Wm.sum() == pytest.approx(1.0, abs=1e-12)
    assert scale == pytest.approx(0.3**2 * (4 + 1.0), rel=1e-15)


def test_ukf_equals_kalman_filter_on_linear_model():
    system = mass_spring_damper()
    model = prior_model(system)
    settings = UKFSettings.from_system(system)
    # RK4 of a linear system is linear: read its matrices off F at unit vectors.
    Phi = np.stack([model.step(e, np.zeros(1)) for e in np.eye(2)], axis=1)
    Gamma = model.step(np.zeros(2), np.ones(1))[:, None]
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F, kf.B, kf.H, kf.Q, kf.R = Phi, Gamma, np.array([[1.0, 0.0]]), settings.Q(), settings.R()
    kf.x, kf.P = np.array(system.x0), settings.P0()
    run = simulate(system, 200)
    ukf = UKF(model, settings)
    ukf.reset(system.x0)
    for k in range(200):
        u = run["U"][max(k - 1, 0)]
        if k > 0:
            kf.predict(u=u)
        kf.update(run["Y"][k])
        ukf.step(u, run["Y"][k])
        np.testing.assert_allclose(ukf.x, kf.x, rtol=0, atol=1e-10 * np.abs(kf.x).max())
        np.testing.assert_allclose(ukf.P, kf.P, rtol=0, atol=1e-10 * np.abs(kf.P).max())


def test_symbolic_functions_match_filterpy(cartpole, models):
    # random measurements far from the state: the gate is off to compare the plain update
    model = models["nominal"]
    settings = UKFSettings.from_system(cartpole, gate=GateSettings(threshold=0))
    step_fn, update_fn = ukf_step_function(model, settings), ukf_update_function(model, settings)
    assert step_fn.name_in() == ["x", "P", "u", "y", "Q", "R"]
    assert step_fn.name_out() == ["x_post", "P_post"]
    rng = np.random.default_rng(3)
    ukf = UKF(model, settings)
    Q, R = settings.Q(), settings.R()
    for _ in range(20):
        A = rng.normal(size=(4, 4))
        x0, P0 = np.array(cartpole.x0) + rng.normal(size=4), 0.01 * (A @ A.T + 0.1 * np.eye(4))
        (u0, u1), (y0, y1) = rng.normal(size=(2, 1)), rng.normal(size=(2, 2))
        ukf.reset(x0, P0)
        for fn, x, P, u, y in ((update_fn, x0, P0, u0, y0), (step_fn, None, None, u1, y1)):
            x, P = (ukf.x, ukf.P) if x is None else (x, P)
            x_sym, P_sym = (np.array(v) for v in fn(x, P, u, y, Q, R))
            ukf.step(u, y)
            kf = ukf._kf
            Z = np.array([model.measure(s, u) for s in kf.sigmas_f])
            gain_x, gain_P = update_gain(kf, Z, P if fn is update_fn else kf.P_prior)
            assert relative_difference(x_sym.T, ukf.x[None])[0] <= unscented_rounding(
                kf.Wm, kf.Wc, gain=gain_x)
            assert relative_difference(P_sym[None], ukf.P[None])[0] <= unscented_rounding(
                kf.Wm, kf.Wc, gain=gain_P)


def test_gated_update_equals_filterpy_update_on_the_kept_outputs(cartpole, models):
    """The masked update of the C (``M S M + (I - M)``, ``Pxz M``) is FilterPy's own update on
    the kept outputs alone (reduced ``R`` and ``hx``); mask 0 everywhere is the prediction; d2
    is ``(y - zp)^2 / diag(S)`` of FilterPy's unscented transform."""
    from filterpy.kalman import UnscentedKalmanFilter, unscented_transform

    model, settings = models["nominal"], UKFSettings.from_system(cartpole)
    fn = ukf_gated_update_function(model, settings)
    Wm, Wc, _ = merwe_weights(4, settings)
    points = MerweScaledSigmaPoints(4, settings.alpha, settings.beta, settings.kappa)
    rng = np.random.default_rng(5)
    for mask in ([1.0, 0.0], [0.0, 1.0], [0.0, 0.0]):
        A = rng.normal(size=(4, 4))
        x, P = np.array(cartpole.x0) + rng.normal(size=4), 0.01 * (A @ A.T + 0.1 * np.eye(4))
        u, y = rng.normal(size=1), rng.normal(size=2)
        x_sym, P_sym, d2 = (np.array(v) for v in fn(x, P, u, y, settings.R(), mask))
        keep = np.array(mask, dtype=bool)
        kf = UnscentedKalmanFilter(4, 2, model.dt, hx=lambda s, u: model.measure(s, u),
                                   fx=lambda s, dt: s, points=points)
        kf.x, kf.P, kf.R = x.copy(), P.copy(), settings.R()
        kf.sigmas_f = points.sigma_points(x, P)
        Z = np.array([model.measure(s, u) for s in kf.sigmas_f])
        zp, S = unscented_transform(Z, Wm, Wc, settings.R())
        d2_ref = (y - zp) ** 2 / np.diag(S)
        assert np.all(np.abs(d2.ravel() - d2_ref) <= d2_bound(Wm, Wc, Z, zp, S, y) * d2_ref)
        gain_x, gain_P = 1.0, 1.0
        if keep.any():
            kf.update(y[keep], R=settings.R()[np.ix_(keep, keep)],
                      hx=lambda s, u, keep=keep: model.measure(s, u)[keep], u=u)
            gain_x, gain_P = update_gain(kf, Z[:, keep], P)
        assert relative_difference(x_sym.T, kf.x[None])[0] <= unscented_rounding(Wm, Wc, gain=gain_x)
        assert relative_difference(P_sym[None], kf.P[None])[0] <= unscented_rounding(Wm, Wc, gain=gain_P)


# -- compiled parity -----------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["nominal", "knode"])
def test_compiled_run_matches_filterpy(kind, built, reference, data, cartpole):
    X_ref, P_ref = reference[kind]
    compiled = CompiledUKF(built[kind].directory,
                           expect={"system": "cartpole", "model_kind": kind, "nx": 4})
    X_c = compiled.run(data["U"], data["Y"], cartpole.x0)
    rel = relative_difference(X_c, X_ref)
    print(f"{kind}: max relative state difference over {T_RUN} steps {rel.max():.2e}")
    assert rel.max() <= PARITY_RTOL
    assert relative_difference(compiled.P[None], P_ref[None])[0] <= PARITY_RTOL
    # Guard against two equally broken filters agreeing: the estimates must track the truth.
    assert np.abs(X_ref[:, [0, 2]] - data["X"][:, [0, 2]]).mean() < 0.05


def test_ctypes_step_equals_c_run(built, data, cartpole):
    compiled = CompiledUKF(built["knode"].directory)
    U, Y = data["U"][:50], data["Y"][:50]
    X_run = compiled.run(U, Y, cartpole.x0)
    compiled.reset(cartpole.x0)
    X_step = np.stack([compiled.step(U[max(k - 1, 0)], Y[k]) for k in range(50)])
    np.testing.assert_array_equal(X_step, X_run)  # the same C code path: bit for bit


def test_plain_c_program_uses_library(built, data, cartpole, tmp_path):
    """A plain C main with two filters in static workspaces, stepped interleaved: the first
    reproduces the ctypes run bit for bit, the second (other data) does not disturb it."""
    gen = built["nominal"]
    T, p, P = 20, gen.prefix, gen.prefix.upper()
    settings = UKFSettings.from_system(cartpole)

    def c_array(name, values):
        return f"static const double {name}[] = {{{', '.join(repr(float(v)) for v in np.ravel(values))}}};"

    main = "\n".join([
        "#include <stdio.h>", f'#include "{p}.h"',
        c_array("x0", cartpole.x0), c_array("P0", settings.P0()), c_array("Q", settings.Q()),
        c_array("R", settings.R()), c_array("U", data["U"][:T]), c_array("Y", data["Y"][:T]),
        f"static unsigned char mem_a[{P}_WORKSPACE_BYTES], mem_b[{P}_WORKSPACE_BYTES];",
        "int main(void) {",
        f"    double x[{P}_NX], other[{P}_NY] = {{0.1, -0.2}};",
        f"    {p}_t *a, *b;",
        f"    if ({p}_workspace_size() > sizeof mem_a) return 3;",
        f"    if ({p}_init(mem_a, sizeof mem_a, x0, P0, Q, R, &a) != LEARNEST_OK) return 1;",
        f"    if ({p}_init(mem_b, sizeof mem_b, P0, P0, Q, R, &b) != LEARNEST_OK) return 1;",
        f"    for (int k = 0; k < {T}; ++k) {{",
        f"        if ({p}_step(a, &U[(k > 0 ? k - 1 : 0) * {P}_NU], &Y[k * {P}_NY], NULL))",
        "            return 2;",
        f"        if ({p}_step(b, &U[0], other, NULL)) return 2;",
        f"        {p}_get_state(a, x);",
        f"        for (int i = 0; i < {P}_NX; ++i) printf(\"%.17g \", x[i]);",
        '        printf("\\n");', "    }", "    return 0;", "}", ""])
    (tmp_path / "main.c").write_text(main)
    exe, lib_dir = tmp_path / "main", gen.directory
    proc = subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic",
                           str(tmp_path / "main.c"), f"-I{lib_dir}", str(gen.library_path),
                           f"-Wl,-rpath,{lib_dir}", "-lm", "-o", str(exe)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    out = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout
    X_c = np.array([[float(v) for v in line.split()] for line in out.splitlines()])
    X_ctypes = CompiledUKF(lib_dir).run(data["U"][:T], data["Y"][:T], cartpole.x0)
    np.testing.assert_array_equal(X_c, X_ctypes)


def test_sources_are_warning_free(built):
    """The glue and CasADi's model code alike, without a per-file flag."""
    gen = built["nominal"]
    for source in gen.source_paths:
        proc = subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic",
                               "-fsyntax-only", f"-I{gen.directory}", str(source)],
                              capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr


def test_manifest_content(built, models):
    gen = built["knode"]
    compiled = CompiledUKF(gen.directory)
    m = compiled.manifest
    assert (m["estimator"], m["system"], m["model_kind"], m["prefix"]) == \
        ("ukf", "cartpole", "knode", "cartpole_knode_ukf")
    assert (m["nx"], m["nu"], m["ny"], m["dt"]) == (4, 1, 2, 0.002)
    assert m["settings"] == UKFSettings.from_system(models["knode"].system).to_json()
    assert m["model_hash"] == "test-knode" and m["casadi_version"] == cs.__version__
    assert m["code_bytes"] == gen.code_bytes > 0 and (gen.directory / m["library"]).is_file()


def test_unchanged_inputs_reuse_build(built, models):
    first = built["nominal"]
    code_hash = json.loads(first.manifest_path.read_text())["code_hash"]
    again = generate_ukf(models["nominal"], UKFSettings.from_system(models["nominal"].system),
                         first.directory, model_hash="test-nominal")
    assert again.reused and not first.reused
    assert json.loads(again.manifest_path.read_text())["code_hash"] == code_hash


def test_compiler_failure_raises_build_error(tmp_path, monkeypatch):
    fake_cc = tmp_path / "fake-cc"
    fake_cc.write_text("#!/bin/sh\necho 'fake-cc: cannot compile today' >&2\nexit 3\n")
    fake_cc.chmod(0o755)
    monkeypatch.setenv("CC", str(fake_cc))
    system = mass_spring_damper()
    with pytest.raises(BuildError, match="cannot compile today") as info:
        generate_ukf(prior_model(system), UKFSettings.from_system(system), tmp_path / "out")
    assert "exit 3" in str(info.value) and str(fake_cc) in str(info.value)


# -- errors ---------------------------------------------------------------------------------

def test_manifest_mismatch_raises(built):
    directory = built["nominal"].directory
    with pytest.raises(ModelMismatchError, match="system: library has 'cartpole', expected 'pendulum'"):
        CompiledUKF(directory, expect={"system": "pendulum"})
    with pytest.raises(ModelMismatchError, match="model_kind"):
        CompiledUKF(directory, expect={"model_kind": "knode", "nx": 4})
    other_alpha = UKFSettings.from_system(get_system("cartpole"), alpha=0.5)
    compiled_alpha = json.loads((directory / "manifest.json").read_text())["settings"]["alpha"]
    assert compiled_alpha != 0.5
    with pytest.raises(ModelMismatchError, match=rf"alpha: library has {compiled_alpha!r}, expected 0.5"):
        CompiledUKF(directory, settings=other_alpha)  # the message used to swap the two
    with pytest.raises(FileNotFoundError, match="does not exist"):
        CompiledUKF(directory / "missing")


def test_library_built_before_the_gate_must_be_recompiled(built, tmp_path):
    """A folder written before the innovation gate (manifest format 1, settings without a gate)
    is refused with a "recompile" message, as is a manifest whose settings were edited after
    the build (its settings hash no longer matches)."""
    import shutil

    folder = tmp_path / "old"
    shutil.copytree(built["nominal"].directory, folder)
    manifest = json.loads((folder / "manifest.json").read_text())
    old = {**manifest, "format_version": 1, "settings": {k: v for k, v in manifest["settings"].items()
                                                         if k != "gate"}}
    old.pop("settings_hash")
    (folder / "manifest.json").write_text(json.dumps(old))
    with pytest.raises(ModelMismatchError, match="format_version 1.*innovation gate.*recompile"):
        CompiledUKF(folder)
    edited = {**manifest, "settings": {**manifest["settings"], "gate": {
        **manifest["settings"]["gate"], "threshold": 9.0}}}
    (folder / "manifest.json").write_text(json.dumps(edited))
    with pytest.raises(ModelMismatchError, match="settings were edited.*recompile"):
        CompiledUKF(folder)


def test_missing_library_raises(built, tmp_path):
    manifest = json.loads(built["nominal"].manifest_path.read_text())
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(FileNotFoundError, match=r"libcartpole_nominal_ukf-\w+\.so does not exist"):
        CompiledUKF(tmp_path)


@pytest.fixture(params=["python", "compiled"])
def any_ukf(request, built, models):
    if request.param == "python":
        return UKF(models["nominal"])
    return CompiledUKF(built["nominal"].directory)


def test_bad_shapes_and_nan_raise(any_ukf, cartpole, data):
    with pytest.raises(RuntimeError, match="reset"):
        any_ukf.step(np.zeros(1), np.zeros(2))
    with pytest.raises(ShapeError, match=r"x0: expected shape \(4,\), got \(3,\)"):
        any_ukf.reset(np.zeros(3))
    any_ukf.reset(cartpole.x0)
    with pytest.raises(ShapeError, match=r"u: expected shape \(1,\), got \(2,\)"):
        any_ukf.step(np.zeros(2), np.zeros(2))
    with pytest.raises(DataError, match="y: (non-finite|infinite) value"):  # NaN: a missing output
        any_ukf.step(np.zeros(1), np.array([0.0, np.inf]))
    with pytest.raises(ShapeError, match=r"expected U \(T, 1\) and Y \(T, 2\).*got \(9, 1\) and \(10, 2\)"):
        any_ukf.run(data["U"][:9], data["Y"][:10], cartpole.x0)
    Y = data["Y"][:10].copy()
    Y[7, 1] = np.inf
    with pytest.raises(DataError, match="Y has a non-finite value at sample 7"):
        any_ukf.run(data["U"][:10], Y, cartpole.x0)


@pytest.mark.parametrize("P0, problem", [(-np.eye(4), "positive semidefinite"),
                                         (np.eye(4) + np.triu(np.ones((4, 4)), 1), "symmetric")])
def test_covariance_that_is_not_one_is_refused(any_ukf, cartpole, P0, problem):
    """An indefinite or non-symmetric P0 used to be accepted and to yield non-PSD covariances."""
    with pytest.raises(DataError, match=problem):
        any_ukf.reset(cartpole.x0, P0)


def test_c_init_refuses_what_is_not_a_covariance(built, cartpole):
    """The C API checks P0, Q and R itself (a C caller has no Python validator in front)."""
    ukf = CompiledUKF(built["nominal"].directory)
    ukf.reset(cartpole.x0)
    good = [ukf.real_array(a) for a in (cartpole.x0, ukf.settings.P0(), ukf.settings.Q(), ukf.settings.R())]
    indefinite_Q = ukf.settings.Q().copy()
    indefinite_Q[2, 2] = -1e-3
    skew_R = ukf.settings.R() + np.array([[0.0, 1e-3], [0.0, 0.0]])
    for which, bad in ((2, indefinite_Q), (3, skew_R), (1, -ukf.settings.P0())):
        args = list(good)
        args[which] = ukf.real_array(bad)
        assert ukf._c["reset"](ukf._handle, *args) == -6  # LEARNEST_NOT_POSITIVE_DEFINITE
    np.testing.assert_array_equal(ukf.x, cartpole.x0)  # unchanged
    zero_Q = np.zeros((4, 4))  # semidefinite: allowed
    assert ukf._c["reset"](ukf._handle, good[0], good[1], ukf.real_array(zero_Q), good[3]) == 0


def test_two_compiled_filters_on_one_library_are_independent(built, data, cartpole):
    """Each CompiledUKF owns its workspace: stepping one does not move the other."""
    U, Y = data["U"][:50], data["Y"][:50]
    first, second = (CompiledUKF(built["knode"].directory) for _ in range(2))
    X_alone = first.run(U, Y, cartpole.x0)
    first.reset(cartpole.x0)
    second.reset(np.zeros(4))
    for k in range(len(Y)):
        x_first = first.step(U[max(k - 1, 0)], Y[k])
        second.step(-U[max(k - 1, 0)], Y[k] + 0.1)
        np.testing.assert_array_equal(x_first, X_alone[k])


def test_settings_validation(cartpole, models):
    with pytest.raises(ValueError, match="process_std"):
        UKFSettings.from_system(cartpole, process_std=(1.0, -1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="alpha"):
        UKFSettings.from_system(cartpole, alpha=float("nan"))
    with pytest.raises(TypeError, match="lamda"):
        UKFSettings.from_system(cartpole, lamda=1.0)
    short = UKFSettings.from_system(cartpole, measurement_std=(0.1,))
    with pytest.raises(ShapeError, match="measurement_std: the model has ny = 2, got 1"):
        UKF(models["nominal"], short)
    settings = UKFSettings.from_system(cartpole, kappa=1.0)
    assert UKFSettings(**json.loads(json.dumps(settings.to_json()))) == settings


def test_runtime_imports_neither_torch_nor_filterpy():
    code = ("import sys, learnest_codegen.runtime.ukf; "
            "print(sorted(m for m in ('torch', 'filterpy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, capture_output=True,
                         text=True).stdout
    assert out.strip() == "[]"
