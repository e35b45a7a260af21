"""The KNODE-EKF: the compiled filter equals FilterPy's ``ExtendedKalmanFilter`` (the Python
reference, :class:`~learnest_codegen.estimators.ekf.EKF`) on the nonlinear KNODE cartpole, and
``learnest-compile --estimator ekf`` and the Python calls build it.

Tolerances: float64 1e-10 of the largest |x| and |P| (the same operations in another order and
FilterPy's Joseph-form covariance update against the kit's ``P - K C P``; measured 2.9e-15 (x)
and 2.3e-15 (P) on this run); float32 2e-3 of the largest |x| (its 7 digits through 250
updates; measured 3.3e-6).
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from filterpy.kalman import ExtendedKalmanFilter

import learnest_codegen as ln
from learnest_codegen.cli import compile_cmd
from learnest_codegen.estimators.ekf import EKF, EKFSettings, jacobians
from learnest_codegen.runtime.ekf import CompiledEKF

MODEL_DIR = Path(__file__).parent / "data" / "model_b12bfa1"
T = 250


@pytest.fixture(scope="module")
def knode(cartpole):
    return ln.resolve(str(MODEL_DIR), cartpole)


@pytest.fixture(scope="module")
def run(cartpole):
    return ln.simulate(cartpole, seed=4, duration=T * cartpole.dt)


def test_reference_is_filterpys_extended_kalman_filter(knode, run, cartpole):
    """The reference written out with FilterPy's ExtendedKalmanFilter by hand: predict with
    F(x, u) and A = dF/dx at the previous estimate, update with h and C = dh/dx (no gate
    rejects anything on this clean run): equal to rounding."""
    model = knode.model
    settings = EKFSettings.from_system(cartpole)
    A, C = jacobians(model)
    kf = ExtendedKalmanFilter(model.nx, model.ny)
    kf.x, kf.P, kf.Q, kf.R = np.array(cartpole.x0, float), settings.P0(), settings.Q(), settings.R()
    ref = EKF(model, settings)
    ref.reset(cartpole.x0)
    for k in range(T):
        u = run.u[max(k - 1, 0)]
        if k > 0:
            kf.F = np.asarray(A(kf.x, u))
            kf.x = model.step(kf.x, u)
            kf.P = kf.F @ kf.P @ kf.F.T + kf.Q
        kf.update(run.y[k], lambda x, u: np.asarray(C(x, u)), model.measure, args=(u,),
                  hx_args=(u,))
        ref.step(u, run.y[k])
        np.testing.assert_allclose(ref.x, kf.x, rtol=0, atol=1e-12 * np.abs(kf.x).max())
        np.testing.assert_allclose(ref.P, kf.P, rtol=0, atol=1e-12 * np.abs(kf.P).max())
    assert ref.rejections == 0


@pytest.mark.parametrize("precision, tolerance", [("float64", 1e-10), ("float32", 2e-3)])
def test_compiled_ekf_equals_filterpy(knode, run, cartpole, tmp_path, precision, tolerance):
    """The compiled KNODE-EKF against the reference over the run, every sample's x and P."""
    c = ln.make_estimator(knode, "ekf", out=tmp_path, precision=precision)
    assert isinstance(c, CompiledEKF) and c.precision == precision
    ref = ln.make_estimator(knode, "ekf", backend="python")
    for est in (c, ref):
        est.reset(cartpole.x0)
    worst_x = worst_P = 0.0
    for k in range(T):
        u = run.u[max(k - 1, 0)]
        x_c, x_r = c.step(u, run.y[k]), ref.step(u, run.y[k])
        worst_x = max(worst_x, np.abs(x_c - x_r).max() / np.abs(x_r).max())
        worst_P = max(worst_P, np.abs(c.P - ref.P).max() / np.abs(ref.P).max())
    assert worst_x < tolerance, worst_x
    if precision == "float64":
        assert worst_P < tolerance, worst_P


def test_learnest_compile_builds_the_ekf(tmp_path, cartpole, run):
    """``learnest-compile --nominal --estimator ekf`` writes the folder; loading it gives the EKF,
    equal to the Python reference of the nominal model."""
    r = CliRunner().invoke(compile_cmd, ["--nominal", "--estimator", "ekf", "--out",
                                                str(tmp_path)], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    folder = tmp_path / "cartpole_nominal_ekf"
    assert r.output.startswith(f"ekf: {folder}")
    est = ln.load_estimator(folder)
    assert isinstance(est, CompiledEKF) and est.manifest["estimator"] == "ekf"
    X_c = est.run(run.u, run.y, cartpole.x0)
    ref = ln.make_estimator("nominal", "ekf", backend="python", system=cartpole)
    X_r = ref.run(run.u, run.y, cartpole.x0)
    assert np.abs(X_c - X_r).max() <= 1e-10 * np.abs(X_r).max()


def test_plain_c_main_two_instances_and_no_allocation(knode, run, cartpole, tmp_path):
    """test_embedded_mhe.py's firmware-style main over the KNODE-EKF: malloc, calloc, realloc
    and free wrapped and counted over init and every step (none), two handles interleaved, the
    estimates those of the binding to 1e-12."""
    from test_embedded_mhe import C_MAIN, c_array, gn_sources

    est = ln.make_estimator(knode, "ekf", out=tmp_path / "gen")
    prefix, directory = est.manifest["prefix"], est.directory
    T = 60
    U, Y = run.u[:T], run.y[:T]
    s = est.settings
    flat = lambda M: "{" + c_array(M.ravel()).strip("{}") + "}"  # noqa: E731
    source = (C_MAIN.replace("PREFIX_UP", prefix.upper()).replace("PREFIX", prefix)
              .replace("UDATA", c_array(U)).replace("YDATA", c_array(Y))
              .replace("X0", flat(np.asarray(cartpole.x0))).replace("QDATA", flat(s.Q()))
              .replace("RDATA", flat(s.R())).replace("PDATA", flat(s.P0())))
    main_c = tmp_path / "main.c"
    main_c.write_text(f"#define T_RUN {T}\n" + source)
    exe = tmp_path / "main"
    subprocess.run(["gcc", "-O2", "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", str(main_c),
                    *map(str, gn_sources(directory)), f"-I{directory}",
                    "-Wl,--wrap=malloc,--wrap=calloc,--wrap=realloc,--wrap=free", "-lm", "-o", str(exe)],
                   check=True)
    proc = subprocess.run([str(exe)], capture_output=True, text=True)
    assert proc.returncode == 0 and "allocations 0" in proc.stderr, proc.stderr
    X_c = np.loadtxt(proc.stdout.splitlines())
    np.testing.assert_allclose(X_c, est.run(U, Y, cartpole.x0), rtol=0, atol=1e-12)
