"""MHE: theory (== Kalman filter while the horizon holds all data), an independent least-squares
solve, the custom Hessian vs CasADi's, compiled C == Python reference, and errors.

Parity measure: max over samples and states of ``|x_compiled - x_python|`` (absolute; the
cartpole states are O(0.01..1)), tolerance 1e-6 as specified. Both sides run the same Ipopt
on the same NLP from the same warm start, so the difference is round-off that Newton's method
does not amplify (the solver tolerance leaves each step within ~4e-9 of its optimum).
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import casadi as cs
import numpy as np
import pytest
import torch
from filterpy.kalman import KalmanFilter
from scipy.optimize import least_squares

from learnest_codegen import NoiseModel, Signal, System, get_system, simulation
from learnest_codegen.codegen.mhe import generate_mhe
from learnest_codegen.codegen.mhe_gn import generate_embedded_mhe
from learnest_codegen.errors import DataError, ModelMismatchError, ShapeError, SolverError
from learnest_codegen.estimators.gate import GateSettings
from learnest_codegen.estimators.mhe import MHE
from learnest_codegen.estimators.mhe_problem import MHESettings, build_problem, mhe_settings
from learnest_codegen.export import hybrid_model, prior_model
from learnest_codegen.learning.network import ResidualNet
from learnest_codegen.runtime.mhe import CompiledMHE
from learnest_codegen.runtime.mhe_gn import CompiledEmbeddedMHE
from learnest_codegen.toolchain import casadi_dirs

REPO = Path(__file__).resolve().parents[1]
T_RUN = 300
PARITY_ATOL = 1e-6


def mass_spring_damper() -> System:
    """A linear system: RK4 of it is linear, so full-information MHE is the Kalman filter."""
    def dynamics(ops, x, u, p):
        return [x[1], (-p["k"] * x[0] - p["c"] * x[1] + u[0]) / p["m"]]

    params = {"m": 2.0, "k": 3.0, "c": 0.4}
    return System(
        name="msd", states=(Signal("q", "m"), Signal("v", "m/s")), inputs=(Signal("F", "N"),),
        outputs=(Signal("q", "m"),), params=params, true_params=params, dynamics=dynamics,
        measurement=lambda ops, x, u, p: [x[0]],
        noise=NoiseModel(measurement_std=(0.05,), state_std=(0.01, 0.01),
                         process_std=(1e-3, 1e-2), initial_std=(0.5, 0.5)),
        dt=0.05, duration=12.0, x0=(1.0, 0.0),
        excitation=lambda t, rng: np.sin(t + rng.uniform())[:, None])


@pytest.fixture(scope="session")
def cartpole() -> System:
    return get_system("cartpole")


@pytest.fixture(scope="session")
def data(cartpole) -> dict[str, np.ndarray]:
    run = simulation.simulate(cartpole, seed=0, duration=T_RUN * cartpole.dt)
    return {"U": run.u, "Y": run.y, "X": run.x}


@pytest.fixture(scope="session")
def models(cartpole):
    torch.manual_seed(0)
    return {"nominal": prior_model(cartpole), "knode": hybrid_model(cartpole, ResidualNet(4, 1))}


@pytest.fixture(scope="session")
def built(models, tmp_path_factory):
    """Each model generated and compiled once for the whole session."""
    root = tmp_path_factory.mktemp("mhe")
    return {kind: generate_mhe(m, None, root / kind, model_hash=f"test-{kind}")
            for kind, m in models.items()}


@pytest.fixture(scope="session")
def reference(models, data, cartpole):
    """Python reference runs ``{kind: X_hat (T, nx)}``."""
    return {kind: MHE(m).run(data["U"], data["Y"], cartpole.x0) for kind, m in models.items()}


# -- theory ------------------------------------------------------------------------------------

def linear_data(system: System, T: int) -> tuple[np.ndarray, ...]:
    """``(A, B, C, U, Y)``: the exact linear RK4 model and a run with matching noise."""
    x, u = cs.SX.sym("x", 2), cs.SX.sym("u", 1)
    x_next = prior_model(system).F(x, u)
    A, B = (np.array(M) for M in cs.Function("AB", [x, u], [cs.jacobian(x_next, x),
                                                             cs.jacobian(x_next, u)])(0, 0))
    C = np.array([[1.0, 0.0]])
    rng = np.random.default_rng(0)
    noise = system.noise
    U = system.excitation(np.arange(T) * system.dt, rng)
    X = np.empty((T, 2))
    X[0] = np.array(system.x0) + rng.normal(size=2) * noise.initial_std
    for k in range(T - 1):
        X[k + 1] = A @ X[k] + B @ U[k] + rng.normal(size=2) * noise.process_std
    Y = X @ C.T + rng.normal(size=(T, 1)) * noise.measurement_std
    return A, B, C, U, Y


def kalman_filter(system: System, A, B, C, U, Y) -> tuple[np.ndarray, np.ndarray]:
    """FilterPy KF with the MHE's conventions: ``(X (T, 2), std (T, 2))`` of the posterior."""
    kf = KalmanFilter(dim_x=2, dim_z=1, dim_u=1)
    kf.F, kf.B, kf.H = A, B, C
    noise = system.noise
    kf.Q, kf.R = (np.diag(np.square(s)) for s in (noise.process_std, noise.measurement_std))
    kf.P, kf.x = np.diag(np.square(noise.initial_std)), np.array(system.x0)[:, None]
    X, std = np.empty((len(Y), 2)), np.empty((len(Y), 2))
    for k in range(len(Y)):
        if k > 0:
            kf.predict(u=U[k - 1:k])
        kf.update(Y[k])
        X[k], std[k] = kf.x.ravel(), np.sqrt(np.diag(kf.P))
    return X, std


def test_mhe_is_kalman_filter_while_the_horizon_holds_all_data():
    """For k <= N the MHE is full-information estimation with prior (x0, P0): for a linear-
    Gaussian model that is exactly the KF posterior mean. After the window is full, the arrival
    cost (fixed P, xbar = previous smoothed estimate) approximates the discarded data; its
    effect decays geometrically with N (measured in the KF's own std: 1.5, 0.30, 0.025 for
    N = 20, 40, 80)."""
    system = mass_spring_damper()
    A, B, C, U, Y = linear_data(system, T=200)
    X_kf, std = kalman_filter(system, A, B, C, U, Y)
    after = []
    for N in (20, 40, 80):
        settings = MHESettings.from_system(system, horizon=N, arrival="arrival_std")
        X = MHE(prior_model(system), settings).run(U, Y, system.x0)
        # ~1e-13 measured: the Ipopt tolerance, not the formulation, sets this.
        np.testing.assert_allclose(X[:N + 1], X_kf[:N + 1], rtol=0, atol=1e-9)
        after.append(np.max(np.abs(X - X_kf)[N + 1:] / std[N + 1:]))
    assert after[0] > 3 * after[1] > 9 * after[2]
    assert after[2] < 0.05


@pytest.mark.parametrize("k", [6, 45])
def test_mhe_step_solves_its_least_squares_problem(models, data, cartpole, k):
    """Sample k of a cartpole run against scipy's least_squares on the same stacked, whitened
    residuals written out independently (window not yet full at k=6, full at k=45)."""
    model, U, Y = models["nominal"], data["U"], data["Y"]
    mhe = MHE(model)
    mhe.run(U[:k], Y[:k], cartpole.x0)
    previous = mhe.window
    mhe.step(U[k - 1], Y[k])
    N = mhe.settings.horizon
    first = max(0, k - N)  # the oldest sample in the window
    xbar = previous[1] if k > N else np.asarray(cartpole.x0)  # the window was full before
    real = first - (k - N)  # window index of sample `first`; stages before it are padding
    inv_std = [1.0 / np.asarray(s) for s in (mhe.settings.process_std, mhe.settings.measurement_std)]
    L = np.linalg.cholesky(mhe.settings.weights()[2])  # the steady-state arrival weight, L L^T

    def residuals(z):
        X = z.reshape(-1, 4)  # samples first..k
        r = [L.T @ (X[0] - xbar)]
        for j, s in enumerate(range(first, k + 1)):
            u_in = U[s - 1] if s > 0 else np.zeros(1)
            r.append(inv_std[1] * (Y[s] - model.measure(X[j], u_in)))
            if s < k:
                r.append(inv_std[0] * (X[j + 1] - model.step(X[j], U[s])))
        return np.concatenate(r)

    start = np.tile(previous[-1], k - first + 1)
    sol = least_squares(residuals, start, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    np.testing.assert_allclose(mhe.window[real:], sol.x.reshape(-1, 4), rtol=0, atol=1e-6)
    np.testing.assert_allclose(mhe.window[:real], np.tile(xbar, (real, 1)), rtol=0, atol=1e-9)


def test_custom_hessian_equals_casadis(models, cartpole):
    """The hess_lag given to Ipopt (stage Hessians assembled) vs CasADi's Hessian of the cost."""
    model = models["knode"]
    problem = build_problem(model, MHESettings.from_system(cartpole, horizon=5), "hess_check")
    x, p = cs.MX.sym("x", 4 * 6), cs.MX.sym("p", problem.layout.size)
    cost = problem.solver.oracle()(x=x, p=p)["f"]
    casadi_hessian = cs.Function("H", [x, p], [cs.hessian(cost, x)[0]])
    rng = np.random.default_rng(1)
    lay = problem.layout
    for mask in ([0, 0, 0, 1, 1, 1], [1] * 6):
        pv = rng.normal(size=lay.size)
        pv[lay.slice("mask")] = mask
        for name, n in (("Q", 4), ("R", 2), ("P", 4)):
            M = rng.normal(size=(n, n))
            pv[lay.slice(name)] = (M @ M.T + n * np.eye(n)).ravel()
        xv = rng.normal(size=24) * 0.3
        H_ref = np.array(casadi_hessian(xv, pv))
        H = np.array(problem.hessian(xv, pv, 1.0, []))
        np.testing.assert_allclose(H + np.triu(H, 1).T, H_ref, rtol=0, atol=1e-12 * np.abs(H_ref).max())


# -- compiled == reference ---------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["nominal", "knode"])
def test_compiled_run_matches_python(kind, built, reference, data, cartpole):
    compiled = CompiledMHE(built[kind].directory, expect={"model_kind": kind})
    X_c = compiled.run(data["U"], data["Y"], cartpole.x0)
    assert np.max(np.abs(X_c - reference[kind])) <= PARITY_ATOL
    compiled.reset(cartpole.x0)
    X_step = [compiled.step(np.zeros(1), data["Y"][0])]
    X_step += [compiled.step(data["U"][k - 1], data["Y"][k]) for k in range(1, T_RUN)]
    np.testing.assert_array_equal(np.array(X_step), X_c)  # the same C code path: bit for bit


def test_plain_c_program_uses_library(built, models, reference, data, cartpole, tmp_path):
    """A plain C main: status codes, and two estimators in static workspaces, the second
    stepped between the first's samples with other data."""
    gen, T = built["nominal"], 25
    p, P = gen.prefix, gen.prefix.upper()
    Q, R, P0 = mhe_settings(models["nominal"]).covariances()  # what the library was built with

    def c_array(name, values):
        numbers = ", ".join(repr(float(v)) for v in np.ravel(values))
        return f"static const double {name}[] = {{{numbers}}};"

    main = "\n".join([
        "#include <math.h>", "#include <stdio.h>", f'#include "{p}.h"',
        c_array("x0", cartpole.x0), c_array("Q", Q), c_array("R", R), c_array("P0", P0),
        c_array("U", data["U"][:T]), c_array("Y", data["Y"][:T]),
        "static unsigned char mem_a[1 << 20], mem_b[1 << 20];",
        "int main(void) {",
        f"    double x[{P}_NX], bad[{P}_NY] = {{0.0, NAN}}, other[{P}_NY] = {{0.1, 0.2}};",
        f"    {p}_t *a = 0, *b;",
        f"    if ({p}_workspace_size() > sizeof mem_a) return 3;",
        f"    printf(\"%d\\n\", {p}_step(a, U, Y, NULL));  /* before init */",
        f"    if ({p}_init(mem_a, sizeof mem_a, x0, P0, Q, R, &a) != LEARNEST_OK) return 1;",
        f"    if ({p}_init(mem_b, sizeof mem_b, x0, P0, Q, R, &b) != LEARNEST_OK) return 1;",
        f"    printf(\"%d\\n\", {p}_step(a, U, bad, NULL));",
        f"    for (int k = 0; k < {T}; ++k) {{",
        f"        if ({p}_step(a, k ? &U[(k - 1) * {P}_NU] : U, &Y[k * {P}_NY], NULL) != LEARNEST_OK)",
        "            return 2;",
        f"        if ({p}_step(b, U, other, NULL) < 0) return 2;  /* gated, not an error */",
        "    }",
        f"    {p}_get_state(a, x);",
        f"    for (int i = 0; i < {P}_NX; ++i) printf(\"%.17g \", x[i]);",
        f"    printf(\"\\n%d\\n\", {p}_samples(a));",
        "    return 0;", "}", ""])
    (tmp_path / "main.c").write_text(main)
    exe, lib_dir = tmp_path / "main", gen.directory
    proc = subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic",
                           str(tmp_path / "main.c"), f"-I{lib_dir}", str(gen.library_path),
                           f"-Wl,-rpath,{lib_dir}", "-lm", "-o", str(exe)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    lines = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout.splitlines()
    assert lines[:2] == ["-1", "-3"]  # NOT_INITIALISED, NONFINITE_INPUT
    x_last = np.array([float(v) for v in lines[2].split()])
    assert np.max(np.abs(x_last - reference["nominal"][T - 1])) <= PARITY_ATOL
    assert lines[3] == f"{T}"


def test_sources_are_warning_free(built):
    """The glue and CasADi's solver code alike, without a per-file flag."""
    gen = built["nominal"]
    include, _ = casadi_dirs()
    for source in gen.source_paths:
        proc = subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic",
                               "-fsyntax-only", f"-I{gen.directory}", f"-I{include}", str(source)],
                              capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr


def test_manifest_content(built, models, cartpole):
    gen = built["knode"]
    m = CompiledMHE(gen.directory).manifest
    assert (m["estimator"], m["system"], m["model_kind"], m["prefix"]) == \
        ("mhe", "cartpole", "knode", "cartpole_knode_mhe_n20")
    assert (m["nx"], m["nu"], m["ny"], m["dt"], m["horizon"]) == (4, 1, 2, 0.002, 20)
    assert m["settings"] == mhe_settings(models["knode"]).to_json()
    assert m["model_hash"] == "test-knode" and m["casadi_version"] == cs.__version__
    assert m["code_bytes"] == gen.code_bytes > 0 and m["build_seconds"] > 0
    assert (gen.directory / m["library"]).is_file() and len(m["code_hash"]) == 64


def test_unchanged_inputs_reuse_build(built, models):
    first = built["nominal"]
    before = json.loads(first.manifest_path.read_text())
    again = generate_mhe(models["nominal"], None, first.directory, model_hash="test-nominal")
    after = json.loads(again.manifest_path.read_text())
    assert again.reused and not first.reused
    assert after["code_hash"] == before["code_hash"]
    assert after["build_seconds"] == before["build_seconds"] > 0  # the build's, not the reuse's


# -- errors ------------------------------------------------------------------------------------

def test_manifest_mismatch_raises(built, cartpole, tmp_path):
    directory = built["nominal"].directory
    with pytest.raises(ModelMismatchError, match="model_kind: library has 'nominal', expected 'knode'"):
        CompiledMHE(directory, expect={"model_kind": "knode"})
    with pytest.raises(ModelMismatchError, match="model_hash"):
        CompiledMHE(directory, expect={"model_hash": "other"})
    with pytest.raises(ModelMismatchError, match="horizon is 10, the library was generated for 20"):
        CompiledMHE(directory, settings=MHESettings.from_system(cartpole, horizon=10))
    with pytest.raises(FileNotFoundError, match="missing does not exist"):
        CompiledMHE(directory / "missing")
    shutil.copy(directory / "manifest.json", tmp_path / "manifest.json")
    with pytest.raises(FileNotFoundError, match=r"libcartpole_nominal_mhe_n20-\w+\.so does not exist"):
        CompiledMHE(tmp_path)


@pytest.fixture(scope="module")
def embedded(models, tmp_path_factory):
    """The embedded (Gauss-Newton) MHE of the nominal model: the same checks apply to it."""
    return generate_embedded_mhe(models["nominal"], None, tmp_path_factory.mktemp("gn")).directory


@pytest.fixture(params=["python", "compiled", "embedded"])
def any_mhe(request, built, models, embedded):
    if request.param == "python":
        return MHE(models["nominal"])
    if request.param == "embedded":
        return CompiledEmbeddedMHE(embedded)
    return CompiledMHE(built["nominal"].directory)


def test_bad_shapes_and_nan_raise(any_mhe, cartpole, data):
    with pytest.raises(RuntimeError, match="reset"):
        any_mhe.step(np.zeros(1), np.zeros(2))
    with pytest.raises(ShapeError, match=r"x0: expected shape \(4,\), got \(3,\)"):
        any_mhe.reset(np.zeros(3))
    any_mhe.reset(cartpole.x0)
    with pytest.raises(ShapeError, match=r"u: expected shape \(1,\), got \(2,\)"):
        any_mhe.step(np.zeros(2), np.zeros(2))
    with pytest.raises(DataError, match="y: (non-finite|infinite)"):  # NaN: a missing output
        any_mhe.step(np.zeros(1), np.array([0.0, np.inf]))
    with pytest.raises(ShapeError, match=r"U \(T, 1\) and Y \(T, 2\).*got \(9, 1\) and \(10, 2\)"):
        any_mhe.run(data["U"][:9], data["Y"][:10], cartpole.x0)
    Y = data["Y"][:10].copy()
    Y[7, 1] = np.inf
    with pytest.raises(DataError, match="Y has a non-finite value at sample 7"):
        any_mhe.run(data["U"][:10], Y, cartpole.x0)
    with pytest.raises(ValueError, match="must be positive definite"):
        any_mhe.reset(cartpole.x0, -np.eye(4))
    with pytest.raises(AttributeError, match="no state covariance"):
        _ = any_mhe.P


def test_failed_solve_raises_and_keeps_state(any_mhe, cartpole, data):
    """Gate off, a measurement of 1e200 makes the cost overflow: Ipopt (or the Gauss-Newton line
    search) fails, the step raises and the estimator is left as it was, ready for the next
    sample."""
    any_mhe.settings = dataclasses.replace(any_mhe.settings, gate=GateSettings(threshold=0))
    any_mhe.run(data["U"][:5], data["Y"][:5], cartpole.x0)
    window = any_mhe.window
    with pytest.raises(SolverError, match="sample 5"):
        any_mhe.step(data["U"][4], np.array([1e200, 0.0]))
    np.testing.assert_array_equal(any_mhe.window, window)
    any_mhe.step(data["U"][4], data["Y"][5])


def test_gate_rejects_an_absurd_output_and_steps_on(any_mhe, cartpole, data):
    """Gate on (the default), the same 1e200 is rejected: status 1, not an error, the other
    output is used, and the next clean sample is accepted."""
    any_mhe.run(data["U"][:5], data["Y"][:5], cartpole.x0)
    assert (any_mhe.last_status, any_mhe.rejections) == (0, 0)
    x = any_mhe.step(data["U"][4], np.array([1e200, data["Y"][5, 1]]))
    assert np.all(np.isfinite(x)) and np.abs(x[0] - data["X"][5, 0]) < 0.05
    assert any_mhe.last_status == 1 and any_mhe.rejected.tolist() == [True, False]
    any_mhe.step(data["U"][5], data["Y"][6])
    assert any_mhe.last_status == 0 and any_mhe.rejected.tolist() == [False, False]
    assert any_mhe.rejections == 1


def test_arrival_weight_from_P0(any_mhe, cartpole):
    P0 = np.diag([0.1, 0.2, 0.3, 0.4]) ** 2
    any_mhe.reset(cartpole.x0, P0)
    np.testing.assert_allclose(any_mhe.arrival_weight, np.linalg.inv(P0), rtol=1e-12)
    any_mhe.reset(cartpole.x0)  # every door: the steady-state arrival covariance
    np.testing.assert_allclose(any_mhe.arrival_weight,
                               np.linalg.inv(np.asarray(any_mhe.settings.arrival_covariance)),
                               rtol=1e-9)


def test_two_compiled_estimators_on_one_library_are_independent(built, reference, data, cartpole):
    """Each CompiledMHE owns its workspace and its solver memory: interleaved steps of a second
    estimator on other data leave the first's estimates bit-identical to its solo run."""
    U, Y = data["U"][:40], data["Y"][:40]
    first, second = (CompiledMHE(built["nominal"].directory) for _ in range(2))
    X_alone = first.run(U, Y, cartpole.x0)
    first.reset(cartpole.x0)
    second.reset(np.zeros(4))
    for k in range(len(Y)):
        x_first = first.step(U[k - 1] if k else np.zeros(1), Y[k])
        second.step(np.zeros(1), Y[k] + 0.05)
        np.testing.assert_array_equal(x_first, X_alone[k])


def test_settings_validation(cartpole, models):
    with pytest.raises(ValueError, match="process_std"):
        MHESettings.from_system(cartpole, process_std=(1.0, -1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="horizon"):
        MHESettings.from_system(cartpole, horizon=0)
    with pytest.raises(TypeError, match="horizn"):
        MHESettings.from_system(cartpole, horizn=5)
    with pytest.raises(ShapeError, match="measurement_std needs 2 values, got 1"):
        MHE(models["nominal"], MHESettings.from_system(cartpole, measurement_std=(0.1,)))
    settings = MHESettings.from_system(cartpole, horizon=7)
    assert MHESettings.from_json(json.loads(json.dumps(settings.to_json()))) == settings
    with pytest.raises(ValueError, match="steady-state arrival covariance is computed from the model"):
        settings.weights()
    with pytest.raises(ValueError, match="arrival must be one of"):
        MHESettings.from_system(cartpole, arrival="steady")
    Q, R, P = dataclasses.replace(settings, arrival="arrival_std").weights()
    np.testing.assert_allclose(np.diag(R), 1 / np.square(cartpole.noise.measurement_std))


def test_runtime_is_torch_free(built, data, reference, cartpole):
    """Loading and running a compiled MHE keeps torch out of the process."""
    code = ("import sys, json, numpy as np; from learnest_codegen.runtime.mhe import CompiledMHE; "
            f"m = CompiledMHE({str(built['knode'].directory)!r}); "
            f"X = m.run(np.array({data['U'][:5].tolist()}), np.array({data['Y'][:5].tolist()}), "
            f"np.array({list(cartpole.x0)})); "
            "print(json.dumps(['torch' in sys.modules, X[-1].tolist()]))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, check=True, capture_output=True,
                         text=True).stdout
    torch_loaded, x_last = json.loads(out)
    assert not torch_loaded
    assert np.max(np.abs(np.array(x_last) - reference["knode"][4])) <= PARITY_ATOL
