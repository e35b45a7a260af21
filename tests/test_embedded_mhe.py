"""Embedded (Gauss-Newton) MHE: parity with the Ipopt MHE, RTI accuracy, no allocation,
independent instances, the C status contract and its errors.

Parity measure as in test_mhe.py: max over samples and states of ``|x_gn - x_ipopt|``,
tolerance 1e-6. Both solve the same eq. (2) NLP from the same warm start; the converged
Gauss-Newton iteration stops at a stationary point of the same cost (step <= 1e-10), Ipopt at
gradient <= 1e-12 of the scaled cost, so the difference is the two solvers' tolerances.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import replace

import numpy as np
import pytest
import torch

from learnest_codegen import get_system, simulation
from learnest_codegen.codegen.mhe import generate_mhe
from learnest_codegen.codegen.mhe_gn import (
    generate_embedded_mhe,
    model_functions,
    pattern_defines,
    state_groups,
)
from learnest_codegen.compilation import estimator_kind
from learnest_codegen.data import write_run
from learnest_codegen.errors import DataError, ModelMismatchError, ShapeError, SolverError
from learnest_codegen.estimators.mhe_gn import GaussNewtonSettings
from learnest_codegen.estimators.mhe_problem import mhe_settings
from learnest_codegen.export import hybrid_model, prior_model
from learnest_codegen.learning.training import TrainingSettings, make_net, train
from learnest_codegen.runtime.mhe import CompiledMHE
from learnest_codegen.runtime.mhe_gn import CompiledEmbeddedMHE
from learnest_codegen.runtime.status import STATUSES

PARITY_ATOL = 1e-6
RTI_MSE_RTOL = 0.02
T_PARITY = 1000
RTI = GaussNewtonSettings(mode="rti")


@pytest.fixture(scope="module")
def cartpole_models(cartpole, cartpole_run):
    """Nominal, and a KNODE trained briefly (parity does not need a good model)."""
    torch.manual_seed(0)
    trained = train(cartpole, cartpole_run.x[:1000], cartpole_run.u[:1000], cartpole_run.dt,
                    TrainingSettings(epochs=3), progress=False)
    return {"nominal": prior_model(cartpole), "knode": hybrid_model(cartpole, trained.net)}


@pytest.fixture(scope="module")
def builds(cartpole_models, tmp_path_factory):
    """{(kind, estimator): directory} for the Ipopt MHE, mhe_gn and mhe_rti of each model."""
    root, out = tmp_path_factory.mktemp("embedded"), {}
    for kind, model in cartpole_models.items():
        settings = estimator_kind("mhe").default_settings(model)
        out[kind, "mhe"] = generate_mhe(model, settings, root / kind / "mhe").directory
        out[kind, "mhe_gn"] = generate_embedded_mhe(model, settings, root / kind / "gn").directory
        out[kind, "mhe_rti"] = generate_embedded_mhe(model, settings, root / kind / "rti",
                                                     solver=RTI).directory
    return out


@pytest.fixture(scope="module")
def parity_run(cartpole):
    return simulation.simulate(cartpole, seed=3, duration=T_PARITY * cartpole.dt)


def mse(X_hat, X):
    return float(np.mean((X_hat - X) ** 2))


@pytest.mark.parametrize("kind", ["nominal", "knode"])
def test_converged_matches_ipopt_on_every_step(kind, builds, parity_run, cartpole):
    U, Y = parity_run.u, parity_run.y
    X_ipopt = CompiledMHE(builds[kind, "mhe"]).run(U, Y, cartpole.x0)
    gn = CompiledEmbeddedMHE(builds[kind, "mhe_gn"])
    X_gn = gn.run(U, Y, cartpole.x0)
    assert len(X_gn) == T_PARITY
    assert np.max(np.abs(X_gn - X_ipopt)) <= PARITY_ATOL
    # and it is a real estimator: far better than the measurement-free prediction from x0
    assert mse(X_gn, parity_run.x) < 0.1 * mse(np.tile(cartpole.x0, (T_PARITY, 1)), parity_run.x)


@pytest.mark.parametrize("kind", ["nominal", "knode"])
def test_converged_takes_at_most_4_steps_on_every_sample(kind, builds, parity_run, cartpole):
    """From the shifted warm start, Gauss-Newton converges in about two steps; a line search
    that halved steps on the cost's round-off crawled on in a tail of many short steps."""
    gn = CompiledEmbeddedMHE(builds[kind, "mhe_gn"])
    gn.reset(cartpole.x0)
    iterations = []
    for k in range(T_PARITY):
        gn.step(parity_run.u[k - 1] if k else np.zeros(1), parity_run.y[k])
        iterations.append(gn.iterations)
    assert max(iterations) <= 4, np.bincount(iterations)


def test_rti_mse_within_2_percent_of_ipopt_short_run(builds, parity_run, cartpole):
    for kind in ("nominal", "knode"):
        X_ipopt = CompiledMHE(builds[kind, "mhe"]).run(parity_run.u, parity_run.y, cartpole.x0)
        X_rti = CompiledEmbeddedMHE(builds[kind, "mhe_rti"]).run(parity_run.u, parity_run.y,
                                                                 cartpole.x0)
        ref = mse(X_ipopt, parity_run.x)
        assert abs(mse(X_rti, parity_run.x) - ref) <= RTI_MSE_RTOL * ref, kind


@pytest.mark.slow
def test_rti_mse_within_2_percent_of_ipopt_cartpole(builds, cartpole_test_run, cartpole):
    run = cartpole_test_run
    for kind in ("nominal", "knode"):
        X_ipopt = CompiledMHE(builds[kind, "mhe"]).run(run.u, run.y, cartpole.x0)
        X_rti = CompiledEmbeddedMHE(builds[kind, "mhe_rti"]).run(run.u, run.y, cartpole.x0)
        ref = mse(X_ipopt, run.x)
        assert abs(mse(X_rti, run.x) - ref) <= RTI_MSE_RTOL * ref, kind


@pytest.mark.slow
def test_rti_mse_within_2_percent_of_ipopt_ground_robot(tmp_path):
    robot = get_system("ground_robot")
    run = simulation.simulate(robot, seed=1)
    model = prior_model(robot)
    settings = estimator_kind("mhe").default_settings(model)
    X_ipopt = CompiledMHE(generate_mhe(model, settings, tmp_path / "mhe").directory).run(
        run.u, run.y, robot.x0)
    rti = CompiledEmbeddedMHE(generate_embedded_mhe(model, settings, tmp_path / "rti",
                                                    solver=RTI).directory)
    X_rti = rti.run(run.u, run.y, robot.x0)
    ref = mse(X_ipopt, run.x)
    assert abs(mse(X_rti, run.x) - ref) <= RTI_MSE_RTOL * ref


def test_step_equals_run_and_two_instances_are_independent(builds, parity_run, cartpole):
    U, Y = parity_run.u[:200], parity_run.y[:200]
    a = CompiledEmbeddedMHE(builds["knode", "mhe_gn"])
    b = CompiledEmbeddedMHE(builds["knode", "mhe_gn"])
    X_run = a.run(U, Y, cartpole.x0)
    a.reset(cartpole.x0)
    b.reset(np.zeros(4))
    rng, iterations = np.random.default_rng(0), []
    for k in range(len(Y)):
        u_k = U[k - 1] if k else np.zeros(1)
        x_a = a.step(u_k, Y[k])
        b.step(rng.normal(size=1), Y[k] + rng.normal(size=2))  # interleaved, other data
        np.testing.assert_array_equal(x_a, X_run[k])
        iterations.append(a.iterations)
    assert 1 <= np.mean(iterations) <= 5


C_MAIN = r"""
#include <stdio.h>
#include <stdlib.h>
#include "PREFIX.h"
static long calls;
void* __real_malloc(size_t n);
void* __real_calloc(size_t n, size_t m);
void* __real_realloc(void* p, size_t n);
void __real_free(void* p);
void* __wrap_malloc(size_t n) { ++calls; return __real_malloc(n); }
void* __wrap_calloc(size_t n, size_t m) { ++calls; return __real_calloc(n, m); }
void* __wrap_realloc(void* p, size_t n) { ++calls; return __real_realloc(p, n); }
void __wrap_free(void* p) { ++calls; __real_free(p); }
#define NX PREFIX_UP_NX
static double U[T_RUN][1] = UDATA, Y[T_RUN][2] = YDATA;
static double x0[NX] = X0, P0[NX * NX] = PDATA, Q[NX * NX] = QDATA, R[4] = RDATA;
static unsigned char mem_a[200000], mem_b[200000];
int main(void) {
  PREFIX_t *a, *b;
  double x[NX], zero[1] = {0}, other[2];
  int k, i;
  if (PREFIX_workspace_size() > sizeof mem_a) return 10;
  calls = 0;
  if (PREFIX_init(mem_a, sizeof mem_a, x0, P0, Q, R, &a) != LEARNEST_OK) return 11;
  if (PREFIX_init(mem_b, sizeof mem_b, x0, P0, Q, R, &b) != LEARNEST_OK) return 12;
  if (PREFIX_init(mem_b, 16, x0, P0, Q, R, &b) != LEARNEST_NO_MEMORY || b) return 13;
  if (PREFIX_init(mem_b, sizeof mem_b, x0, P0, Q, R, &b) != LEARNEST_OK) return 14;
  for (k = 0; k < T_RUN; ++k) {
    if (PREFIX_step(a, k ? U[k - 1] : zero, Y[k], NULL) != LEARNEST_OK) return 20;
    for (i = 0; i < 2; ++i) other[i] = 0.5 * Y[T_RUN - 1 - k][i];
    /* b's made-up samples are partly rejected by the gate: status 1, not an error */
    if (PREFIX_step(b, zero, other, NULL) < 0) return 21;
    PREFIX_get_state(a, x);
    for (i = 0; i < NX; ++i) printf("%.17g%c", x[i], i + 1 < NX ? ' ' : '\n');
  }
  fprintf(stderr, "allocations %ld\n", calls);
  return calls != 0;
}
"""


def gn_sources(directory):
    """The C sources of a generated folder (its manifest's list)."""
    from learnest_codegen.runtime.manifest import GeneratedEstimator

    return GeneratedEstimator.read(directory).source_paths


def c_array(values) -> str:
    values = np.atleast_2d(values)
    return "{" + ",".join("{" + ",".join(repr(float(v)) for v in row) + "}" for row in values) + "}"


def test_plain_c_main_two_instances_and_no_allocation(builds, parity_run, cartpole, tmp_path):
    """A firmware-style main with static workspaces: malloc/calloc/realloc/free are wrapped
    (-Wl,--wrap) and counted over init and every step; two handles step interleaved."""
    directory = builds["knode", "mhe_gn"]
    gn = CompiledEmbeddedMHE(directory)
    prefix = gn.manifest["prefix"]
    T = 60
    U, Y = parity_run.u[:T], parity_run.y[:T]
    Q, R, P = gn.settings.covariances()
    flat = lambda M: c_array(M.ravel()).strip("{}")  # noqa: E731
    source = (C_MAIN.replace("PREFIX_UP", prefix.upper()).replace("PREFIX", prefix)
              .replace("UDATA", c_array(U)).replace("YDATA", c_array(Y))
              .replace("X0", "{" + flat(np.asarray(cartpole.x0)) + "}")
              .replace("QDATA", "{" + flat(Q) + "}").replace("RDATA", "{" + flat(R) + "}")
              .replace("PDATA", "{" + flat(P) + "}"))
    main_c = tmp_path / "main.c"
    main_c.write_text(f"#define T_RUN {T}\n" + source)
    exe = tmp_path / "main"
    wrap = "-Wl,--wrap=malloc,--wrap=calloc,--wrap=realloc,--wrap=free"
    subprocess.run(["gcc", "-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic",
                    str(main_c), *map(str, gn_sources(directory)), f"-I{directory}",
                    wrap, "-lm", "-o", str(exe)], check=True)
    proc = subprocess.run([str(exe)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    assert "allocations 0" in proc.stderr
    X_c = np.loadtxt(proc.stdout.splitlines())
    np.testing.assert_allclose(X_c, gn.run(U, Y, cartpole.x0), rtol=0, atol=1e-12)


def test_status_header_documents_every_code(builds):
    header = (builds["nominal", "mhe_gn"] / "learnest_status.h").read_text()
    for s in STATUSES:
        assert f"#define LEARNEST_{s.name} ({s.code})" in header
        assert s.recovery in header


def test_errors_leave_the_estimator_unchanged(builds, parity_run, cartpole):
    gn = CompiledEmbeddedMHE(builds["nominal", "mhe_gn"])
    with pytest.raises(RuntimeError, match="reset"):
        gn.step(np.zeros(1), parity_run.y[0])
    gn.reset(cartpole.x0)
    for k in range(30):
        gn.step(parity_run.u[k - 1] if k else np.zeros(1), parity_run.y[k])
    window = gn.window
    with pytest.raises(ShapeError):
        gn.step(np.zeros(2), parity_run.y[30])
    with pytest.raises(DataError):
        gn.step(np.zeros(1), np.array([np.inf, 0.0]))
    # a converged solve that cannot reach its tolerance in one iteration: MAX_ITERATIONS (the
    # first sample is a linear least-squares problem, solved in one; the nonlinear ones are not)
    tight = CompiledEmbeddedMHE(builds["nominal", "mhe_gn"],
                                solver=GaussNewtonSettings(max_iterations=1, tolerance=1e-14))
    tight.reset(cartpole.x0)
    for k in range(10):
        before = tight.window
        try:
            tight.step(parity_run.u[k - 1] if k else np.zeros(1), parity_run.y[k])
        except SolverError as exc:
            assert "MAX_ITERATIONS" in str(exc) and k > 0
            np.testing.assert_array_equal(tight.window, before)
            break
    else:
        pytest.fail("one iteration never failed to reach a tolerance of 1e-14")
    np.testing.assert_array_equal(gn.window, window)


def test_manifest_and_mismatch(builds, cartpole):
    m = CompiledEmbeddedMHE(builds["knode", "mhe_rti"]).manifest
    assert (m["estimator"], m["model_kind"], m["precision"], m["solver"]["mode"]) == \
        ("mhe_rti", "knode", "float64", "rti")
    with pytest.raises(ModelMismatchError, match="estimator"):
        CompiledEmbeddedMHE(builds["knode", "mhe"])
    with pytest.raises(ModelMismatchError, match="system"):
        CompiledEmbeddedMHE(builds["knode", "mhe_gn"], expect={"system": "ground_robot"})


def test_settings_validation():
    for bad in ({"mode": "fast"}, {"max_iterations": 0}, {"tolerance": -1.0},
                {"precision": "float16"}, {"tolerance": 1e300}, {"tolerance": 1e-300},
                {"max_iterations": 2**32 + 3}, {"tolerance": 1e-10, "precision": "float32"}):
        with pytest.raises(ValueError):
            GaussNewtonSettings(**bad)
    assert GaussNewtonSettings(precision="float32").tolerance == 1e-4


def test_cli_compiles_and_runs_the_embedded_mhe(tmp_path, cartpole):
    from click.testing import CliRunner

    from learnest_codegen.cli import cli, compile_cmd

    run = simulation.simulate(cartpole, seed=5, duration=100 * cartpole.dt)
    data = tmp_path / "run.csv"
    write_run(run, cartpole, data)
    runner = CliRunner()
    result = runner.invoke(compile_cmd, ["--nominal", "--system", "cartpole", "--estimator",
                                                "mhe_rti", "--out", str(tmp_path / "gen")])
    assert result.exit_code == 0, result.output
    directory = tmp_path / "gen" / "cartpole_nominal_mhe_rti_n20"
    result = runner.invoke(cli, ["estimate", "--system", "cartpole", "--data", str(data),
                                 "--estimator", "mhe_rti", "--compiled", str(directory),
                                 "--out", str(tmp_path / "est.csv")])
    assert result.exit_code == 0, result.output
    written = np.loadtxt(tmp_path / "est.csv", delimiter=",", skiprows=1)[:, 1:]
    expected = CompiledEmbeddedMHE(directory).run(run.u, run.y, cartpole.x0)
    np.testing.assert_allclose(written, expected, rtol=0, atol=1e-12)
    result = runner.invoke(compile_cmd, ["--nominal", "--estimator", "mhe", "--precision",
                                                "float32", "--out", str(tmp_path / "gen")])
    assert result.exit_code == 2 and "cannot be generated in float32" in result.output
    result = runner.invoke(cli, ["estimate", "--data", str(data), "--estimator", "mhe_rti",
                                 "--backend", "python", "--out", str(tmp_path / "x.csv")])
    assert result.exit_code == 2 and "no Python reference" in result.output


def test_float32_embedded_mhe_and_ukf_track_float64(builds, parity_run, cartpole, tmp_path):
    """float32 builds (single-precision FPUs): the embedded MHE's MSE within 1 % of float64 on
    the cartpole; the UKF's within 1 % on the ground robot (on the cartpole its covariance
    loses too many digits: docs/reports/embedded_mhe.md)."""
    model = prior_model(cartpole)
    settings = estimator_kind("mhe").default_settings(model)
    solver = GaussNewtonSettings(mode="rti", precision="float32")
    rti32 = CompiledEmbeddedMHE(generate_embedded_mhe(model, settings, tmp_path / "rti32",
                                                      solver=solver).directory)
    assert rti32.dtype == np.float32 and rti32.manifest["precision"] == "float32"
    X32 = rti32.run(parity_run.u, parity_run.y, cartpole.x0)
    X64 = CompiledEmbeddedMHE(builds["nominal", "mhe_rti"]).run(parity_run.u, parity_run.y, cartpole.x0)
    assert 0 < np.max(np.abs(X32 - X64)) < 1e-2  # it is single precision, and close
    assert abs(mse(X32, parity_run.x) - mse(X64, parity_run.x)) <= 0.01 * mse(X64, parity_run.x)
    with pytest.raises(ModelMismatchError, match="precision"):
        CompiledEmbeddedMHE(rti32.directory, solver=GaussNewtonSettings(mode="rti"))

    from learnest_codegen.codegen.ukf import generate_ukf
    from learnest_codegen.estimators.ukf import UKFSettings
    from learnest_codegen.runtime.ukf import CompiledUKF

    robot = get_system("ground_robot")
    run = simulation.simulate(robot, seed=1, duration=10.0)
    robot_model, ukf_settings = prior_model(robot), UKFSettings.from_system(robot, alpha=0.5)
    with pytest.raises(ValueError, match="float32 UKF needs alpha >= 0.5"):
        generate_ukf(robot_model, UKFSettings.from_system(robot), tmp_path / "bad", precision="float32")
    X = {p: CompiledUKF(generate_ukf(robot_model, ukf_settings, tmp_path / f"ukf_{p}",
                                     precision=p).directory).run(run.u, run.y, robot.x0)
         for p in ("float64", "float32")}
    ref = mse(X["float64"], run.x)
    assert 0 < np.max(np.abs(X["float32"] - X["float64"])) and \
        abs(mse(X["float32"], run.x) - ref) <= 0.01 * ref


def _groups(model):
    return state_groups(*model_functions(model, "m")[:2], model.nx, model.ny)


def test_state_groups_are_read_off_the_jacobians(cartpole):
    """The quadrotor's prior moves each axis on its own and measures each axis's position and
    acceleration: three groups, each with its two outputs. A net that sees every axis's
    velocity and acceleration couples them all; the cartpole is one group."""
    quad = get_system("quadrotor")
    assert _groups(prior_model(quad)) == (((0, 3, 6), (0, 3)), ((1, 4, 7), (1, 4)),
                                          ((2, 5, 8), (2, 5)))
    torch.manual_seed(0)
    assert _groups(hybrid_model(quad, make_net(quad))) == ((tuple(range(9)), tuple(range(6))),)
    assert _groups(prior_model(cartpole)) == (((0, 1, 2, 3), (0, 1)),)


def test_jacobian_patterns_are_the_exact_zeros_of_the_evaluated_jacobians():
    """The tables the kit's assembly skips by (LEARNEST_A_PATTERN, LEARNEST_C_PATTERN): for the
    KNODE quadrotor, A = dF/dx is the identity in the position columns (neither the prior nor
    the net reads the position) and dense elsewhere, C selects position and acceleration; at
    random points every entry outside the tables is exactly 0 (a skipped term adds nothing)."""
    quad = get_system("quadrotor")
    torch.manual_seed(0)
    model = hybrid_model(quad, make_net(quad))
    stage, node, _ = model_functions(model, "m")
    tables = pattern_defines(stage, node, model.nx)
    A_nz = np.array(json.loads(tables["LEARNEST_A_PATTERN"].replace("{", "[").replace("}", "]")))
    C_nz = np.array(json.loads(tables["LEARNEST_C_PATTERN"].replace("{", "[").replace("}", "]")))
    A_nz, C_nz = A_nz.reshape(9, 9).T, C_nz.reshape(9, 6).T  # column-major tables
    expected_A = np.ones((9, 9), dtype=int)
    expected_A[:, :3] = np.eye(9, 3, dtype=int)
    assert np.array_equal(A_nz, expected_A)
    assert np.array_equal(C_nz, np.eye(9, dtype=int)[[0, 1, 2, 6, 7, 8]])
    rng = np.random.default_rng(0)
    for _ in range(5):
        x, u = rng.normal(size=9), rng.uniform(0, 1, size=4)
        A, C = np.array(stage(x, u)[1]), np.array(node(x, u)[1])
        assert np.all(A[A_nz == 0] == 0) and np.all(A[A_nz == 1] != 0)
        assert np.all(C[C_nz == 0] == 0)


def test_separate_axes_are_solved_one_by_one_and_agree_with_ipopt(tmp_path):
    """The grey-box quadrotor (fitted acceleration rows, axes apart): mhe_gn solves the three
    axes' normal equations one by one and equals the Ipopt MHE on every step; the same library
    with an arrival covariance that couples two axes by 1e-9 (so the whole window is solved at
    once) gives the same estimates to that coupling; one RTI step solves this linear model."""
    quad = replace(get_system("quadrotor_linear"),
                   params={"k_v_xy": 1.4, "k_a_xy": 0.3, "k_v_z": 0.8, "k_a_z": 0.5})
    run = simulation.simulate(quad, seed=1, duration=100 * quad.dt)
    model = prior_model(quad)
    settings = mhe_settings(model, estimator_kind("mhe").default_settings(model))
    directory = generate_embedded_mhe(model, settings, tmp_path / "gn").directory
    assert json.loads((directory / "manifest.json").read_text())["state_groups"] == [
        [0, 3, 6], [1, 4, 7], [2, 5, 8]]
    X_ipopt = CompiledMHE(generate_mhe(model, settings, tmp_path / "mhe").directory).run(
        run.u, run.y, quad.x0)
    X_split = CompiledEmbeddedMHE(directory).run(run.u, run.y, quad.x0)
    assert np.max(np.abs(X_split - X_ipopt)) <= PARITY_ATOL
    P = np.array(settings.arrival_covariance)
    P[0, 1] = P[1, 0] = 1e-9 * np.sqrt(P[0, 0] * P[1, 1])
    coupled = replace(settings, arrival_covariance=tuple(map(tuple, P)))
    X_whole = CompiledEmbeddedMHE(directory, settings=coupled).run(run.u, run.y, quad.x0)
    assert 0 < np.max(np.abs(X_whole - X_split)) <= 1e-9
    rti = generate_embedded_mhe(model, settings, tmp_path / "rti", solver=RTI).directory
    X_rti = CompiledEmbeddedMHE(rti).run(run.u, run.y, quad.x0)
    assert np.max(np.abs(X_rti - X_ipopt)) <= PARITY_ATOL
