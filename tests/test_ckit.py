"""The C kit on its own: built without any generated code, checked against independent references.

``tests/ckit/*.c`` wrap the kit (``learnest_codegen/ckit``) in plain functions (``kit_core.c``:
dense algebra, the block-tridiagonal solve, the gate, the MHE window) or instantiate its
estimators over a hand-written linear model (``kit_ukf.c``, ``kit_gn.c``, ``kit_ekf.c``;
``kit_gn_groups.c``: a model whose states fall apart in groups), or over that model written by
hand in CasADi's calling convention (``kit_casadi.h``) behind ``learnest_casadi.h``'s hooks
(``kit_casadi_gn.c``; ``kit_casadi_ukf.c``: the UKF's own sigma points; ``kit_ipopt.c``: the
Ipopt MHE over a hand-written nlpsol linked to the casadi wheel's libipopt), or over a nonlinear
model written by hand in the scalar and the lane-parallel form (``kit_lanes.h``: the batch hooks,
the UKF's batched sigma points in ``kit_lanes_ukf.c``, the MHE's batched stages in
``kit_lanes_gn.c``, each against its scalar build, closed forms, FilterPy and the Python MHE).
Each is compiled under ``-std=c99 -Wall -Wextra -Werror -pedantic`` with gcc and clang, in double and float
(``kit_ipopt.c``: double, Ipopt's precision), and as C++ with g++; the results are compared
with numpy.linalg, a dense solve, the Python gate (``estimators/gate.py``), the Python MHE's
window bookkeeping (``estimators/mhe.py``, ``mhe_window.py``), the Ipopt MHE (CasADi's
nlpsol) and FilterPy's Kalman and unscented Kalman filters.
"""

from __future__ import annotations

import ctypes
import platform
import re
import shutil
import subprocess
from dataclasses import replace
from pathlib import Path

import casadi as cs
import numpy as np
import pytest
from conftest import rounding, unscented_rounding
from test_ukf import update_gain

from learnest_codegen import NoiseModel, Signal, System, get_system
from learnest_codegen.codegen.mhe import arrival_defines, bounds_defines
from learnest_codegen.codegen.mhe_gn import model_functions, pattern_defines
from learnest_codegen.codegen.templates import KIT, kit_files, status_header_text, write_kit
from learnest_codegen.estimators.ekf import EKF, EKFSettings
from learnest_codegen.estimators.gate import GateSettings, GateState
from learnest_codegen.estimators.mhe import MHE
from learnest_codegen.estimators.mhe_gn import DEFAULT_TOLERANCE
from learnest_codegen.estimators.mhe_problem import MHESettings, mhe_settings
from learnest_codegen.export import DiscreteModel, prior_model
from learnest_codegen.runtime.limits import LIMITS
from learnest_codegen.runtime.status import STATUS_NAMES
from learnest_codegen.toolchain import casadi_dirs

SOURCES = Path(__file__).resolve().parent / "ckit"
COMPILERS = [cc for cc in ("gcc", "clang") if shutil.which(cc)]
FLAGS = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic", "-fno-math-errno",
         "-ffp-contract=off"]
DTYPES = {"double": np.float64, "float": np.float32}
CODES = {name: code for code, name in STATUS_NAMES.items()}
SOURCE_NAMES = ["kit_core", "kit_gn", "kit_gn_groups", "kit_ukf", "kit_ekf", "kit_casadi_gn",
                "kit_casadi_ukf", "kit_ipopt", "kit_lanes_ukf", "kit_lanes_gn"]
CASADI_INCLUDE, CASADI_LIB = casadi_dirs()
#: What a source needs besides the kit: Ipopt's headers and library (the casadi wheel's, as
#: codegen/mhe.py links a generated Ipopt MHE).
EXTRA = {"kit_ipopt": {"compile": [f"-I{CASADI_INCLUDE / 'coin-or'}"],
                       "link": [f"-L{CASADI_LIB}", f"-Wl,-rpath,{CASADI_LIB}", "-lipopt"]}}
#: The precisions a source builds in (Ipopt solves in double only).
REALS = {"kit_ipopt": ("double",)}
N = 5  # kit_core.c's horizon; its sizes are the cartpole's (NX 4, NU 1, NY 2)


@pytest.fixture(scope="module")
def kit(tmp_path_factory):
    """The kit as a generated folder gets it (``write_kit``; the kit's own folder, compiled
    in place, is the same files: ``test_the_kit_is_what_a_folder_gets``)."""
    root = tmp_path_factory.mktemp("kit")
    write_kit(root)
    return root


@pytest.fixture(scope="module")
def libraries(kit):
    """(source, compiler, real) -> a loaded shared library, built on first use."""
    cache = {}

    def get(source: str, cc: str = "gcc", real: str = "double", defines: dict | None = None):
        """``defines``: more macros, as a generated glue sets them (``{"LEARNEST_STATE_LO": ...}``)."""
        macros = tuple(f"-D{name}={value}" for name, value in sorted((defines or {}).items()))
        key = (source, cc, real, macros)
        if key not in cache:
            library = kit / f"{source}_{cc}_{real}_{len(cache)}.so"
            extra = EXTRA.get(source, {})
            command = [cc, *FLAGS, f"-DKIT_REAL={real}", *macros, f"-I{kit}", *extra.get("compile", []),
                       "-fPIC", "-shared", str(SOURCES / f"{source}.c"), "-o", str(library),
                       *extra.get("link", []), "-lm"]
            proc = subprocess.run(command, capture_output=True, text=True)
            assert proc.returncode == 0, f"{' '.join(command)}\n{proc.stderr}"
            cache[key] = Kit(ctypes.CDLL(str(library)), DTYPES[real])
        return cache[key]
    return get


class Kit:
    """A loaded test library: calls with numpy arrays of its real type."""

    def __init__(self, lib, dtype):
        self.lib, self.dtype = lib, dtype
        self.c_real = ctypes.c_float if dtype == np.float32 else ctypes.c_double

    def a(self, values) -> np.ndarray:
        """A C-contiguous copy of ``values`` in the library's real type (the C may write it)."""
        return np.array(values, dtype=self.dtype, order="C")

    def __call__(self, name, *args, restype=ctypes.c_int):
        fn = getattr(self.lib, name)
        fn.restype = restype
        converted = []
        for arg in args:
            if isinstance(arg, np.ndarray):
                converted.append(arg.ctypes.data_as(ctypes.c_void_p))
            elif isinstance(arg, float):
                converted.append(self.c_real(arg))
            else:
                converted.append(arg)
        return fn(*converted)


def random_spd(rng, n, scale=1.0):
    A = rng.normal(size=(n, n))
    return scale * (A @ A.T + 0.5 * np.eye(n))


def tolerance(dtype) -> float:
    return 1e-11 if dtype == np.float64 else 2e-4


# -- builds ------------------------------------------------------------------------------

@pytest.mark.parametrize("cc", COMPILERS)
@pytest.mark.parametrize("source", SOURCE_NAMES)
def test_builds_warning_free_in_c_and_cpp(kit, source, cc):
    """Every test source (so every kit header) under -Werror with gcc and clang in double and
    float (the library fixture), and as C++11 with g++."""
    include = EXTRA.get(source, {}).get("compile", [])
    for real in REALS.get(source, DTYPES):
        proc = subprocess.run([cc, *FLAGS, f"-DKIT_REAL={real}", f"-I{kit}", *include, "-fsyntax-only",
                               str(SOURCES / f"{source}.c")], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
    if cc == "gcc" and shutil.which("g++"):
        proc = subprocess.run(["g++", "-x", "c++", "-std=c++11", "-Wall", "-Wextra", "-Werror",
                               "-pedantic", f"-I{kit}", *include, "-fsyntax-only",
                               str(SOURCES / f"{source}.c")], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr


def test_the_kit_is_what_a_folder_gets(kit):
    names = {p.name for p in kit_files()}
    assert {"learnest_kit.h", "learnest_gn.h", "learnest_window.h", "learnest_ukf.h",
            "learnest_status.h"} <= names
    assert {p.name for p in kit.iterdir() if p.suffix == ".h"} == names
    assert all((kit / name).read_text() == (p.read_text()) for name, p in
               ((p.name, p) for p in kit_files()))
    status = (kit / "learnest_status.h").read_text()
    for limit in (lim for lim in LIMITS.values() if lim.c_name):
        high = re.search(rf"#define LEARNEST_{limit.c_name}_MAX (\S+)", status).group(1)
        assert float(high) == limit.high
    assert "#define LEARNEST_INPUT_REJECTED (2)" in status


def test_the_status_header_is_the_status_table():
    """ckit/learnest_status.h is a header of the kit (it builds without Python) and the
    rendering of runtime/status.py and limits.py; after a change to either, run
    ``python -c "from learnest_codegen.codegen.templates import write_status_header as w; w()"``."""
    assert (KIT / "learnest_status.h").read_text() == status_header_text()


@pytest.mark.parametrize("source", SOURCE_NAMES)
def test_builds_from_the_kit_folder_alone(source):
    """Every test source compiles against learnest_codegen/ckit itself: no file written by
    Python."""
    proc = subprocess.run(["gcc", *FLAGS, "-DKIT_REAL=double", f"-I{KIT}",
                           *EXTRA.get(source, {}).get("compile", []), "-fsyntax-only",
                           str(SOURCES / f"{source}.c")], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


# -- dense algebra -----------------------------------------------------------------------

@pytest.mark.parametrize("cc", COMPILERS)
@pytest.mark.parametrize("real", list(DTYPES))
def test_dense_algebra_equals_numpy(libraries, cc, real):
    k = libraries("kit_core", cc, real)
    tol = tolerance(k.dtype)
    rng = np.random.default_rng(0)
    for n in range(1, 7):
        A = random_spd(rng, n)
        M = k.a(A.T)  # column-major
        assert k("kt_cholesky", M, n) == 1
        L = np.tril(M.reshape(n, n).T.astype(float))
        np.testing.assert_allclose(L, np.linalg.cholesky(A), rtol=0, atol=tol * np.abs(A).max())
        b = rng.normal(size=n)
        Lc = k.a(L.T)
        x = k.a(b)
        k("kt_forward", Lc, n, x)
        np.testing.assert_allclose(x, np.linalg.solve(L, b), rtol=0, atol=tol * 10 * np.abs(b).max())
        x = k.a(b)
        k("kt_backward", Lc, n, x)
        np.testing.assert_allclose(x, np.linalg.solve(L.T, b), rtol=0, atol=tol * 10 * np.abs(b).max())
        inv = k.a(np.zeros((n, n)))
        assert k("kt_spd_inverse", k.a(A), n, inv) == 1
        expected = np.linalg.inv(A)
        np.testing.assert_allclose(inv, expected, rtol=0, atol=tol * 100 * np.abs(expected).max())
        d = rng.uniform(0.1, 3, size=n) ** 2
        inv = k.a(np.zeros((n, n)))
        assert k("kt_spd_inverse", k.a(np.diag(d)), n, inv) == 1
        np.testing.assert_array_equal(np.diag(inv), (1 / k.a(d)))  # the diagonal rule: exact
        r = rng.normal(size=n)
        assert k("kt_quad", k.a(A.T), k.a(r), n, restype=k.c_real) == pytest.approx(r @ A @ r, rel=tol * 10)
        assert k("kt_covariance_ok", k.a(A), n) == 1
        if n > 1:
            indefinite = A - 2 * np.linalg.eigvalsh(A).max() * np.outer(np.eye(n)[0], np.eye(n)[0])
            skew = A + np.triu(np.ones((n, n)), 1) * np.abs(A).max()
            for bad in (indefinite, skew):
                assert k("kt_covariance_ok", k.a(bad), n) == 0
            # the inverse reads a symmetric matrix (its callers check symmetry first)
            assert k("kt_spd_inverse", k.a(indefinite), n, k.a(np.zeros((n, n)))) == 0
    assert k("kt_covariance_ok", k.a(np.zeros((3, 3))), 3) == 1  # semidefinite is a covariance
    assert k("kt_spd_inverse", k.a(np.zeros((3, 3))), 3, k.a(np.zeros((3, 3)))) == 0


@pytest.mark.parametrize("cc", COMPILERS)
@pytest.mark.parametrize("real", list(DTYPES))
def test_block_tridiagonal_solve_equals_a_dense_solve(libraries, cc, real):
    """H dx = -g for a random SPD block-tridiagonal H of N+1 blocks of 4 x 4."""
    k = libraries("kit_core", cc, real)
    nx, rng = 4, np.random.default_rng(1)
    for _ in range(5):
        blocks = [rng.normal(size=(2 * nx, 2 * nx)) for _ in range(N)]
        H = np.zeros(((N + 1) * nx, (N + 1) * nx))
        for i, B in enumerate(blocks):  # a sum of stage terms J_i' J_i: SPD, block tridiagonal
            H[i * nx:(i + 2) * nx, i * nx:(i + 2) * nx] += B.T @ B
        H += 0.1 * np.eye(len(H))
        D = np.stack([H[i * nx:(i + 1) * nx, i * nx:(i + 1) * nx].T for i in range(N + 1)])
        E = np.stack([H[(i + 1) * nx:(i + 2) * nx, i * nx:(i + 1) * nx].T for i in range(N)])
        g = rng.normal(size=len(H))
        Dc, Ec, dx = k.a(D), k.a(E), k.a(np.zeros(len(H)))
        assert k("kt_btd_solve", Dc, Ec, k.a(g), dx) == 1
        expected = np.linalg.solve(H, -g)
        scale = np.abs(expected).max() * np.linalg.cond(H)
        np.testing.assert_allclose(dx, expected, rtol=0, atol=tolerance(k.dtype) * scale)
    H = -np.eye((N + 1) * nx)  # not positive definite: refused
    D = np.stack([H[:nx, :nx]] * (N + 1))
    assert k("kt_btd_solve", k.a(D), k.a(np.zeros((N, nx, nx))), k.a(np.ones(len(H))),
             k.a(np.zeros(len(H)))) == 0


# -- the gate ------------------------------------------------------------------------------

@pytest.mark.parametrize("cc", COMPILERS)
def test_gate_equals_the_python_gate(libraries, cc):
    """Random normalised innovations and validity: the C gate rejects the same outputs, keeps
    the same per-output streaks, inflation and age, ends the same episodes, loses and re-seeds
    the same tracks and returns the same factors as estimators/gate.py."""
    k = libraries("kit_core", cc, "double")
    settings = GateSettings(threshold=9.0, recover_after=3, inflation=2.0)
    g = np.zeros(k("kt_gate_size", restype=ctypes.c_size_t), dtype=np.uint8)
    k("kt_gate_defaults", g, 9.0, 3, 2.0, 1e4, restype=None)
    py = GateState(settings, 2)
    assert py.lost_after == 3 + 13  # 2**13 <= 1e4 < 2**14
    rng = np.random.default_rng(2)
    rho, streaks, episodes = ctypes.c_double(), np.zeros(2, dtype=np.intc), 0
    age, lost, reseeds, lost_steps = ctypes.c_int(), ctypes.c_int(), 0, 0
    for step in range(3000):
        phase = (step // 300) % 3  # clean-ish, a lost track, long gaps
        p = ([0.3, 0.2, 0.2, 0.2, 0.1], [0.02, 0.02, 0.06, 0.8, 0.1], [0.3, 0.2, 0.2, 0.2, 0.1])[phase]
        d2 = rng.choice([0.5, 3.0, 20.0, 1e6, np.nan], size=2, p=p)
        rate = ([0.9, 0.3], [0.9, 0.6], [0.05, 0.02])[phase]
        valid = (rng.random(2) < rate).astype(np.uint8)  # a fast and a slow output
        rejected = np.zeros(2, dtype=np.intc)
        any_c = k("kt_gate_test", g, k.a(d2), valid, rejected)
        expected = py.test(d2, valid.astype(bool))
        np.testing.assert_array_equal(rejected.astype(bool), expected, err_msg=f"step {step}")
        assert any_c == int(expected.any())
        reseed = k("kt_gate_reseeds", g, rejected)
        assert reseed == int(py.reseeds(expected)), f"step {step}"
        if reseed:
            expected = np.zeros(2, dtype=bool)
            assert not rejected.any()
        reseeds += reseed
        ends = k("kt_gate_ends_episode", g, rejected, valid)
        assert ends == int(py.ends_episode(expected, valid.astype(bool)))
        episodes += ends
        factor = k("kt_gate_record", g, rejected, valid, restype=ctypes.c_double)
        assert factor == py.record(expected, valid.astype(bool))
        k("kt_gate_state", g, ctypes.byref(rho), streaks, ctypes.byref(age), ctypes.byref(lost),
          restype=None)
        assert rho.value == py.inflation and streaks.tolist() == py.streaks.tolist()
        assert (age.value, lost.value) == (py.age, int(py.lost)), f"step {step}"
        lost_steps += lost.value
    assert episodes > 0 and py.inflation >= 1 and reseeds > 0 and lost_steps > 0
    # out of range: refused, nothing changed
    for bad in ((0.5, 3, 2.0), (-1.0, 3, 2.0), (np.nan, 3, 2.0), (9.0, 0, 2.0), (9.0, 10**7, 2.0),
                (9.0, 3, 1.0), (9.0, 3, 1e4), (9.0, 3, np.inf)):
        assert k("kt_gate_set", g, float(bad[0]), bad[1], float(bad[2])) == CODES["BAD_ARGUMENT"]
    assert k("kt_gate_set", g, 0.0, 3, 2.0) == 0 and k("kt_gate_set", g, float("inf"), 3, 2.0) == 0


# -- the MHE window ------------------------------------------------------------------------

def test_window_equals_the_python_mhe_bookkeeping(libraries):
    """The C window (shift, arrival update, per-output weights G, gate, restart, the arrival
    weight carried after a restart) against the Python MHE's own ``_advance`` over a random
    sequence: missing outputs, outliers that trip the gate and its recovery, failed solves that
    restart the window. Both are given the same stand-in solutions; every array of the window
    and the warm start must be equal, bit for bit where both copy or shift the same values, and
    to rounding where they compute: the restart prior (a Kalman update, numpy's LU solve against
    the kit's Cholesky), which stays the window's ``xbar`` until the window is full again, and
    the carried arrival weight (a covariance recursion and its inverse). A second build with
    the cartpole's Jacobian patterns (LEARNEST_A_PATTERN, LEARNEST_C_PATTERN: the carry, the gate
    and the Kalman update skip their structural zeros) runs alongside and must equal the dense
    build bit for bit on every step."""
    k = libraries("kit_core", "gcc", "double")
    cartpole = get_system("cartpole")
    model = prior_model(cartpole)
    patterns = pattern_defines(*model_functions(model, "m")[:2], model.nx)
    assert set(patterns) == {"LEARNEST_A_PATTERN", "LEARNEST_C_PATTERN"}  # both have zeros
    kp = libraries("kit_core", "gcc", "double", patterns)
    settings = mhe_settings(model, MHESettings.from_system(cartpole, horizon=N,
                                                           gate=GateSettings(recover_after=3)))
    mhe = MHE(model, settings)
    rng = np.random.default_rng(3)
    x0 = np.array(cartpole.x0, dtype=float)
    Q, R, P0 = settings.covariances()
    mhe.reset(x0)
    m = np.zeros(k("kt_mhe_size", restype=ctypes.c_size_t), dtype=np.uint8)
    assert k("kt_mhe_reset", m, k.a(x0), k.a(P0), k.a(Q), k.a(R)) == 0
    g = np.zeros(k("kt_gate_size", restype=ctypes.c_size_t), dtype=np.uint8)
    gate = settings.gate
    k("kt_gate_defaults", g, gate.threshold, gate.recover_after, gate.inflation, 1e4, restype=None)
    mp, gp = m.copy(), g.copy()  # the pattern build's state, driven alongside
    n1, restarts, rejections, carried_steps, reseeds = N + 1, 0, 0, 0, 0
    prior = None  # (Python's restart prior, its tolerance) while it is the window's xbar
    for step in range(300):
        u = rng.normal(size=1)
        y = model.measure(mhe.x, u) + 0.01 * rng.normal(size=2)
        if 100 <= step < 106 or 200 <= step < 230 or rng.random() < 0.03:
            y = y + 5.0  # gross: rejected; six in a row trip the recovery, thirty lose the track
        valid = rng.random(2) < 0.85
        y = np.where(valid, y, np.nan)  # a missing output's value is never read
        has_previous = mhe._count > 0
        if rng.random() < 0.03 and has_previous:  # a failed solve: both restart next step
            mhe._restart = True
            k("kt_mhe_fail", m, restype=None)
            kp("kt_mhe_fail", mp, restype=None)
        x_pred = model.step(mhe.x, u) if has_previous else x0  # the warm start's last state
        # where a carried arrival covariance moves on: the leaving stage X[0] (Python's _carried)
        H0 = np.asarray(mhe._meas(mhe._window[0], mhe._now.U[0])[1])
        A0 = np.asarray(mhe._jac(mhe._window[0], mhe._now.U[1]))
        rejected_before = mhe._gate.test(np.full(2, np.inf), valid) if mhe._gate.lost else np.zeros(2, bool)
        cov_in = mhe._P_run_cov if mhe._arrival_cov is None else mhe._arrival_cov  # the gate's
        rho = mhe._gate.inflation
        nxt = mhe._advance(u, y, valid)
        window, guess, rejected = nxt.window, nxt.guess, nxt.rejected
        h, C = (np.asarray(v) for v in mhe._meas(x_pred, u))
        k("kt_mhe_advance", m, int(has_previous), k.a(u), k.a(x_pred), k.a(H0.T), k.a(A0.T),
          restype=None)
        kp("kt_mhe_advance", mp, int(has_previous), k.a(u), k.a(x_pred), k.a(H0.T), k.a(A0.T),
           restype=None)
        rej, restarted = np.zeros(2, dtype=np.intc), ctypes.c_int()
        any_c = k("kt_mhe_gate", m, g, int(has_previous), k.a(u), k.a(y), valid.astype(np.uint8),
                  k.a(h.ravel()), k.a(C.T), rej, ctypes.byref(restarted))
        rej_p, restarted_p = np.zeros(2, dtype=np.intc), ctypes.c_int()
        assert kp("kt_mhe_gate", mp, gp, int(has_previous), k.a(u), k.a(y), valid.astype(np.uint8),
                  k.a(h.ravel()), k.a(C.T), rej_p, ctypes.byref(restarted_p)) == any_c
        assert np.array_equal(rej_p, rej) and restarted_p.value == restarted.value
        np.testing.assert_array_equal(rej.astype(bool), rejected, err_msg=f"step {step}")
        assert any_c == int(rejected.any())
        blocks = [np.zeros(s) for s in (4, n1, 2 * n1, n1, 2 * n1, 4 * n1)]
        k("kt_mhe_next", m, *blocks, restype=None)
        blocks_p = [np.zeros_like(b) for b in blocks]
        kp("kt_mhe_next", mp, *blocks_p, restype=None)
        for b, b_p in zip(blocks, blocks_p):  # the same bits (a NaN nowhere: compared as bytes)
            assert b.tobytes() == b_p.tobytes(), f"step {step}"
        xbar, U, Y, mask, G, Xn = blocks
        np.testing.assert_array_equal(U, window.U.ravel(), err_msg=f"step {step}")
        np.testing.assert_array_equal(Y, window.Y.ravel(), err_msg=f"step {step}")
        np.testing.assert_array_equal(mask, window.mask, err_msg=f"step {step}")
        np.testing.assert_array_equal(G, window.G.ravel(), err_msg=f"step {step}")
        restarts += restarted.value
        reseeds += int(restarted.value and rejected_before.any() and not rejected.any())
        if restarted.value:
            prior = (window.xbar.copy(), restart_tolerance(x_pred, window.xbar, C, rho * cov_in,
                                                           mhe._R_cov, valid & ~rejected))
            np.testing.assert_allclose(Xn, np.tile(xbar, n1), rtol=0, atol=0)  # xbar copied
        elif prior is not None and not np.array_equal(window.xbar, prior[0]):
            prior = None  # the window is full: xbar moved on to the committed solution's X[1]
        if prior is not None:  # computed on both sides: to rounding
            np.testing.assert_allclose(xbar, window.xbar, rtol=0, atol=prior[1], err_msg=f"step {step}")
        else:
            np.testing.assert_array_equal(xbar, window.xbar, err_msg=f"step {step}")
        if restarted.value:
            np.testing.assert_allclose(Xn, guess.ravel(), rtol=0, atol=prior[1])
        else:  # shifted from the committed solution, the new stage predicted by the same F
            np.testing.assert_array_equal(Xn, guess.ravel(), err_msg=f"step {step}")
        X = guess + 1e-3 * rng.normal(size=guess.shape)  # a stand-in solution, the same for both
        k("kt_mhe_commit", m, k.a(X.ravel()), restype=None)
        kp("kt_mhe_commit", mp, k.a(X.ravel()), restype=None)
        mhe._commit(nxt, X)
        Qc, Rc, Pc = np.zeros((4, 4)), np.zeros((2, 2)), np.zeros((4, 4))
        k("kt_mhe_weights", m, Qc, Rc, Pc, restype=None)
        Pc_p = np.zeros((4, 4))
        kp("kt_mhe_weights", mp, np.zeros((4, 4)), np.zeros((2, 2)), Pc_p, restype=None)
        assert Pc_p.tobytes() == Pc.tobytes(), f"step {step}"
        carried = mhe._arrival_cov is not None
        assert k("kt_mhe_carried", m) == int(carried), f"step {step}"
        assert kp("kt_mhe_carried", mp) == int(carried), f"step {step}"
        # the carried covariance's recursion (products and a Kalman update of nx x nx matrices)
        # and its inverse: at most nx^3 operations into an entry, amplified by the inverse's
        # condition number
        W = mhe.arrival_weight
        tol = rounding(ops=4**3, cond=np.linalg.cond(W)) * np.abs(W).max()
        np.testing.assert_allclose(Pc, W, rtol=0, atol=tol, err_msg=f"step {step}")
        carried_steps += carried
        k("kt_gate_record", g, rej, valid.astype(np.uint8), restype=ctypes.c_double)
        kp("kt_gate_record", gp, rej, valid.astype(np.uint8), restype=ctypes.c_double)
        rejections += int(rejected.sum())
    # the recovery, the re-seed, the failures and the carried arrival covariance were exercised
    assert restarts >= 3 and rejections >= 6 and carried_steps >= 3 * n1 and reseeds >= 1


def restart_tolerance(x_pred, xbar, C, P, R, keep) -> float:
    """How far two roundings of the restart prior ``xbar = x_pred + K (y - h)`` (``K = diag(P)
    C' S^-1``, ``S = C diag(P) C' + R`` over the kept outputs) may lie apart: at most
    ``(nx + ny)^2`` operations into an entry (forming ``S``, solving for ``K``, applying it),
    amplified by the condition number of ``S``, on the scale of the largest ``|x_pred| +
    |K (y - h)|``."""
    nx, ny = len(x_pred), len(keep)
    if not keep.any():  # no update: the prediction itself, copied
        return 0.0
    Ck = C[keep]
    S = Ck @ np.diag(np.diag(P)) @ Ck.T + R[np.ix_(keep, keep)]
    scale = np.max(np.abs(x_pred) + np.abs(xbar - x_pred))
    return rounding(ops=(nx + ny) ** 2, cond=np.linalg.cond(S)) * scale


# -- the kit's estimators over a linear model ----------------------------------------------

def linear_system() -> System:
    """A mass-spring-damper with both states measured: RK4 of it is linear."""
    def dynamics(ops, x, u, p):
        return [x[1], (-p["k"] * x[0] - p["c"] * x[1] + u[0]) / p["m"]]

    return System(
        name="msd2", states=(Signal("q", "m"), Signal("v", "m/s")), inputs=(Signal("F", "N"),),
        outputs=(Signal("q", "m"), Signal("v", "m/s")), params={"m": 2.0, "k": 3.0, "c": 0.4},
        true_params={"m": 2.0, "k": 3.0, "c": 0.4}, dynamics=dynamics,
        measurement=lambda ops, x, u, p: [x[0], x[1]],
        noise=NoiseModel(measurement_std=(0.05, 0.1), state_std=(0.01, 0.01),
                         process_std=(1e-3, 1e-2), initial_std=(0.5, 0.5)),
        dt=0.05, duration=10.0, x0=(1.0, 0.0),
        excitation=lambda t, rng: np.sin(t + rng.uniform())[:, None])


@pytest.fixture(scope="module")
def linear():
    """The linear system, its matrices (Phi, Gamma, C) and a simulated run with missing outputs."""
    from learnest_codegen.simulation import simulate

    system = linear_system()
    model = prior_model(system)
    Phi = np.stack([model.step(e, np.zeros(1)) for e in np.eye(2)], axis=1)
    Gamma = model.step(np.zeros(2), np.ones(1))[:, None]
    run = simulate(system, seed=0, duration=8.0)
    valid = np.random.default_rng(4).random(run.y.shape) < 0.7
    valid[40:50] = False  # ten samples with no output: ten predictions
    return system, model, (Phi, Gamma, np.eye(2)), run, valid


def start(k, prefix, model_matrices, x0, P0, Q, R):
    """init a kit estimator on a numpy workspace and set its linear model."""
    memory = np.zeros(k(f"{prefix}_workspace_size", restype=ctypes.c_size_t), dtype=np.uint8)
    handle = ctypes.c_void_p()
    assert k(f"{prefix}_init", memory, ctypes.c_size_t(memory.nbytes),
             *(k.a(a) for a in (x0, P0, Q, R)), ctypes.byref(handle)) == 0
    if model_matrices is not None:  # None: the source's model is fixed (kit_lanes.h)
        Phi, Gamma, C = model_matrices
        assert k("kt_set_model", handle, k.a(Phi.T), k.a(Gamma.T), k.a(C.T)) == 0
    return memory, handle


@pytest.mark.parametrize("cc", COMPILERS)
@pytest.mark.parametrize("prefix, source", [("tukf", "kit_ukf"), ("tekf", "kit_ekf")])
def test_kalman_filters_equal_a_kalman_filter_skipping_missing_updates(libraries, linear, cc,
                                                                      prefix, source):
    """The kit's UKF logic over the Kalman filter's predict and masked update, and the kit's
    EKF (docs/guide/c_kit.md's worked example) over the linear model: both equal FilterPy's
    KalmanFilter that predicts every sample after the first and updates on the outputs present
    only (none: no update), to 1e-12."""
    from filterpy.kalman import KalmanFilter

    k = libraries(source, cc, "double")
    system, model, matrices, run, valid = linear
    Q, R = np.diag(np.square(system.noise.process_std)), np.diag(np.square(system.noise.measurement_std))
    P0, x0 = np.diag(np.square(system.noise.initial_std)), np.array(system.x0, dtype=float)
    memory, h = start(k, prefix, matrices, x0, P0, Q, R)
    kf = KalmanFilter(dim_x=2, dim_z=2)
    kf.F, kf.B, kf.Q, kf.x, kf.P = matrices[0], matrices[1], Q, x0.copy(), P0.copy()
    x, P = k.a(np.zeros(2)), k.a(np.zeros((2, 2)))
    for i in range(len(run.y)):
        u = run.u[max(i - 1, 0)]
        if i > 0:
            kf.predict(u=u)
        keep = valid[i]
        if keep.any():
            kf.update(run.y[i][keep], R=R[np.ix_(keep, keep)], H=np.eye(2)[keep])
        y = np.where(keep, run.y[i], np.nan)  # a missing output may hold NaN
        code = k(f"{prefix}_step", h, k.a(u), k.a(y), keep.astype(np.uint8))
        assert code == 0
        k(f"{prefix}_get_state", h, x)
        k(f"{prefix}_get_covariance", h, P)
        np.testing.assert_allclose(x, kf.x, rtol=0, atol=1e-12 * np.abs(kf.x).max())
        np.testing.assert_allclose(P, kf.P, rtol=0, atol=1e-12 * np.abs(kf.P).max())
    assert k(f"{prefix}_samples", h) == len(run.y)


@pytest.mark.parametrize("cc", COMPILERS)
def test_embedded_mhe_equals_the_ipopt_mhe_with_missing_outputs(libraries, linear, cc):
    """The kit's Gauss-Newton MHE (converged) over the linear model against the Python MHE
    (CasADi's nlpsol with Ipopt) of the same model, with outputs missing at random and ten
    samples without any: the same estimates to 1e-7."""
    k = libraries("kit_gn", cc, "double")
    system, model, matrices, run, valid = linear
    settings = mhe_settings(model, MHESettings.from_system(system, horizon=6))  # as every door
    Q, R, P0 = settings.covariances()
    x0 = np.array(system.x0, dtype=float)
    memory, h = start(k, "tgn", matrices, x0, P0, Q, R)
    assert k("tgn_set_arrival", h, k.a(P0)) == 0  # the running arrival covariance: the same
    gate = settings.gate
    assert k("tgn_set_gate", h, gate.threshold, gate.recover_after, gate.inflation) == 0
    T = 120
    Y = np.where(valid[:T], run.y[:T], np.nan)  # a missing output may hold NaN
    X_c = k.a(np.zeros((T, 2)))
    assert k("tgn_run", h, T, k.a(run.u[:T]), k.a(Y), valid[:T].astype(np.uint8), X_c) == 0
    X_py = MHE(model, settings).run(run.u[:T], Y, x0, valid=valid[:T])
    np.testing.assert_allclose(X_c, X_py, rtol=0, atol=1e-7)
    assert np.abs(X_c - run.x[:T]).mean() < 0.05
    # samples 43..49 have no output: the window after sample 49 is its arrival prior and six
    # predictions, F of each state with the input of the next sample
    memory, h = start(k, "tgn", matrices, x0, P0, Q, R)
    assert k("tgn_set_arrival", h, k.a(P0)) == 0
    assert k("tgn_run", h, 50, k.a(run.u[:50]), k.a(Y[:50]), valid[:50].astype(np.uint8),
             k.a(np.zeros((50, 2)))) == 0
    window = k.a(np.zeros((7, 2)))
    assert k("tgn_get_window", h, window) == 0
    Phi, Gamma, _ = matrices
    for i in range(6):
        predicted = Phi @ window[i] + Gamma @ run.u[43 + i]
        np.testing.assert_allclose(window[i + 1], predicted, rtol=0, atol=1e-9)


@pytest.mark.parametrize("prefix, source", [("tukf", "kit_ukf"), ("tgn", "kit_gn"), ("tekf", "kit_ekf")])
def test_failed_init_leaves_a_live_estimator_as_it_was(libraries, linear, prefix, source):
    """init on a workspace that holds a running estimator, with arguments it refuses, returns
    the error, sets the handle to NULL and leaves the estimator stepping as before."""
    k = libraries(source, "gcc", "double")
    system, model, matrices, run, valid = linear
    Q, R = np.diag(np.square(system.noise.process_std)), np.diag(np.square(system.noise.measurement_std))
    P0, x0 = np.diag(np.square(system.noise.initial_std)), np.array(system.x0, dtype=float)
    memory, h = start(k, prefix, matrices, x0, P0, Q, R)
    twin_memory, twin = start(k, prefix, matrices, x0, P0, Q, R)
    for i in range(20):
        for handle in (h, twin):
            assert k(f"{prefix}_step", handle, k.a(run.u[max(i - 1, 0)]), k.a(run.y[i]), None) >= 0
    out = ctypes.c_void_p(1)
    for bad in ((np.full(2, np.nan), P0, Q, R), (x0, -P0, Q, R), (x0, P0, Q, R + [[0, 1], [0, 0]])):
        code = k(f"{prefix}_init", memory, ctypes.c_size_t(memory.nbytes), *(k.a(a) for a in bad),
                 ctypes.byref(out))
        assert code < 0 and out.value is None
    assert k(f"{prefix}_init", memory, ctypes.c_size_t(3), *(k.a(a) for a in (x0, P0, Q, R)),
             ctypes.byref(out)) == CODES["NO_MEMORY"]
    x_h, x_t = k.a(np.zeros(2)), k.a(np.zeros(2))
    for i in range(20, 40):
        for handle in (h, twin):
            assert k(f"{prefix}_step", handle, k.a(run.u[i - 1]), k.a(run.y[i]), None) >= 0
        k(f"{prefix}_get_state", h, x_h)
        k(f"{prefix}_get_state", twin, x_t)
        np.testing.assert_array_equal(x_h, x_t)


def two_oscillators(outputs=(0, 1, 3)) -> System:
    """Two mass-spring-dampers driven by one force, states ``[q1, q2, v1, v2]``, the states
    ``outputs`` measured: no Jacobian entry couples ``(q1, v1)`` with ``(q2, v2)``
    (``kit_gn_groups.c``'s two groups)."""
    states = (Signal("q1", "m"), Signal("q2", "m"), Signal("v1", "m/s"), Signal("v2", "m/s"))
    std = (0.05, 0.05, 0.1, 0.1)

    def dynamics(ops, x, u, p):
        return [x[2], x[3], (-p["k1"] * x[0] - p["c1"] * x[2] + u[0]) / p["m1"],
                (-p["k2"] * x[1] - p["c2"] * x[3] - u[0]) / p["m2"]]

    params = {"m1": 2.0, "k1": 3.0, "c1": 0.4, "m2": 0.5, "k2": 5.0, "c2": 0.2}
    return System(
        name="msd2x2", states=states, inputs=(Signal("F", "N"),),
        outputs=tuple(states[i] for i in outputs), params=params, true_params=params,
        dynamics=dynamics, measurement=lambda ops, x, u, p: [x[i] for i in outputs],
        noise=NoiseModel(measurement_std=tuple(std[i] for i in outputs), state_std=(0.01,) * 4,
                         process_std=(1e-3, 1e-3, 1e-2, 1e-2), initial_std=(0.5,) * 4),
        dt=0.05, duration=10.0, x0=(1.0, -0.5, 0.0, 0.0),
        excitation=lambda t, rng: np.sin(t + rng.uniform())[:, None])


@pytest.mark.parametrize("cc", COMPILERS)
@pytest.mark.parametrize("outputs", [(0, 1, 3), (0, 1)])
def test_grouped_embedded_mhe_solves_group_by_group_and_equals_the_ipopt_mhe(libraries, cc, outputs):
    """learnest_gn_groups.h without generated code: the kit's Gauss-Newton MHE over two
    oscillators apart, with diagonal and then within-group dense weights, solves the two
    groups' normal equations one by one (kt_split) and equals the Python MHE (CasADi's nlpsol
    with Ipopt) of the same model, outputs missing at random, to 1e-7 as the ungrouped one
    does; a process covariance that couples the groups makes it solve the whole window at
    once, to the same estimates. Outputs ``(0, 1)``: groups of one size, declared as such
    (LEARNEST_COMP_SIZE)."""
    from learnest_codegen.simulation import simulate

    k = libraries("kit_gn_groups", cc, "double", {"KIT_UNIFORM_GROUPS": 1} if len(outputs) == 2 else {})
    system = two_oscillators(outputs)
    model = prior_model(system)
    Phi = np.stack([model.step(e, np.zeros(1)) for e in np.eye(4)], axis=1)
    Gamma = model.step(np.zeros(4), np.ones(1))[:, None]
    C = np.eye(4)[list(outputs)]
    run = simulate(system, seed=0, duration=6.0)
    valid = np.random.default_rng(5).random(run.y.shape) < 0.7
    Y = np.where(valid, run.y, np.nan)
    x0 = np.array(system.x0, dtype=float)
    base = MHESettings.from_system(system, horizon=6, arrival="arrival_std")
    Q, R, P = mhe_settings(model, base).covariances()
    Qd, Rd, Qc = Q.copy(), R.copy(), Q.copy()
    Qd[0, 2] = Qd[2, 0] = 0.3 * np.sqrt(Q[0, 0] * Q[2, 2])  # within group 0
    if len(outputs) == 3:
        Rd[1, 2] = Rd[2, 1] = 0.3 * np.sqrt(R[1, 1] * R[2, 2])  # within group 1
    Qc[2, 3] = Qc[3, 2] = 0.3 * np.sqrt(Q[2, 2] * Q[3, 3])  # across the groups
    for (Qs, Rs, Ps), split in (((Q, R, P), 1), ((Qd, Rd, P), 1), ((Qc, R, P), 0)):
        settings = mhe_settings(model, replace(base, arrival_covariance=tuple(map(tuple, Ps))))
        memory, h = start(k, "tgg", (Phi, Gamma, C), x0, Ps, Qs, Rs)
        assert k("tgg_set_arrival", h, k.a(Ps)) == 0
        gate = settings.gate
        assert k("tgg_set_gate", h, gate.threshold, gate.recover_after, gate.inflation) == 0
        X_c = k.a(np.zeros((len(Y), 4)))
        assert k("tgg_run", h, len(Y), k.a(run.u), k.a(Y), valid.astype(np.uint8), X_c) == 0
        assert k("kt_split", h) == split
        mhe = MHE(model, settings)
        mhe.reset(x0, Ps)  # as init: the first prior's covariance, the running one
        mhe.set_noise(Q=Qs, R=Rs)
        X_py = np.array([mhe.step(run.u[max(i - 1, 0)], Y[i], valid[i]) for i in range(len(Y))])
        np.testing.assert_allclose(X_c, X_py, rtol=0, atol=1e-7)
        assert np.abs(X_c - run.x).mean() < 0.15  # it tracks states of amplitude ~1 (v1 unmeasured)


# -- the CasADi hooks and the Ipopt glue over a hand-written model ---------------------------

@pytest.mark.parametrize("cc", COMPILERS)
def test_casadi_hooks_run_the_embedded_mhe_as_the_direct_model_does(libraries, linear, cc):
    """learnest_casadi.h's stage, node and F hooks (kit_casadi_gn.c: the linear model written
    in CasADi's calling convention) under the kit's Gauss-Newton MHE: the same estimates as the
    Python MHE (CasADi's nlpsol with Ipopt) to 1e-7 as kit_gn.c's, and bit for bit kit_gn.c's
    (the same operations, reached through the hooks instead of direct calls)."""
    k, direct = libraries("kit_casadi_gn", cc, "double"), libraries("kit_gn", cc, "double")
    system, model, matrices, run, valid = linear
    settings = mhe_settings(model, MHESettings.from_system(system, horizon=6))
    Q, R, P0 = settings.covariances()
    x0 = np.array(system.x0, dtype=float)
    T = 120
    Y = np.where(valid[:T], run.y[:T], np.nan)
    out = {}
    for name, lib, prefix in (("casadi", k, "tcg"), ("direct", direct, "tgn")):
        memory, h = start(lib, prefix, matrices, x0, P0, Q, R)
        assert lib(f"{prefix}_set_arrival", h, lib.a(P0)) == 0
        X = lib.a(np.zeros((T, 2)))
        assert lib(f"{prefix}_run", h, T, lib.a(run.u[:T]), lib.a(Y), valid[:T].astype(np.uint8), X) == 0
        out[name] = X
    X_py = MHE(model, settings).run(run.u[:T], Y, x0, valid=valid[:T])
    np.testing.assert_allclose(out["casadi"], X_py, rtol=0, atol=1e-7)
    np.testing.assert_array_equal(out["casadi"], out["direct"])


@pytest.mark.parametrize("cc", COMPILERS)
@pytest.mark.parametrize("real", list(DTYPES))
def test_kit_sigma_points_equal_filterpys_ukf(libraries, linear, cc, real):
    """learnest_ukf.h's own sigma points, transforms and masked update (LEARNEST_UKF_ALPHA, as a
    generated UKF builds it) over learnest_casadi.h's F and h hooks (kit_casadi_ukf.c) against
    FilterPy's UnscentedKalmanFilter with the same Merwe points (alpha 0.5, beta 2, kappa 1),
    updating on the outputs present only (none: the prediction), sample by sample, in double and
    float. Each step's rounding is ``unscented_rounding`` with its update's gain
    (tests/test_ukf.py's ``update_gain``); a stable filter carries the earlier steps' errors
    forward without growth, so step ``k`` may differ by the sum of the bounds so far."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    k = libraries("kit_casadi_ukf", cc, real)
    system, model, matrices, run, valid = linear
    Phi, Gamma, C = matrices
    Q, R = np.diag(np.square(system.noise.process_std)), np.diag(np.square(system.noise.measurement_std))
    P0, x0 = np.diag(np.square(system.noise.initial_std)), np.array(system.x0, dtype=float)
    memory, h = start(k, "tcu", matrices, x0, P0, Q, R)
    points = MerweScaledSigmaPoints(2, 0.5, 2.0, 1.0)
    ukf = UnscentedKalmanFilter(2, 2, system.dt, hx=lambda s, **_: C @ s,
                                fx=lambda s, dt, u: Phi @ s + Gamma @ u, points=points)
    ukf.x, ukf.P, ukf.Q = x0.copy(), P0.copy(), Q
    x, P = k.a(np.zeros(2)), k.a(np.zeros((2, 2)))
    bound_x = bound_P = 0.0
    for i in range(len(run.y)):
        u = run.u[max(i - 1, 0)]
        if i > 0:
            ukf.predict(u=u)
        else:  # no transition on the first sample: the points of (x0, P0) itself
            ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
            ukf.x_prior, ukf.P_prior = ukf.x.copy(), ukf.P.copy()
        keep = valid[i]
        gain_x = gain_P = 1.0
        if keep.any():
            ukf.update(run.y[i][keep], R=R[np.ix_(keep, keep)], hx=lambda s, keep=keep: (C @ s)[keep])
            gain_x, gain_P = update_gain(ukf, ukf.sigmas_h, ukf.P_prior)
        else:
            ukf.x, ukf.P = ukf.x_prior.copy(), ukf.P_prior.copy()
        assert k("tcu_step", h, k.a(u), k.a(np.where(keep, run.y[i], np.nan)), keep.astype(np.uint8)) == 0
        k("tcu_get_state", h, x)
        k("tcu_get_covariance", h, P)
        bound_x += unscented_rounding(points.Wm, points.Wc, k.dtype, gain=gain_x)
        bound_P += unscented_rounding(points.Wm, points.Wc, k.dtype, gain=gain_P)
        np.testing.assert_allclose(x, ukf.x, rtol=0, atol=bound_x * np.abs(ukf.x).max(), err_msg=f"{i}")
        np.testing.assert_allclose(P, ukf.P, rtol=0, atol=bound_P * np.abs(ukf.P).max(), err_msg=f"{i}")
    assert k("tcu_samples", h) == len(run.y)


def test_ipopt_glue_solves_the_nlp_as_casadis_ipopt(libraries, linear):
    """learnest_casadi.h's solver glue and learnest_mhe_ipopt.h over a hand-written nlpsol
    (kit_ipopt.c: eq. (2) of the linear model given to Ipopt's C interface, the casadi wheel's
    libipopt) against the Python MHE, whose nlpsol CasADi builds over the same Ipopt, with
    outputs missing at random; its parameter vector is ParamLayout's; a refused solver memory
    and Ipopt's iteration limit come back as NO_MEMORY and MAX_ITERATIONS, restart the window,
    and the memory is given back."""
    from learnest_codegen.estimators.mhe_problem import ParamLayout

    k = libraries("kit_ipopt", "gcc", "double")
    system, model, matrices, run, valid = linear
    layout = np.zeros(9, dtype=np.intc)
    k("kt_layout", layout, restype=None)
    expected = ParamLayout(2, 1, 2, 6)
    assert layout.tolist() == [expected.size, *expected.offsets().values()]
    settings = mhe_settings(model, MHESettings.from_system(system, horizon=6))
    Q, R, P0 = settings.covariances()
    x0 = np.array(system.x0, dtype=float)
    T = 120
    Y = np.where(valid[:T], run.y[:T], np.nan)
    memory, h = start(k, "tip", matrices, x0, P0, Q, R)
    assert k("tip_set_arrival", h, k.a(P0)) == 0
    X_c = k.a(np.zeros((T, 2)))
    solves = k("kt_solves")
    assert k("tip_run", h, T, k.a(run.u[:T]), k.a(Y), valid[:T].astype(np.uint8), X_c) == 0
    assert k("kt_solves") - solves == T and k("kt_checked_out") == 0
    X_py = MHE(model, settings).run(run.u[:T], Y, x0, valid=valid[:T])
    np.testing.assert_allclose(X_c, X_py, rtol=0, atol=ipopt_resolution(model, settings, matrices[0]))
    for max_iter, refuse, code in ((0, 0, "MAX_ITERATIONS"), (100, 1, "NO_MEMORY")):
        k("kt_solver_set", max_iter, refuse, restype=None)
        assert k("tip_step", h, k.a(run.u[T]), k.a(run.y[T + 1]), None) == CODES[code]
        assert k("kt_checked_out") == 0
    k("kt_solver_set", 100, 0, restype=None)
    assert k("tip_step", h, k.a(run.u[T]), k.a(run.y[T + 1]), None) == 0


def ipopt_resolution(model, settings, Phi) -> float:
    """How far two Ipopt solutions of one window's unconstrained, strongly convex quadratic NLP
    may lie apart: each stops with a scaled gradient of at most ``tol`` (IPOPT_OPTIONS), so
    lies within ``sqrt(NW) tol / lambda_min(H)`` of the minimiser, ``H`` the scaled cost's
    Hessian. Its smallest eigenvalue is that of the window with every output missing (the
    measurement terms only add positive semidefinite blocks): the arrival and process terms."""
    from learnest_codegen.estimators.mhe_problem import IPOPT_OPTIONS

    Qw, Rw, Pw = settings.weights()
    scale = 1 / max(np.diag(Qw).max(), np.diag(Rw).max(), np.diag(Pw).max())
    n, nx = settings.horizon, model.nx
    H = np.zeros(((n + 1) * nx, (n + 1) * nx))
    H[:nx, :nx] += Pw
    for i in range(n):
        J = np.zeros((nx, (n + 1) * nx))
        J[:, i * nx:(i + 1) * nx], J[:, (i + 1) * nx:(i + 2) * nx] = -Phi, np.eye(nx)
        H += J.T @ Qw @ J
    return 2 * np.sqrt(len(H)) * IPOPT_OPTIONS["tol"] / np.linalg.eigvalsh(2 * scale * H).min()


#: The MHE options a generated glue may set, each as MHESettings overrides.
OPTIONS = {"state_bounds": {"state_bounds": ((-0.5, 0.95), (-np.inf, np.inf))},
           "arrival_update": {"arrival_update": True},
           "input_limits": {"input_limits": ((-0.8, 0.8),)}}


@pytest.mark.parametrize("option", list(OPTIONS))
@pytest.mark.parametrize("prefix, source", [("tgn", "kit_gn"), ("tip", "kit_ipopt")])
def test_mhe_options_from_the_kit_alone_equal_the_python_mhe(libraries, linear, option, prefix, source):
    """What a generated glue switches on, from the kit alone: state bounds (learnest_bounds.h:
    the projected Gauss-Newton steps, Ipopt's variable bounds), the arrival cost that follows
    the data (LEARNEST_ARRIVAL_UPDATE) and the input limits (learnest_api.h), with the macros
    the generators write (codegen/mhe.py's bounds_defines, arrival_defines), in the
    Gauss-Newton and the Ipopt MHE against the Python MHE with the same settings. A bounded
    window never leaves its box and touches it; a rejected input sets the status bit 2."""
    system, model, matrices, run, valid = linear
    settings = mhe_settings(model, MHESettings.from_system(system, horizon=6, **OPTIONS[option]))
    defines = {**bounds_defines(settings), **arrival_defines(settings)}
    if option == "input_limits":
        defines.update({"LEARNEST_INPUT_LO": "{-0.8}", "LEARNEST_INPUT_HI": "{0.8}"})
    k = libraries(source, "gcc", "double", defines)
    Q, R, P0 = settings.covariances()
    x0 = np.array(system.x0, dtype=float)
    T = 120
    Y = np.where(valid[:T], run.y[:T], np.nan)
    memory, h = start(k, prefix, matrices, x0, P0, Q, R)
    assert k(f"{prefix}_set_arrival", h, k.a(P0)) == 0
    X_c = k.a(np.zeros((T, 2)))
    code = k(f"{prefix}_run", h, T, k.a(run.u[:T]), k.a(Y), valid[:T].astype(np.uint8), X_c)
    assert code >= 0 and bool(code & 2) == (option == "input_limits")
    X_py = MHE(model, settings).run(run.u[:T], Y, x0, valid=valid[:T])
    # both solve one window's problem: the unbounded one to Ipopt's resolution (the Gauss-Newton
    # MHE to 1e-7 of Ipopt's, as unbounded above); the bounded one to 1e-7 as well (Ipopt with
    # BOUNDED_IPOPT_OPTIONS meets the projected Gauss-Newton's KKT point within 1.4e-8 on the
    # cartpole: estimators/mhe_problem.py)
    bounded = option == "state_bounds"
    atol = ipopt_resolution(model, settings, matrices[0]) if source == "kit_ipopt" and not bounded else 1e-7
    np.testing.assert_allclose(X_c, X_py, rtol=0, atol=atol)
    if bounded:  # inside the box (clamped: exactly), and on its upper side at times
        assert np.all((X_c[:, 0] >= -0.5) & (X_c[:, 0] <= 0.95)) and np.any(X_c[:, 0] >= 0.95 - 1e-7)
        assert np.any(MHE(model, replace(settings, state_bounds=None)).run(
            run.u[:T], Y, x0, valid=valid[:T])[:, 0] > 0.95 + 1e-3)  # which unbounded it leaves


def test_the_apis_other_doors_from_the_kit_alone(libraries, linear):
    """The API's doors besides init and step, on the kit's EKF over the linear model (where it
    is FilterPy's Kalman filter, to 1e-12 as above): the build's sizes, real size, dt and
    fingerprint; init_default (the build's defaults, which are the linear system's tuning);
    predict (a step without outputs); set_noise (Q and R from the next step on); reset. On
    the Gauss-Newton MHE: set_options (one iteration per sample, RTI, which on a linear model
    is the converged solution: the Python MHE's to 1e-7 as above; out-of-range options
    refused), iterations, get_arrival and get_arrival_weight (its inverse, to rounding)."""
    from filterpy.kalman import KalmanFilter

    k = libraries("kit_ekf", "gcc", "double")
    system, model, matrices, run, valid = linear
    sizes = [ctypes.c_int() for _ in range(4)]
    k("tekf_sizes", *(ctypes.byref(s) for s in sizes), restype=None)
    assert [s.value for s in sizes] == [2, 1, 2, 0]
    assert k("tekf_real_size") == 8 and k("tekf_dt", restype=ctypes.c_double) == system.dt
    assert k("tekf_fingerprint", restype=ctypes.c_char_p).startswith(b"learnest kit test")
    memory = np.zeros(k("tekf_workspace_size", restype=ctypes.c_size_t), dtype=np.uint8)
    h = ctypes.c_void_p()
    assert k("tekf_init_default", memory, ctypes.c_size_t(memory.nbytes), ctypes.byref(h)) == 0
    Phi, Gamma, C = matrices
    assert k("kt_set_model", h, k.a(Phi.T), k.a(Gamma.T), k.a(C.T)) == 0
    Q, R = np.diag(np.square(system.noise.process_std)), np.diag(np.square(system.noise.measurement_std))
    kf = KalmanFilter(dim_x=2, dim_z=2)
    kf.F, kf.B, kf.H, kf.Q, kf.R = Phi, Gamma, C, Q, R
    kf.x, kf.P = np.array([1.0, 0.0]), np.diag([0.25, 0.25])  # kit_linear.h's defaults
    x, P = k.a(np.zeros(2)), k.a(np.zeros((2, 2)))

    def same():
        k("tekf_get_state", h, x)
        k("tekf_get_covariance", h, P)
        np.testing.assert_allclose(x, kf.x, rtol=0, atol=1e-12 * np.abs(kf.x).max())
        np.testing.assert_allclose(P, kf.P, rtol=0, atol=1e-12 * np.abs(kf.P).max())

    same()
    for i in range(60):
        u, y = run.u[max(i - 1, 0)], run.y[i]
        if i == 20:
            Q, R = 4 * Q, 0.25 * R
            assert k("tekf_set_noise", h, k.a(Q), k.a(R)) == 0
            kf.Q, kf.R = Q, R
        if i == 40:
            x0, P0 = np.array([0.5, -0.2]), np.diag([0.1, 0.3])
            assert k("tekf_reset", h, k.a(x0), k.a(P0), k.a(Q), k.a(R)) == 0
            kf.x, kf.P = x0.copy(), P0.copy()
        if i % 3 == 2:  # no outputs: the prediction
            assert k("tekf_predict", h, k.a(u)) == 0
        else:
            assert k("tekf_step", h, k.a(u), k.a(y), None) == 0
        if i not in (0, 40):  # the first sample after init or reset has no transition
            kf.predict(u=u)
        if i % 3 != 2:
            kf.update(y)
        same()

    k = libraries("kit_gn", "gcc", "double")
    settings = mhe_settings(model, MHESettings.from_system(system, horizon=6))
    Q, R, P0 = settings.covariances()
    x0 = np.array(system.x0, dtype=float)
    memory, h = start(k, "tgn", matrices, x0, P0, Q, R)
    assert k("tgn_set_arrival", h, k.a(P0)) == 0
    got, weight = k.a(np.zeros((2, 2))), k.a(np.zeros((2, 2)))
    assert k("tgn_get_arrival", h, got) == 0 and k("tgn_get_arrival_weight", h, weight) == 0
    np.testing.assert_array_equal(got, P0)  # copied
    inverse = np.linalg.inv(P0)  # the kit's Cholesky inverse against LU: nx^3 operations
    tol = rounding(ops=2**3, cond=np.linalg.cond(P0)) * np.abs(inverse).max()
    np.testing.assert_allclose(weight, inverse, rtol=0, atol=tol)
    for bad in ((2, 10, 1e-10), (1, 0, 1e-10), (1, 10, 0.0)):
        assert k("tgn_set_options", h, bad[0], bad[1], bad[2]) == CODES["BAD_ARGUMENT"]
    assert k("tgn_set_options", h, 1, 10, 1e-10) == 0  # RTI
    T = 120
    Y = np.where(valid[:T], run.y[:T], np.nan)
    X_c = k.a(np.zeros((T, 2)))
    for i in range(T):
        assert k("tgn_step", h, k.a(run.u[max(i - 1, 0)]), k.a(Y[i]), valid[i].astype(np.uint8)) == 0
        assert k("tgn_iterations", h) == 1
        k("tgn_get_state", h, X_c[i])
    X_py = MHE(model, settings).run(run.u[:T], Y, x0, valid=valid[:T])
    np.testing.assert_allclose(X_c, X_py, rtol=0, atol=1e-7)


# -- the lane-parallel paths over a hand-written nonlinear model ------------------------------

VECTORS = shutil.which("gcc") is not None and platform.machine() == "x86_64"
LANES = {"double": 4, "float": 8}  # learnest_simd.h's lanes a 32-byte vector
needs_vectors = pytest.mark.skipif(not VECTORS, reason="learnest_simd.h's vectors are GCC on x86-64")
G, B, C_DRAG, D_DRAG = 4.0, 1.0, 0.5, 0.1  # kit_lanes.h's constants
#: The dependent operations of kit_lanes.h's F1 and A11 (eleven + - * and the kit's sin, cos
#: and tanh, each within 3 ulp: three operations each).
MODEL_OPS = 20


def lanes_model(x: np.ndarray, u: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """kit_lanes.h's model in closed form (numpy, float64): F and A = dF/dx of the points x
    (n, 2) with inputs u (n, 1)."""
    x0, x1, u0 = x[:, 0], x[:, 1], u[:, 0]
    F = np.stack([x0 + dt * x1, x1 + dt * (B * u0 * np.cos(x0) - G * np.sin(x0)
                                           - C_DRAG * np.tanh(x1) - D_DRAG * x1 * np.abs(x1))], axis=1)
    A = np.zeros((len(x), 2, 2))
    A[:, 0, 0], A[:, 0, 1] = 1.0, dt
    A[:, 1, 0] = dt * (-G * np.cos(x0) - B * u0 * np.sin(x0))
    A[:, 1, 1] = 1.0 + dt * (-C_DRAG * (1 - np.tanh(x1) ** 2) - 2 * D_DRAG * np.abs(x1))
    return F, A


def lanes_scale(x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """The largest term's size in each point's F1 and A11 (what their rounding is relative to)."""
    x0, x1, u0 = np.abs(x[:, 0]), np.abs(x[:, 1]), np.abs(u[:, 0])
    return np.maximum(x0 + x1, 1.0 + dt * (B * u0 + G + C_DRAG + 2 * D_DRAG * x1 + D_DRAG * x1**2))


def lanes_casadi_model(system: System) -> DiscreteModel:
    """kit_lanes.h's model as CasADi functions, for the Python MHE (CasADi's nlpsol with Ipopt)."""
    x, u, dt = cs.SX.sym("x", 2), cs.SX.sym("u", 1), system.dt
    F = cs.vertcat(x[0] + dt * x[1], x[1] + dt * (B * u[0] * cs.cos(x[0]) - G * cs.sin(x[0])
                                                 - C_DRAG * cs.tanh(x[1]) - D_DRAG * x[1] * cs.fabs(x[1])))
    return DiscreteModel(system, "nominal", cs.Function("F", [x, u], [F], ["x", "u"], ["x_next"]),
                         cs.Function("f", [x, u], [(F - x) / dt], ["x", "u"], ["xdot"]),
                         system.casadi_h(), dt)


@pytest.fixture(scope="module")
def pendulum():
    """The nonlinear model's system (the linear system's names, sizes and noise), its CasADi
    model and a simulated run (F with process noise, outputs with noise, missing at random and
    for ten samples in a row)."""
    system = linear_system()
    rng = np.random.default_rng(11)
    T = 160
    u = (2.0 * np.sin(0.7 * system.dt * np.arange(T)))[:, None]
    x = np.empty((T, 2))
    x[0] = (1.0, 0.0)
    for i in range(1, T):
        x[i] = lanes_model(x[i - 1][None], u[i - 1][None], system.dt)[0][0] + rng.normal(
            scale=system.noise.process_std)
    y = x + rng.normal(scale=system.noise.measurement_std, size=x.shape)
    valid = rng.random(y.shape) < 0.7
    valid[60:70] = False
    return system, lanes_casadi_model(system), u, y, valid


@needs_vectors
@pytest.mark.parametrize("real", list(DTYPES))
def test_lane_parallel_hooks_equal_the_scalar_hooks_and_the_closed_forms(libraries, real):
    """learnest_casadi.h's batch hooks (F, and the stage F with A) with learnest_casadi.h's lane
    gather and scatter over kit_lanes.h's batch copies (learnest_simd.h's sin, cos, tanh, fabs
    and square) on 11 points (batches with spare lanes): bit for bit the scalar hooks, and the
    closed forms to the model's rounding. Points include both tanh branches, its saturation,
    and angles beyond the vector sin/cos reduction range (its per-lane scalar fallback)."""
    k = libraries("kit_lanes_gn", "gcc", real)
    rng = np.random.default_rng(5)
    dt = 0.05
    for big in (30.0, 1e6):
        X = k.a(np.column_stack([rng.uniform(-big, big, 11), rng.uniform(-12, 12, 11)]))
        X[:4, 1] = (0.0, 0.1, -0.3, 40.0)
        U = k.a(rng.uniform(-3, 3, (11, 1)))
        for stage in (False, True):
            out = {}
            for lanes in (1, 2):
                F, A = k.a(np.zeros((11, 2))), k.a(np.zeros((11, 2, 2)))
                used = k("kl_model_points", lanes, 11, X, U, F, A if stage else None)
                assert used == (1 if lanes == 1 else LANES[real])
                out[lanes] = F, A
            np.testing.assert_array_equal(out[2][0], out[1][0])
            np.testing.assert_array_equal(out[2][1], out[1][1])
        F_ref, A_ref = lanes_model(X.astype(float), U.astype(float), dt)
        tol = rounding(k.dtype, ops=MODEL_OPS) * lanes_scale(X.astype(float), U.astype(float), dt)
        F, A = out[1]
        assert np.all(np.abs(F - F_ref) <= tol[:, None])
        assert np.all(np.abs(A.transpose(0, 2, 1) - A_ref) <= tol[:, None, None])  # A column-major


@needs_vectors
@pytest.mark.parametrize("real", list(DTYPES))
def test_lane_parallel_ukf_equals_the_scalar_ukf_and_filterpys_ukf(libraries, pendulum, real):
    """learnest_ukf.h's batched sigma-point propagation (F on 4 or 8 points a call, kit_lanes_ukf.c)
    against the same source built with -DLEARNEST_NO_SIMD (one call a point): the same state
    and covariance bit for bit at every sample; and against FilterPy's UnscentedKalmanFilter
    (Merwe points, alpha 0.5, beta 2, kappa 1) on the nonlinear model in closed form, with the
    bound of test_kit_sigma_points_equal_filterpys_ukf plus the model's rounding."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    system, _, U, Y, valid = pendulum
    vector = libraries("kit_lanes_ukf", "gcc", real)
    scalar = libraries("kit_lanes_ukf", "gcc", real, {"LEARNEST_NO_SIMD": 1})
    none = (None,) * 4
    assert vector("kl_model_points", 2, 0, *none) == LANES[real]
    assert scalar("kl_model_points", 2, 0, *none) == 0  # no vectors: the scalar loop
    Q, R = np.diag(np.square(system.noise.process_std)), np.diag(np.square(system.noise.measurement_std))
    P0, x0 = np.diag(np.square(system.noise.initial_std)), np.array(system.x0, dtype=float)
    handles = [start(lib, "tlu", None, x0, P0, Q, R) for lib in (vector, scalar)]
    points = MerweScaledSigmaPoints(2, 0.5, 2.0, 1.0)
    ukf = UnscentedKalmanFilter(2, 2, system.dt, hx=lambda s, **_: s, points=points,
                                fx=lambda s, dt, u: lanes_model(s[None], u[None], dt)[0][0])
    ukf.x, ukf.P, ukf.Q = x0.copy(), P0.copy(), Q
    bound_x = bound_P = 0.0
    for i in range(len(Y)):
        u = U[max(i - 1, 0)]
        if i > 0:
            ukf.predict(u=u)
        else:
            ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
            ukf.x_prior, ukf.P_prior = ukf.x.copy(), ukf.P.copy()
        keep = valid[i]
        gain_x = gain_P = 1.0
        if keep.any():
            ukf.update(Y[i][keep], R=R[np.ix_(keep, keep)], hx=lambda s, keep=keep: s[keep])
            gain_x, gain_P = update_gain(ukf, ukf.sigmas_h, ukf.P_prior)
        else:
            ukf.x, ukf.P = ukf.x_prior.copy(), ukf.P_prior.copy()
        states = []
        for lib, (_, h) in zip((vector, scalar), handles):
            y = lib.a(np.where(keep, Y[i], np.nan))
            assert lib("tlu_step", h, lib.a(u), y, keep.astype(np.uint8)) == 0
            x, P = lib.a(np.zeros(2)), lib.a(np.zeros((2, 2)))
            lib("tlu_get_state", h, x)
            lib("tlu_get_covariance", h, P)
            states.append((x, P))
        np.testing.assert_array_equal(states[0][0], states[1][0], err_msg=f"{i}")
        np.testing.assert_array_equal(states[0][1], states[1][1], err_msg=f"{i}")
        x, P = states[0]
        cond = max(np.abs(points.Wm).sum(), np.abs(points.Wc).sum())
        bound_x += rounding(vector.dtype, ops=3 * 2 + 2 + MODEL_OPS, cond=cond * gain_x)
        bound_P += rounding(vector.dtype, ops=3 * 2 + 2 + MODEL_OPS, cond=cond * gain_P)
        np.testing.assert_allclose(x, ukf.x, rtol=0, atol=bound_x * np.abs(ukf.x).max(), err_msg=f"{i}")
        np.testing.assert_allclose(P, ukf.P, rtol=0, atol=bound_P * np.abs(ukf.P).max(), err_msg=f"{i}")


@needs_vectors
@pytest.mark.parametrize("real", list(DTYPES))
def test_lane_parallel_mhe_equals_the_scalar_mhe_and_the_ipopt_mhe(libraries, pendulum, real):
    """learnest_gn.h's batched linearisation of the window's stages (4 or 8 stages a call of
    learnest_casadi.h's stage batch hook, horizon 6: spare lanes) in the embedded MHE over the
    nonlinear model (kit_lanes_gn.c), against the same source built with -DLEARNEST_NO_SIMD
    (one call a stage): the same estimates bit for bit; in double, also the Python MHE
    (CasADi's nlpsol with Ipopt on the model's CasADi form) to 1e-7, as the linear model's."""
    system, model, U, Y, valid = pendulum
    vector = libraries("kit_lanes_gn", "gcc", real)
    scalar = libraries("kit_lanes_gn", "gcc", real, {"LEARNEST_NO_SIMD": 1})
    assert scalar("kl_model_points", 2, 0, *(None,) * 4) == 0
    settings = mhe_settings(model, MHESettings.from_system(system, horizon=6))
    Q, R, P0 = settings.covariances()
    x0 = np.array(system.x0, dtype=float)
    T = 120
    Ym = np.where(valid[:T], Y[:T], np.nan)
    out = []
    for lib in (vector, scalar):
        memory, h = start(lib, "tlg", None, x0, P0, Q, R)
        assert lib("tlg_set_arrival", h, lib.a(P0)) == 0
        if real == "float":  # the float MHEs' default tolerance (estimators/mhe_gn.py)
            assert lib("tlg_set_options", h, 0, 30, DEFAULT_TOLERANCE["float32"]) == 0
        X = lib.a(np.zeros((T, 2)))
        assert lib("tlg_run", h, T, lib.a(U[:T]), lib.a(Ym), valid[:T].astype(np.uint8), X) == 0
        out.append(X)
    np.testing.assert_array_equal(out[0], out[1])
    assert np.all(np.isfinite(out[0]))
    if real == "double":
        X_py = MHE(model, settings).run(U[:T], Ym, x0, valid=valid[:T])
        np.testing.assert_allclose(out[0], X_py, rtol=0, atol=1e-7)


def test_gate_accessors_and_the_reseed_equal_the_python_filter(libraries, linear):
    """The gate's and the input check's accessors (get_rejected, rejections, get_input_rejected,
    input_rejections) and the Kalman filters' re-seed of a lost estimate (learnest_kalman.h),
    on the kit's EKF over the linear model with input limits, against the Python EKF
    (estimators/ekf.py: FilterPy's filter in the step every reference Kalman filter shares):
    a two-sample outlier on one output (rejected), then a lasting offset of 3 on the other
    (rejected until the estimate is lost, then re-seeded). Per sample: the status bits,
    the rejected outputs and inputs and their counts exactly; the estimate to 1e-10 of its size
    (the two filters' rounding, amplified by the re-seed's wide prior)."""
    system, model, matrices, run, valid = linear
    settings = EKFSettings.from_system(system, input_limits=((-0.8, 0.8),))
    k = libraries("kit_ekf", "gcc", "double", {"LEARNEST_INPUT_LO": "{-0.8}", "LEARNEST_INPUT_HI": "{0.8}"})
    x0 = np.array(system.x0, dtype=float)
    memory, h = start(k, "tekf", matrices, x0, settings.P0(), settings.Q(), settings.R())
    gate = settings.gate
    assert k("tekf_set_gate", h, float(gate.threshold), gate.recover_after, float(gate.inflation)) == 0
    ekf = EKF(model, settings)
    ekf.reset(x0)
    Y = run.y[:160].copy()
    Y[20:22, 1] += 5.0
    Y[50:, 0] += 3.0
    statuses = []
    for i in range(len(Y)):
        u = run.u[max(i - 1, 0)]
        code = k("tekf_step", h, k.a(u), k.a(Y[i]), None)
        ekf.step(u, Y[i])
        assert code == ekf.last_status, i
        statuses.append(code)
        x, rejected, input_rejected = k.a(np.zeros(2)), np.zeros(2, np.intc), np.zeros(1, np.intc)
        k("tekf_get_state", h, x)
        assert k("tekf_get_rejected", h, rejected) == 0
        assert k("tekf_get_input_rejected", h, input_rejected) == 0
        np.testing.assert_array_equal(rejected.astype(bool), ekf.rejected, err_msg=f"{i}")
        np.testing.assert_array_equal(input_rejected.astype(bool), ekf.input_rejected, err_msg=f"{i}")
        assert k("tekf_rejections", h) == ekf.rejections
        assert k("tekf_input_rejections", h) == ekf.input_rejections
        np.testing.assert_allclose(x, ekf.x, rtol=0, atol=1e-10 * np.abs(ekf.x).max(), err_msg=f"{i}")
    statuses = np.array(statuses)
    assert np.all(statuses[20:22] & 1) and np.any(statuses & 2)  # outliers rejected, inputs replaced
    lost = np.flatnonzero(statuses & 4)  # lost under the offset, re-seeded, then accepted
    assert len(lost) and lost[0] > 50 and not np.any(statuses[lost[0] + 1:lost[0] + 6] & 1)


def test_mhe_set_noise_from_the_kit_alone_equals_the_python_mhe(libraries, linear):
    """The MHEs' run-time tuning (learnest_mhe_api.h's set_noise: Q and R from the next step on,
    the window and gate kept) on the kit's Gauss-Newton MHE against the Python MHE's set_noise,
    to 1e-7 as the embedded MHE above."""
    system, model, matrices, run, valid = linear
    settings = mhe_settings(model, MHESettings.from_system(system, horizon=6))
    Q, R, P0 = settings.covariances()
    x0 = np.array(system.x0, dtype=float)
    k = libraries("kit_gn", "gcc", "double")
    memory, h = start(k, "tgn", matrices, x0, P0, Q, R)
    assert k("tgn_set_arrival", h, k.a(P0)) == 0
    mhe = MHE(model, settings)
    mhe.reset(x0)
    T = 120
    Y = np.where(valid[:T], run.y[:T], np.nan)
    x = k.a(np.zeros(2))
    for i in range(T):
        if i == 40:
            assert k("tgn_set_noise", h, k.a(9 * Q), k.a(0.25 * R)) == 0
            mhe.set_noise(Q=9 * Q, R=0.25 * R)
        assert k("tgn_step", h, k.a(run.u[max(i - 1, 0)]), k.a(Y[i]), valid[i].astype(np.uint8)) >= 0
        x_py = mhe.step(run.u[max(i - 1, 0)], Y[i], valid=valid[i])
        k("tgn_get_state", h, x)
        np.testing.assert_allclose(x, x_py, rtol=0, atol=1e-7, err_msg=f"{i}")
