"""A reproducible battery of hostile inputs to the command line and the Python API.

Every case runs in its own child process (a fresh interpreter; its own process group), so a
crash or a hang of one case is recorded, not suffered. A case is a short Python snippet; most
drive the ``learnest`` / ``learnest-compile`` commands in a further child, the others call the
API. Each ends in one outcome:

- ``clear error``: the command exited 1 (or 2, click's usage error) with one ``Error:`` line
  and no traceback; or the API raised a one-line error of the package (or the builtin
  ``ValueError`` / ``OSError`` / ``ArithmeticError`` family the command line treats as a user
  error). A case may name words the line must hold (``needles``) or must not (``avoid``);
  otherwise the outcome is ``unclear error``.
- ``correct result`` / ``wrong result``: the call succeeded and the case's own check (against
  an independent reference where there is one) passed or failed. A case that expects an error
  and gets none is a ``wrong result`` (accepted silently).
- ``traceback``, ``hang`` (the case's time limit passed; its process group is killed),
  ``crash`` (killed by a signal).

The battery covers options, names, shapes, files, CSVs, libraries, threads, float32 and wrong
inputs ``u``, and the streams surface: validity masks, ``set_noise``/``set_arrival``,
``predict``, ``--x0``/``--P0``, ``--horizon``, empty and mixed-rate CSVs, moved and oddly named
system files, long gaps, long predictions, lost tracks, one handle in two threads, inputs far
outside the range of a system without limits and training data without measurements; and
controls that must keep working. Each case names the part of the package whose checks own its
fix (``owner``): ``boundaries`` (system files, simulation, options, output files, builds, the
bindings), ``c-api`` (the generated C) and ``data`` (run-CSV reading, the estimators' checks of
their inputs). Fixtures (cartpole and ground-robot runs, compiled nominal estimators in both
precisions) are built once.

Outcomes are also counted as the reliability benchmark reports them (:func:`verdicts`):
*silent* (a wrong result accepted without an error), *crash*, *hang* and *confusing* (an error
that does not name the cause and the remedy, or a traceback).

Usage::

    python scripts/hostile_inputs.py --out hostile_inputs.json [--only files/] [--baseline before.json]

``--baseline`` adds the outcome of an earlier run beside each case (before/after tables).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUTCOMES = ("clear error", "correct result", "wrong result", "unclear error", "traceback", "hang",
            "crash", "skipped", "battery error")
ERROR, RESULT = frozenset({"clear error"}), frozenset({"correct result"})


@dataclass(frozen=True)
class Case:
    """One hostile input: its snippet, what it should end in, and who owns the fix."""

    id: str
    owner: str  # boundaries, data, c-api: the part of the package whose checks own the fix
    expect: frozenset
    what: str
    code: str
    timeout: float = 120.0
    needles: tuple[str, ...] = ()
    avoid: tuple[str, ...] = ()

    @property
    def group(self) -> str:
        return self.id.split("/")[0]


# ---- what every snippet can use ------------------------------------------------------------

PRELUDE = r'''
import json, os, shutil, signal, stat, subprocess, sys, time
from pathlib import Path
import numpy as np
W = Path(os.environ["HOSTILE_WORKDIR"]); CASE = Path(os.environ["HOSTILE_CASEDIR"])
TIMEOUT = float(os.environ["HOSTILE_TIMEOUT"])
LIB = W / "lib"
RUN = W / "run.csv"

def mark(kind, **data):
    print(f"HOSTILE_{kind} " + json.dumps(data), flush=True)
    sys.exit(0)

def verdict(ok, note=""):
    mark("RESULT", ok=bool(ok), note=str(note))

def _argv(args, compile=False):
    if compile:
        head = [sys.executable, "-c", "import sys; from learnest_codegen.cli import compile_main; "
                "sys.argv[0] = 'learnest-compile'; compile_main()"]
    else:
        head = [sys.executable, "-m", "learnest_codegen.cli"]
    return head + [str(a) for a in args]

def run(args, compile=False, timeout=None):
    """Run a command; returns (code, stdout, stderr); code None: timed out (killed)."""
    proc = subprocess.Popen(_argv(args, compile), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout or TIMEOUT)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        return None, out, err
    return proc.returncode, out, err

def classify(code, out, err):
    """Emit the outcome of a finished command that did not succeed."""
    if code is None:
        mark("HANG")
    if code < 0:
        mark("CRASH", signal=-code)
    if "Traceback" in err or "Traceback" in out:
        mark("TRACEBACK", tail=err.strip().splitlines()[-1:] or [""])
    lines = [l for l in (err + out).splitlines() if l.startswith("Error:")]
    if code in (1, 2) and len(lines) == 1:
        mark("ERROR", type="cli", message=lines[0][len("Error:"):].strip())
    mark("UNCLEAR", code=code, output=(err + out).strip()[-300:])

def step(args, compile=False, timeout=None):
    """A step of the case: when it fails, that is the case's outcome."""
    code, out, err = run(args, compile, timeout)
    if code != 0:
        classify(code, out, err)
    return out

def final(args, check=None, compile=False, timeout=None):
    """The case's last command: its failure is the outcome; on success check() judges it."""
    out = step(args, compile, timeout)
    if check is None:
        mark("ACCEPTED", output=out.strip()[-200:])
    ok, note = check(out)
    verdict(ok, note)

def must(args, compile=False):
    """A setup command that must succeed (else the battery itself is broken)."""
    code, out, err = run(args, compile)
    if code != 0:
        raise SystemExit(f"HOSTILE_SETUP_FAILED {args}: {err.strip()[-300:]}")
    return out

def compile_force(args):
    """learnest-compile ... --force, or without --force where the command has no such option."""
    code, out, err = run([*args, "--force"], compile=True)
    if code == 2 and "No such option" in err:
        code, out, err = run(args, compile=True)
    if code != 0:
        classify(code, out, err)
    return out

def table(path):
    return np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)

def copy_folder(name):
    dst = CASE / name
    shutil.copytree(LIB / name, dst)
    return dst

def edit_csv(src, dst, row=None, column=None, value=None, transform=None):
    lines = Path(src).read_text().splitlines()
    if transform is not None:
        lines = transform(lines)
    else:
        col = lines[0].split(",").index(column)
        cells = lines[row + 1].split(",")
        cells[col] = value
        lines[row + 1] = ",".join(cells)
    Path(dst).write_text("\n".join(lines) + "\n")
    return dst

PENDULUM = """
import math
import numpy as np
from learnest_codegen import NoiseModel, Signal, System
from learnest_codegen.systems import KinematicChain

def dynamics(ops, x, u, p):
    q, qdot = x
    return {dyn}

def measurement(ops, x, u, p):
    return {meas}

SYSTEM = System(
    name={name!r},
    states=(Signal({s1!r}, "rad"), Signal({s2!r}, "rad/s")),
    inputs=(Signal("tau", "N m"),),
    outputs=(Signal({o1!r}, "rad"),),
    params={{"k": 9.0, "c": 0.0}},
    true_params={{"k": 9.0, "c": 0.3}},
    dynamics=dynamics,
    measurement=measurement,
    noise=NoiseModel(measurement_std=(0.01,), state_std=(0.01, 0.01),
                     process_std=(1e-3, 1e-2), initial_std=(0.1, 0.1)),
    dt=0.01, duration={duration}, x0={x0},
    excitation=lambda t, rng: np.sin(2 * t)[:, None],
    kinematic_chains={chains},
)
"""
GOOD_DYN = '[qdot, -p["k"] * ops.sin(q) - p["c"] * qdot + u[0]]'

def system_file(fname="my.py", dyn=GOOD_DYN, meas="[x[0]]", name="my_pendulum", s1="q", s2="qdot",
                o1="q", duration=1.0, x0=(0.5, 0.0), extra=""):
    chains = '(KinematicChain("q", ("q", "qdot")),)' if (o1, s1, s2) == ("q", "q", "qdot") else "()"
    path = CASE / fname
    path.write_text(PENDULUM.format(dyn=dyn, meas=meas, name=name, s1=s1, s2=s2, o1=o1,
                                    duration=duration, x0=x0, chains=chains) + extra)
    return path

def cartpole_estimate(folder, data, out, *extra):
    return ["estimate", "--system", "cartpole", "--data", data, "--estimator",
            json.loads((Path(folder) / "manifest.json").read_text())["estimator"],
            "--compiled", folder, "--out", out, *extra]

LONG = W / "long.csv"
ROBOT = W / "robot.csv"

def load(name):
    from learnest_codegen.pipeline import load_estimator
    return load_estimator(LIB / name)

def long_run(system="cartpole"):
    from learnest_codegen import get_system
    from learnest_codegen.data import read_run
    return read_run(LONG if system == "cartpole" else ROBOT, get_system(system))

def band_entry(X, X_clean, truth, start, settle=500):
    """The first sample from `start` on after which the estimate stays in the clean run's band
    (|e| <= |e_clean| + rms_clean per state) to the end; None if it is not back within `settle`."""
    e, ec = np.abs(X - truth), np.abs(X_clean - truth)
    rms = np.sqrt(np.mean(ec[start:] ** 2, axis=0))
    out = np.flatnonzero(np.any(e[start:] > ec[start:] + rms, axis=1))
    back = 0 if not len(out) else int(out[-1]) + 1
    return back if back <= settle else None

def step_through(est, U, Y, x0):
    """Step an estimator sample by sample (sample k uses U[k-1]); failed steps keep the estimate."""
    from learnest_codegen.errors import SolverError
    est.reset(x0)
    X, failed = [], 0
    for k in range(len(Y)):
        try:
            X.append(est.step(U[k - 1] if k else np.zeros(U.shape[1]), Y[k]))
        except SolverError:
            failed += 1
            X.append(est.x)
    return np.array(X), failed
'''

WRAPPER = r'''
import json, os, sys, traceback
source = open(sys.argv[1]).read()
try:
    exec(compile(source, "case", "exec"), {"__name__": "__case__"})
except SystemExit:
    raise
except BaseException as exc:
    from learnest_codegen.errors import LearnestError
    message = str(exc).strip()
    user = isinstance(exc, (LearnestError, ValueError, OSError, ArithmeticError))
    if user and message and "\n" not in message:
        print("HOSTILE_ERROR " + json.dumps({"type": type(exc).__name__,
                                             "learnest": isinstance(exc, LearnestError),
                                             "message": message}), flush=True)
        sys.exit(0)
    traceback.print_exc()
    sys.exit(1)
print("HOSTILE_ACCEPTED {}", flush=True)
'''

SETUP = r'''
# --force: a workdir whose fixtures are incomplete or of an older layout is set up again
must(["simulate", "--system", "cartpole", "--seed", 4, "--duration", 1.0, "--out", RUN, "--force"])
from learnest_codegen import get_system
from learnest_codegen.compilation import ESTIMATORS, FLOAT32_NAMES, compile_estimators
from learnest_codegen.export import prior_model, true_model
# every estimator of the table; those generated in float32 also in float32
FLOAT32 = tuple(FLOAT32_NAMES)
model = prior_model(get_system("cartpole"))
compile_estimators(model, LIB, model_hash="nominal", estimators=tuple(ESTIMATORS))
compile_estimators(model, LIB, model_hash="nominal", estimators=FLOAT32, precision="float32")
compile_estimators(true_model(get_system("cartpole")), LIB, model_hash="true", estimators=("mhe",))
robot = prior_model(get_system("ground_robot"))
for precision in ("float64", "float32"):
    compile_estimators(robot, LIB, model_hash="nominal", estimators=FLOAT32, precision=precision)
must(["simulate", "--system", "cartpole", "--seed", 1, "--duration", 24.0, "--out", W / "long.csv",
      "--force"])
must(["simulate", "--system", "ground_robot", "--seed", 1, "--out", W / "robot.csv", "--force"])
print("fixtures ready", sorted(p.name for p in LIB.iterdir()))
'''


def _case(id, owner, expect, what, *code, **kw) -> Case:
    """A case whose snippet is the parts ``code``, each dedented on its own."""
    return Case(id, owner, expect, what,
                "\n".join(textwrap.dedent(part).strip() for part in code) + "\n", **kw)


# ---- the cases ------------------------------------------------------------------------------

def system_cases() -> list[Case]:
    """A user's system file: names, shapes and backends checked when it is loaded."""
    sim = 'final(["simulate", "--system", path, "--out", CASE / "run.csv"])'
    cases = [
        ("shapes/np-sin-simulate", "dynamics call np.sin (not ops.sin): simulate",
         'path = system_file(dyn=GOOD_DYN.replace("ops.sin", "np.sin"))\n' + sim, ("dynamics",)),
        ("shapes/math-sin-simulate", "dynamics call math.sin: simulate",
         'path = system_file(dyn=GOOD_DYN.replace("ops.sin", "math.sin"))\n' + sim, ("dynamics",)),
        ("shapes/dynamics-3-values", "dynamics return 3 values for 2 states: simulate",
         'path = system_file(dyn="[qdot, -9 * ops.sin(q), qdot]")\n' + sim, ("dynamics", "3")),
        ("shapes/dynamics-1-value", "dynamics return 1 value for 2 states: simulate",
         'path = system_file(dyn="[qdot]")\n' + sim, ("dynamics",)),
        ("shapes/measurement-2-values", "measurement returns 2 values for 1 output: simulate",
         'path = system_file(meas="[x[0], x[1]]")\n' + sim, ("measurement",)),
        ("shapes/true-dynamics-3-values", "true_dynamics return 3 values for 2 states",
         'path = system_file(extra="\\nimport dataclasses\\nSYSTEM = dataclasses.replace(SYSTEM, '
         'true_dynamics=lambda ops, x, u, p: [x[1], x[0], x[1]])\\n")\n' + sim, ("dynamics",)),
        ("shapes/branch-on-state", "dynamics branch on a state (if q > 0)",
         'path = system_file(dyn="[qdot, (1.0 if q > 0 else -1.0) * ops.sin(q) + u[0]]")\n' + sim,
         ("dynamics",)),
        ("shapes/dynamics-keyerror", "dynamics read a parameter that does not exist",
         'path = system_file(dyn=GOOD_DYN.replace(\'p["c"]\', \'p["damping"]\'))\n' + sim,
         ("dynamics",)),
        ("shapes/nan-at-x0", "dynamics are NaN at the initial state (sqrt of a negative)",
         'path = system_file(dyn="[qdot, ops.sqrt(q - 1.0) + u[0]]")\n' + sim, ("dynamics",)),
        ("names/comma", "a state named 'q,1' (a comma in a CSV header)",
         'path = system_file(s1="q,1")\n' + sim, ("q,1",)),
        ("names/newline", "a state named 'q\\nx' (a newline in a CSV header)",
         'path = system_file(s1="q\\nx")\n' + sim, ()),
        ("names/empty", "an output named ''", 'path = system_file(o1="")\n' + sim, ()),
        ("names/space", "a state named ' q' (spaces are stripped when read back)",
         'path = system_file(s1=" q")\n' + sim, ()),
        ("names/duplicate-states", "two states named 'q'",
         'path = system_file(s2="q")\n' + sim, ("q",)),
        ("names/system-name", "a system named 'my pendulum' (not a C identifier)",
         'path = system_file(name="my pendulum")\n' + sim, ("my pendulum",)),
    ]
    out = [_case(i, "boundaries", ERROR, what, code, needles=needles, timeout=90)
           for i, what, code, needles in cases]
    out += [
        _case("shapes/np-sin-train", "boundaries", ERROR,
              "dynamics call np.sin: train (a 60-line traceback before)", '''
              good = system_file("good.py")
              must(["simulate", "--system", good, "--out", CASE / "run.csv"])
              path = system_file(dyn=GOOD_DYN.replace("ops.sin", "np.sin"))
              final(["train", "--system", path, "--data", CASE / "run.csv", "--out", CASE / "m",
                     "--epochs", 2, "--refine", 0, "--validation-fraction", 0])
              ''', needles=("dynamics",), timeout=180),
        _case("shapes/dynamics-3-values-compile", "boundaries", ERROR,
              "dynamics return 3 values for 2 states: learnest-compile", '''
              path = system_file(dyn="[qdot, -9 * ops.sin(q), qdot]")
              final(["--nominal", "--system", path, "--estimator", "ukf", "--out", CASE / "gen"],
                    compile=True)
              ''', needles=("dynamics",), timeout=180),
        _case("shapes/readme-pendulum", "boundaries", RESULT,
              "control: the README's pendulum simulates, compiles and estimates", '''
              path = system_file(duration=1.0)
              must(["simulate", "--system", path, "--out", CASE / "run.csv"])
              must(["--nominal", "--system", path, "--estimator", "ukf", "--out", CASE / "gen"],
                   compile=True)
              def check(out):
                  est, truth = table(CASE / "est.csv"), table(CASE / "run.csv")
                  err = float(np.abs(est[:, 1] - truth[:, 3]).max())
                  return err < 0.05, f"max |q_hat - q| = {err:.3g}"
              final(["estimate", "--system", path, "--data", CASE / "run.csv", "--estimator", "ukf",
                     "--compiled", CASE / "gen" / "my_pendulum_nominal_ukf", "--out", CASE / "est.csv"],
                    check=check)
              ''', timeout=240),
        _case("shapes/builtin-systems", "boundaries", RESULT,
              "control: every built-in system loads and simulates 20 samples", '''
              from learnest_codegen.systems import SYSTEMS, get_system
              from learnest_codegen.simulation import simulate
              bad = []
              for name in SYSTEMS:
                  s = get_system(name)
                  run = simulate(s, 0, duration=20 * s.dt)
                  if not (np.isfinite(run.x).all() and run.x.shape == (20, s.nx)):
                      bad.append(name)
              verdict(not bad, f"not finite: {bad}")
              '''),
    ]
    return out


def simulate_cases() -> list[Case]:
    """learnest simulate: durations, and dynamics that go non-finite or stiff on the way."""
    sim = 'final(["simulate", "--system", path, "--out", CASE / "run.csv"])'
    cases = []
    for value in ("-1", "0", "nan", "inf", "1e12"):
        cases.append(_case(f"simulate/duration-{value}", "boundaries", ERROR,
                           f"simulate --duration {value}",
                           f'final(["simulate", "--duration", "{value}", "--out", CASE / "r.csv"])',
                           needles=("duration",), timeout=90))
    cases += [
        _case("simulate/nan-later", "boundaries", ERROR,
              "dynamics finite at x0 that turn NaN after 1 s (sqrt of 1.5 - q, q = t + 0.5): "
              "hung before", 'path = system_file(dyn="[1.0 + 0 * qdot, ops.sqrt(1.5 - q) + u[0]]", '
              'duration=3.0)\n' + sim, needles=("t =",), timeout=90),
        _case("simulate/blow-up", "boundaries", ERROR,
              "dynamics with a finite-time blow-up (qdot' = q^2, x0 = 1: infinite at t = 1 s)",
              'path = system_file(dyn="[q * q + 0 * qdot, 0 * q + u[0]]", x0=(1.0, 0.0), '
              'duration=3.0)\n' + sim, needles=("t =",), timeout=90),
        _case("simulate/stiff", "boundaries", ERROR,
              "a spring of stiffness 1e14 (explicit RK45 needs ~1e6 steps per sample)",
              'path = system_file(dyn="[qdot, -1e14 * q + u[0]]", duration=1.0)\n' + sim,
              needles=("steps",), timeout=90),
    ]
    return cases


def option_cases() -> list[Case]:
    """Options of the commands and of the settings classes: out of range is one clear line."""
    est_ukf = ('final(cartpole_estimate(LIB / "cartpole_nominal_ukf", RUN, CASE / "e.csv", {}))')
    cases = [
        _case("options/gate-recover-after-wrap", "boundaries", ERROR,
              "--gate-recover-after 4294967306 (reached C as 10)",
              est_ukf.format('"--gate-recover-after", "4294967306"'), needles=("recover",)),
        _case("options/gate-recover-after-2^31", "boundaries", ERROR, "--gate-recover-after 2147483648",
              est_ukf.format('"--gate-recover-after", "2147483648"'), needles=("recover",)),
        _case("options/gate-inflation-1e300", "boundaries", ERROR,
              "--gate-inflation 1e300 (above the cap: the recovery never inflates)",
              est_ukf.format('"--gate-inflation", "1e300"'), needles=("inflation",)),
        _case("options/gate-inflation-nan", "boundaries", ERROR, "--gate-inflation nan",
              est_ukf.format('"--gate-inflation", "nan"'), needles=("inflation",)),
        _case("options/gate-threshold-nan", "boundaries", ERROR, "--gate-threshold nan",
              est_ukf.format('"--gate-threshold", "nan"'), needles=("threshold",)),
        _case("options/gate-threshold-1e-300", "boundaries", ERROR,
              "--gate-threshold 1e-300 (rejects every output)",
              est_ukf.format('"--gate-threshold", "1e-300"'), needles=("threshold",)),
        _case("options/gate-threshold-negative", "boundaries", ERROR, "--gate-threshold -1",
              est_ukf.format('"--gate-threshold", "-1"'), needles=("threshold",)),
        _case("options/gate-threshold-1e300", "boundaries", ERROR,
              "--gate-threshold 1e300 (an 'off' that is not 0)",
              est_ukf.format('"--gate-threshold", "1e300"'), needles=("threshold",)),
    ]
    api = [
        ("options/gn-tolerance-1e300", "GaussNewtonSettings(tolerance=1e300): no step taken (MSE 36-47x)",
         "GaussNewtonSettings(tolerance=1e300)", ("tolerance",)),
        ("options/gn-tolerance-inf", "GaussNewtonSettings(tolerance=inf)",
         "GaussNewtonSettings(tolerance=float('inf'))", ("tolerance",)),
        ("options/gn-tolerance-nan", "GaussNewtonSettings(tolerance=nan)",
         "GaussNewtonSettings(tolerance=float('nan'))", ("tolerance",)),
        ("options/gn-tolerance-1e-300", "GaussNewtonSettings(tolerance=1e-300): unreachable",
         "GaussNewtonSettings(tolerance=1e-300)", ("tolerance",)),
        ("options/gn-tolerance-float32-1e-10", "float32 GaussNewtonSettings(tolerance=1e-10): "
         "below float32's rounding", "GaussNewtonSettings(tolerance=1e-10, precision='float32')",
         ("tolerance",)),
        ("options/gn-max-iterations-0", "GaussNewtonSettings(max_iterations=0)",
         "GaussNewtonSettings(max_iterations=0)", ("max_iterations",)),
        ("options/gn-max-iterations-1e9", "GaussNewtonSettings(max_iterations=10**9)",
         "GaussNewtonSettings(max_iterations=10**9)", ("max_iterations",)),
        ("options/gate-recover-after-api", "GateSettings(recover_after=2**32 + 10)",
         "GateSettings(recover_after=2**32 + 10)", ("recover_after",)),
        ("options/gate-inflation-api", "GateSettings(inflation=1e300)",
         "GateSettings(inflation=1e300)", ("inflation",)),
        ("options/horizon-0", "MHESettings horizon 0",
         "MHESettings.from_system(get_system('cartpole'), horizon=0)", ("horizon",)),
        ("options/horizon-1e7", "MHESettings horizon 10**7 (a window of 40 million reals)",
         "MHESettings.from_system(get_system('cartpole'), horizon=10**7)", ("horizon",)),
        ("options/horizon-float", "MHESettings horizon 20.5",
         "MHESettings.from_system(get_system('cartpole'), horizon=20.5)", ("horizon",)),
        ("options/ukf-alpha-1e300", "UKFSettings(alpha=1e300)",
         "UKFSettings.from_system(get_system('cartpole'), alpha=1e300)", ("alpha",)),
        ("options/ukf-std-1e-200", "UKFSettings measurement_std 1e-200 (R = 1e-400 = 0)",
         "UKFSettings.from_system(get_system('cartpole'), measurement_std=(1e-200, 0.01))",
         ("measurement_std",)),
        ("options/mhe-std-1e200", "MHESettings process_std 1e200 (Q = 1e-400 = 0)",
         "MHESettings.from_system(get_system('cartpole'), process_std=(1e200, 1, 1, 1))",
         ("process_std",)),
    ]
    head = ("from learnest_codegen import get_system\n"
            "from learnest_codegen.estimators.mhe_gn import GaussNewtonSettings\n"
            "from learnest_codegen.estimators.gate import GateSettings\n"
            "from learnest_codegen.estimators.mhe_problem import MHESettings\n"
            "from learnest_codegen.estimators.ukf import UKFSettings\n")
    cases += [_case(i, "boundaries", ERROR, what, head, expr, needles=n) for i, what, expr, n in api]
    cases += [
        _case("options/gn-max-iterations-wrap", "boundaries", ERROR,
              "GaussNewtonSettings(max_iterations=2**32 + 3) on a compiled mhe_gn (C int)", '''
              from learnest_codegen.estimators.mhe_gn import GaussNewtonSettings
              from learnest_codegen.runtime.mhe_gn import CompiledEmbeddedMHE
              est = CompiledEmbeddedMHE(LIB / "cartpole_nominal_mhe_gn_n20",
                                        solver=GaussNewtonSettings(max_iterations=2**32 + 3))
              est.reset(np.array([0, 0, 0.3, 0.0]))
              ''', needles=("max_iterations",)),
        _case("options/gn-unreachable-hang", "boundaries", ERROR,
              "mhe_gn with max_iterations 1e9 and tolerance 1e-300 from Python (hours per step)", '''
              from learnest_codegen.estimators.mhe_gn import GaussNewtonSettings
              from learnest_codegen.runtime.mhe_gn import CompiledEmbeddedMHE
              from learnest_codegen.data import read_run
              from learnest_codegen import get_system
              run = read_run(RUN, get_system("cartpole"))
              est = CompiledEmbeddedMHE(LIB / "cartpole_nominal_mhe_gn_n20",
                  solver=GaussNewtonSettings(max_iterations=10**9, tolerance=1e-300))
              est.run(run.u, run.y, np.array([0, 0, 0.3, 0.0]))
              ''', timeout=60, needles=("max_iterations",)),
        _case("options/c-set-options-tol-inf", "c-api", ERROR,
              "C <prefix>_set_options(tol = inf): BAD_ARGUMENT expected",
              _raw_set_options("float('inf')", 30)),
        _case("options/c-set-options-tol-1e300", "c-api", ERROR,
              "C <prefix>_set_options(tol = 1e300): no step taken", _raw_set_options("1e300", 30)),
        _case("options/c-set-options-max-iter-int-max", "c-api", ERROR,
              "C <prefix>_set_options(max_iter = INT_MAX, tol = 1e-300): a step runs for hours",
              _raw_set_options("1e-300", 2**31 - 1), timeout=60),
        _case("options/train-epochs-0", "boundaries", ERROR, "train --epochs 0",
              'final(["train", "--data", RUN, "--out", CASE / "m", "--epochs", 0])',
              needles=("epochs",), timeout=120),
        _case("options/train-hidden-0", "boundaries", ERROR, "train --hidden 0",
              'final(["train", "--data", RUN, "--out", CASE / "m", "--hidden", 0])',
              needles=("hidden",), timeout=120),
        _case("options/train-lr-nan", "boundaries", ERROR, "train --lr nan",
              'final(["train", "--data", RUN, "--out", CASE / "m", "--lr", "nan", "--epochs", 2])',
              needles=("learning_rate",), timeout=120),
        _case("options/train-validation-fraction-1.5", "boundaries", ERROR,
              "train --validation-fraction 1.5",
              'final(["train", "--data", RUN, "--out", CASE / "m", "--validation-fraction", 1.5])',
              needles=("validation_fraction",), timeout=120),
    ]
    return cases


def _raw_set_options(tol: str, max_iter: int) -> str:
    return f'''
    from learnest_codegen.runtime.mhe_gn import CompiledEmbeddedMHE
    from learnest_codegen.data import read_run
    from learnest_codegen import get_system
    run = read_run(RUN, get_system("cartpole"))
    est = CompiledEmbeddedMHE(LIB / "cartpole_nominal_mhe_gn_n20")
    clean = est.run(run.u, run.y, np.array([0, 0, 0.3, 0.0]))
    est.reset(np.array([0, 0, 0.3, 0.0]))
    code = est._c["set_options"](est._handle, 0, {max_iter}, {tol})
    if code < 0:
        mark("ERROR", type="C", message=f"set_options returned {{code}}")
    X = []
    for k in range(len(run.y)):
        X.append(est.step(run.u[k - 1] if k else np.zeros(1), run.y[k]))
    X = np.array(X)
    ratio = float(np.mean((X - run.x) ** 2) / np.mean((clean - run.x) ** 2))
    verdict(False, f"accepted (code {{code}}); MSE {{ratio:.3g}} x the default's")
    '''


def file_cases() -> list[Case]:
    """Where results are written: special files, existing folders, interrupted compiles."""
    special = {
        "char-device": "os.mknod(target, 0o666 | stat.S_IFCHR, os.makedev(1, 7))  # a copy of /dev/full",
        "fifo": "os.mkfifo(target)",
        "socket": "import socket; s = socket.socket(socket.AF_UNIX); s.bind(str(target))",
    }
    test = {"char-device": "stat.S_ISCHR", "fifo": "stat.S_ISFIFO", "socket": "stat.S_ISSOCK"}
    cases = []
    for kind, make in special.items():
        for force in ((True, False) if kind == "fifo" else (True,)):
            flag = ', "--force"' if force else ""
            cases.append(_case(
                f"files/out-{kind}{'-force' if force else ''}", "boundaries", ERROR,
                f"simulate --out <{kind}>{' --force' if force else ''} (replaced by a regular file)",
                f'''
                target = CASE / "special"
                if {kind!r} == "char-device" and os.geteuid() != 0:
                    mark("SKIP", reason="making a device node needs root")
                {make}
                def check(out):
                    kept = {test[kind]}(os.lstat(target).st_mode)
                    return kept, "kept" if kept else "replaced by a regular file"
                final(["simulate", "--duration", 0.1, "--out", target{flag}], check=check)
                ''', needles=("special",)))
    cases += [
        _case("files/estimate-out-fifo", "boundaries", ERROR, "estimate --out <fifo> --force", '''
              target = CASE / "special"
              os.mkfifo(target)
              def check(out):
                  return stat.S_ISFIFO(os.lstat(target).st_mode), "fifo replaced"
              final(cartpole_estimate(LIB / "cartpole_nominal_ukf", RUN, target, "--force"), check=check)
              ''', needles=("special",)),
        _case("files/train-out-file", "boundaries", ERROR, "control: train --out <a file>", '''
              (CASE / "f").write_text("x")
              final(["train", "--data", RUN, "--out", CASE / "f", "--epochs", 1])
              ''', needles=("is a file",)),
        _case("files/estimate-out-is-data", "boundaries", ERROR, "control: estimate --out <its --data>",
              'final(cartpole_estimate(LIB / "cartpole_nominal_ukf", RUN, RUN, "--force"))',
              needles=("input",)),
        _case("files/compile-existing-folder", "boundaries", ERROR,
              "learnest-compile over an existing folder (a hand edit inside) without --force", '''
              must(["--nominal", "--estimator", "ukf", "--out", CASE / "gen"], compile=True)
              folder = CASE / "gen" / "cartpole_nominal_ukf"
              glue = folder / "cartpole_nominal_ukf.c"  # the estimator's own C (the kit's glue)
              glue.write_text(glue.read_text() + "\\n/* my hand edit */\\n")
              final(["--nominal", "--estimator", "ukf", "--out", CASE / "gen"], compile=True)
              ''', needles=("--force",), timeout=180),
        _case("files/compile-existing-folder-force", "boundaries", RESULT,
              "learnest-compile --force over an existing folder: rebuilt whole, loads", '''
              must(["--nominal", "--estimator", "ukf", "--out", CASE / "gen"], compile=True)
              (CASE / "gen" / "cartpole_nominal_ukf" / "stray.txt").write_text("x")
              compile_force(["--nominal", "--estimator", "ukf", "--out", CASE / "gen"])
              folder = CASE / "gen" / "cartpole_nominal_ukf"
              def check(out):
                  ref = table(CASE / "ref.csv")
                  same = np.array_equal(table(CASE / "e.csv"), ref)
                  return same, "estimates equal the fixture's" if same else "estimates differ"
              must(cartpole_estimate(LIB / "cartpole_nominal_ukf", RUN, CASE / "ref.csv"))
              final(cartpole_estimate(folder, RUN, CASE / "e.csv"), check=check)
              ''', timeout=180),
        _case("files/compile-interrupted", "boundaries", RESULT,
              "Ctrl-C during learnest-compile (ukf done, mhe being written): no empty or partial folder",
              '''
              # SIGINT as a terminal's Ctrl-C delivers it (a background job inherits it ignored)
              proc = subprocess.Popen(_argv(["--nominal", "--estimator", "ukf", "--estimator", "mhe",
                                             "--out", CASE / "gen"], compile=True),
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                      preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
              start = time.time()  # interrupt once the MHE's folder (or its temporary one) exists
              while not list((CASE / "gen").glob("*cartpole_nominal_mhe*")) and proc.poll() is None \
                      and time.time() - start < TIMEOUT - 20:
                  time.sleep(0.05)
              time.sleep(0.3)
              finished_first = proc.poll() is not None
              proc.send_signal(signal.SIGINT)
              proc.communicate(timeout=60)
              if proc.returncode == 0:
                  raise SystemExit("HOSTILE_SETUP_FAILED the compile was not interrupted")
              problems = []
              for d in sorted((CASE / "gen").iterdir()):
                  if d.name.startswith("."):
                      problems.append(f"left {d.name}")
                  elif not (d / "manifest.json").is_file() or not list(d.glob("lib*.so")):
                      problems.append(f"{d.name} incomplete ({len(list(d.iterdir()))} files)")
              note = "; ".join(problems) or "only complete folders"
              if finished_first:
                  note += " (the command finished before the interrupt)"
              verdict(not problems, note)
              ''', timeout=240),
    ]
    return cases


def library_cases() -> list[Case]:
    """Compiled folders that were damaged, swapped or edited, and a re-compile over them."""
    variant = ('import dataclasses\nfrom learnest_codegen.systems import CARTPOLE\n'
               'SYSTEM = dataclasses.replace(CARTPOLE, params={**CARTPOLE.params, "l": 0.6}, '
               'true_params={**CARTPOLE.true_params, "l": 0.6})\n')
    same_as_fixture = '''
    def check(out):
        must(cartpole_estimate(LIB / "cartpole_nominal_ukf", RUN, CASE / "ref.csv"))
        diff = float(np.abs(table(CASE / "e.csv") - table(CASE / "ref.csv")).max())
        return diff == 0, f"max difference to the fixture's estimates {diff:.3g}"
    '''
    return [
        _case("libraries/truncated-recompile", "boundaries", RESULT,
              "library cut to a third, then the same learnest-compile again, then estimate (SIGBUS)",
              same_as_fixture, '''
              must(["--nominal", "--estimator", "ukf", "--out", CASE / "gen"], compile=True)
              folder = CASE / "gen" / "cartpole_nominal_ukf"
              lib = next(folder.glob("lib*.so"))
              data = lib.read_bytes()
              lib.write_bytes(data[: len(data) // 3])
              compile_force(["--nominal", "--estimator", "ukf", "--out", CASE / "gen"])
              final(cartpole_estimate(folder, RUN, CASE / "e.csv"), check=check)
              ''', timeout=240),
        _case("libraries/swapped-recompile", "boundaries", RESULT,
              "library replaced by another build of the same prefix (pole 0.6 m), re-compiled, "
              "estimate (ran the wrong model)", same_as_fixture, f'''
              (CASE / "cartpole.py").write_text({variant!r})
              must(["--nominal", "--estimator", "ukf", "--out", CASE / "a"], compile=True)
              must(["--nominal", "--system", CASE / "cartpole.py", "--estimator", "ukf",
                    "--out", CASE / "b"], compile=True)
              folder = CASE / "a" / "cartpole_nominal_ukf"
              lib = next(folder.glob("lib*.so"))
              # libraries are named by their fingerprint: the other build's has its own name
              shutil.copyfile(next((CASE / "b" / "cartpole_nominal_ukf").glob("lib*.so")), lib)
              compile_force(["--nominal", "--estimator", "ukf", "--out", CASE / "a"])
              final(cartpole_estimate(folder, RUN, CASE / "e.csv"), check=check)
              ''', timeout=300),
        _case("libraries/swapped-load", "boundaries", ERROR,
              "control: library replaced by another build, loaded without re-compiling", f'''
              (CASE / "cartpole.py").write_text({variant!r})
              must(["--nominal", "--system", CASE / "cartpole.py", "--estimator", "ukf",
                    "--out", CASE / "b"], compile=True)
              folder = copy_folder("cartpole_nominal_ukf")
              lib = next(folder.glob("lib*.so"))
              # libraries are named by their fingerprint: the other build's has its own name
              shutil.copyfile(next((CASE / "b" / "cartpole_nominal_ukf").glob("lib*.so")), lib)
              final(cartpole_estimate(folder, RUN, CASE / "e.csv"))
              ''', needles=("SHA-256",), timeout=180),
        _case("libraries/truncated-load", "boundaries", ERROR, "control: library cut short, loaded", '''
              folder = copy_folder("cartpole_nominal_ukf")
              lib = next(folder.glob("lib*.so"))
              lib.write_bytes(lib.read_bytes()[:5000])
              final(cartpole_estimate(folder, RUN, CASE / "e.csv"))
              ''', needles=("bytes",)),
        _case("libraries/manifest-precision-mhe_gn", "boundaries", ERROR,
              "manifest.json of a float64 mhe_gn edited to say float32", '''
              folder = copy_folder("cartpole_nominal_mhe_gn_n20")
              m = json.loads((folder / "manifest.json").read_text())
              m["precision"] = "float32"
              (folder / "manifest.json").write_text(json.dumps(m))
              from learnest_codegen.pipeline import load_estimator
              load_estimator(folder)
              ''', needles=("float32", "float64")),
        _case("libraries/manifest-precision-ukf", "boundaries", ERROR,
              "manifest.json of a float64 UKF edited to say float32", '''
              folder = copy_folder("cartpole_nominal_ukf")
              m = json.loads((folder / "manifest.json").read_text())
              m["precision"] = "float32"
              (folder / "manifest.json").write_text(json.dumps(m))
              from learnest_codegen.pipeline import load_estimator
              load_estimator(folder)
              ''', needles=("float32", "float64")),
        _case("libraries/manifest-nx", "boundaries", ERROR, "control: manifest nx edited to 5", '''
              folder = copy_folder("cartpole_nominal_mhe_rti_n20")
              m = json.loads((folder / "manifest.json").read_text())
              m["nx"] = 5
              (folder / "manifest.json").write_text(json.dumps(m))
              from learnest_codegen.pipeline import load_estimator
              load_estimator(folder)
              ''', needles=("5",)),
        _case("libraries/library-deleted", "boundaries", ERROR, "control: library file deleted", '''
              folder = copy_folder("cartpole_nominal_ukf")
              next(folder.glob("lib*.so")).unlink()
              final(cartpole_estimate(folder, RUN, CASE / "e.csv"))
              ''', needles=("does not exist",)),
        _case("libraries/failed-init-keeps-live", "c-api", RESULT,
              "a failed init (NaN x0) on the workspace of a live UKF leaves it as it was", '''
              import ctypes
              from learnest_codegen.pipeline import load_estimator
              est = load_estimator(LIB / "cartpole_nominal_ukf")
              x0 = np.array([0, 0, 0.3, 0.0])
              est.reset(x0)
              est.step(np.zeros(1), np.array([0.0, 0.3]))
              before = est.x
              s = est.settings
              bad = np.array([np.nan, 0, 0, 0])
              handle = ctypes.c_void_p()
              code = est._c["init"](est._memory.ctypes.data, est._memory.nbytes, bad, s.P0(), s.Q(),
                                    s.R(), ctypes.byref(handle))
              try:
                  after = est.x
                  verdict(np.array_equal(after, before), f"init returned {code}; estimate kept")
              except Exception as exc:
                  verdict(False, f"init returned {code}; the live estimator is gone: {exc}")
              '''),
    ]


def thread_cases() -> list[Case]:
    """Estimators in threads: results equal the sequential ones, no spurious failures."""
    body = '''
    import threading
    from learnest_codegen.pipeline import load_estimator
    from learnest_codegen.data import read_run
    from learnest_codegen import get_system
    run = read_run(RUN, get_system("cartpole"))
    U, Y, x0 = run.u[:{T}], run.y[:{T}], np.array([0, 0, 0.3, 0.0])
    ests = [load_estimator(LIB / name) for name in {folders}]
    refs = [e.run(U, Y, x0) for e in ests]
    errors, bad = [], 0
    for round_ in range({rounds}):
        outs = [None] * len(ests)
        def work(i):
            try:
                outs[i] = ests[i].run(U, Y, x0)
            except Exception as exc:
                errors.append(f"round {{round_}}: {{exc}}")
        threads = [threading.Thread(target=work, args=(i,)) for i in range(len(ests))]
        for t in threads: t.start()
        for t in threads: t.join()
        bad += sum(o is not None and not np.array_equal(o, r) for o, r in zip(outs, refs))
    verdict(not errors and not bad, f"{{len(errors)}} failed runs, {{bad}} differing; {{errors[:1]}}")
    '''
    ipopt2 = ["cartpole_nominal_mhe_n20", "cartpole_nominal_mhe_n20"]
    return [
        _case("threads/ipopt-mhe-one-library", "boundaries", RESULT,
              "two Ipopt-MHE handles of one library in two threads (NO_MEMORY before)",
              body.format(T=150, folders=ipopt2, rounds=6), timeout=240),
        _case("threads/ipopt-mhe-two-libraries", "boundaries", RESULT,
              "Ipopt MHEs of two libraries (nominal, true) in two threads",
              body.format(T=150, folders=["cartpole_nominal_mhe_n20", "cartpole_true_mhe_n20"], rounds=6),
              timeout=240),
        _case("threads/ukf-and-mhe_gn", "boundaries", RESULT,
              "control: two UKF and two mhe_gn handles in four threads",
              body.format(T=300, folders=["cartpole_nominal_ukf", "cartpole_nominal_ukf",
                                          "cartpole_nominal_mhe_gn_n20", "cartpole_nominal_mhe_gn_n20"],
                          rounds=4), timeout=240),
    ]


def csv_cases() -> list[Case]:
    """Run CSVs: values, columns, encodings and special files."""
    est = lambda folder, *extra: f'cartpole_estimate(LIB / "{folder}", CASE / "bad.csv", CASE / "e.csv"{"".join(", " + repr(e) for e in extra)})'  # noqa: E501,E731
    rejected = '''
    def check(out):
        ok = "1 output(s) rejected" in out and np.isfinite(table(CASE / "e.csv")).all()
        return ok, out.strip().splitlines()[-1][-80:] if out.strip() else "no output"
    '''
    big = []
    for folder, owner in (("cartpole_nominal_ukf", "boundaries"),
                          ("cartpole_nominal_ukf_float32", "boundaries"),
                          ("cartpole_nominal_mhe_gn_n20_float32", "boundaries"),
                          ("cartpole_nominal_mhe_rti_n20_float32", "boundaries")):
        big.append(_case(f"float32/csv-1e39-{folder.replace('cartpole_nominal_', '')}", owner, RESULT,
                         f"a y value of 1e39 (beyond float32) in the run, {folder}: gated as in float64",
                         rejected, f'''
                         edit_csv(RUN, CASE / "bad.csv", row=100, column="y_p", value="1e39")
                         final({est(folder)}, check=check)
                         '''))
    cases = big + [
        _case("csv/duplicate-column", "data", ERROR, "a run with y_p twice (the last one won)", '''
              def dup(lines):
                  return [l + "," + l.split(",")[lines[0].split(",").index("y_p")] if i == 0 else
                          l + ",5.0" for i, l in enumerate(lines)]
              edit_csv(RUN, CASE / "bad.csv", transform=dup)
              final(''' + est("cartpole_nominal_ukf") + ")\n", needles=("y_p",)),
        _case("csv/complex", "data", ERROR, "a complex value '1+2j' in y_p", '''
              edit_csv(RUN, CASE / "bad.csv", row=10, column="y_p", value="1+2j")
              final(''' + est("cartpole_nominal_ukf") + ")\n", needles=("y_p",)),
        _case("csv/bom", "data", ERROR | RESULT, "a UTF-8 BOM before the header", '''
              (CASE / "bad.csv").write_bytes(b"\\xef\\xbb\\xbf" + RUN.read_bytes())
              final(''' + est("cartpole_nominal_ukf") + ")\n", avoid=("\\ufeff", "missing columns")),
        _case("csv/non-utf8-header", "data", ERROR, "a Latin-1 byte in the header", '''
              (CASE / "bad.csv").write_bytes(RUN.read_bytes().replace(b"y_p", b"y_p\\xe9", 1))
              final(''' + est("cartpole_nominal_ukf") + ")\n", needles=("bad.csv",)),
        _case("csv/dev-zero", "data", ERROR, "--data /dev/zero",
              'final(cartpole_estimate(LIB / "cartpole_nominal_ukf", "/dev/zero", CASE / "e.csv"))',
              avoid=("not found",)),
        _case("csv/nan", "data", RESULT, "control: a NaN in y_p is a missing sample", '''
              def check(out):
                  ok = "1 missing" in out and np.isfinite(table(CASE / "e.csv")).all()
                  return ok, out.strip().splitlines()[-1][-80:] if out.strip() else "no output"
              ''', '''
              edit_csv(RUN, CASE / "bad.csv", row=10, column="y_p", value="nan")
              final(''' + est("cartpole_nominal_ukf") + ", check=check)\n"),
        _case("csv/time-back", "data", ERROR, "control: time goes back", '''
              edit_csv(RUN, CASE / "bad.csv", row=10, column="t", value="0")
              final(''' + est("cartpole_nominal_ukf") + ")\n", needles=("time",)),
        _case("csv/semicolons", "data", ERROR, "control: ';' as the delimiter", '''
              (CASE / "bad.csv").write_text(RUN.read_text().replace(",", ";"))
              final(''' + est("cartpole_nominal_ukf") + ")\n", needles=("missing columns",)),
        _case("csv/header-only", "data", ERROR, "control: a header and no rows", '''
              (CASE / "bad.csv").write_text(RUN.read_text().splitlines()[0] + "\\n")
              final(''' + est("cartpole_nominal_ukf") + ")\n", needles=("samples",)),
        _case("csv/1e308", "data", RESULT, "control: y_p = 1e308 (float64): gated",
              rejected, '''
              edit_csv(RUN, CASE / "bad.csv", row=100, column="y_p", value="1e308")
              final(''' + est("cartpole_nominal_ukf") + ", check=check)\n"),
        _case("api/complex-y", "boundaries", ERROR, "est.step(u, y) with a complex y", '''
              from learnest_codegen.pipeline import load_estimator
              est = load_estimator(LIB / "cartpole_nominal_ukf")
              est.reset(np.array([0, 0, 0.3, 0.0]))
              est.step(np.zeros(1), np.array([0.0, 0.3 + 1j]))
              ''', needles=("complex",)),
        _case("api/object-y", "boundaries", ERROR, "est.step(u, [None, 0.3])", '''
              from learnest_codegen.pipeline import load_estimator
              est = load_estimator(LIB / "cartpole_nominal_ukf")
              est.reset(np.array([0, 0, 0.3, 0.0]))
              est.step(np.zeros(1), [None, 0.3])
              ''', needles=("y",)),
        _case("api/run-complex-U", "boundaries", ERROR, "est.run(U, Y, x0) with a complex U", '''
              from learnest_codegen.pipeline import load_estimator
              est = load_estimator(LIB / "cartpole_nominal_mhe_rti_n20")
              est.run(np.zeros((10, 1)) + 1j, np.zeros((10, 2)), np.array([0, 0, 0.3, 0.0]))
              ''', needles=("complex",)),
        _case("api/step-wrong-shape", "boundaries", ERROR, "control: y of 3 values for 2 outputs", '''
              from learnest_codegen.pipeline import load_estimator
              est = load_estimator(LIB / "cartpole_nominal_mhe_gn_n20")
              est.reset(np.array([0, 0, 0.3, 0.0]))
              est.step(np.zeros(1), np.zeros(3))
              ''', needles=("shape",)),
    ]
    return cases


def input_cases() -> list[Case]:
    """A few samples of a wrong but finite input u: every estimator must recover within 60."""
    body = '''
    from learnest_codegen import get_system
    from learnest_codegen.simulation import simulate
    system = get_system("cartpole")
    run = simulate(system, seed=1, duration=0.8)
    x0 = np.asarray(system.x0, float)
    {make}
    clean, _ = step_through(est, run.u, run.y, x0)
    U = run.u.copy()
    U[149:149 + {length}] = {size}   # sample k uses U[k - 1]: samples 150 .. of the burst
    burst, failed = step_through(est, U, run.y, x0)
    rms = np.sqrt(np.mean((clean - run.x) ** 2, axis=0))
    dev = np.abs(burst - clean) / rms
    after = dev[150 + {length} + 60:].max()
    verdict(after <= 1.0, f"deviation 60 samples after the burst {{after:.3g}} clean RMS errors, "
            f"{{failed}} failed steps")
    '''
    c = 'from learnest_codegen.pipeline import load_estimator\nest = load_estimator(LIB / "{}")'
    py = ('from learnest_codegen.pipeline import make_estimator\n'
          'est = make_estimator("nominal", "{}", backend="python", system="cartpole")')
    rows = [("mhe", "python", 3, 1e3, "data"), ("ukf", "python", 1, 1e6, "data"),
            ("cartpole_nominal_mhe_n20", "c", 3, 1e3, "c-api"),
            ("cartpole_nominal_mhe_gn_n20", "c", 3, 1e3, "c-api"),
            ("cartpole_nominal_mhe_rti_n20", "c", 3, 1e3, "c-api"),
            ("cartpole_nominal_mhe_gn_n20_float32", "c", 3, 1e3, "c-api"),
            ("cartpole_nominal_ukf", "c", 1, 1e6, "c-api"),
            ("cartpole_nominal_ukf_float32", "c", 1, 1e6, "c-api")]
    out = []
    for name, backend, length, size, owner in rows:
        label = name.replace("cartpole_nominal_", "")
        make = (c if backend == "c" else py).format(name)
        make = make.replace("\n", "\n    ")
        out.append(_case(f"inputs/u-burst-{label}-{backend}", owner, RESULT,
                         f"u = {size:g} for {length} sample(s), {label} ({backend}): back within 60 samples",
                         body.format(make=make, length=length, size=size), timeout=240))
    return out


# ---- the streams surface: predictions, gaps, lost tracks, tuning, masks, threads ------------

def _builds(both=True):
    """(label, folder) of the cartpole builds the recovery cases run on."""
    names = [f"{e}{p}" for e in ("ukf", "mhe_gn", "mhe_rti") for p in (("", "_float32") if both else ("",))]
    return [(n, f"cartpole_nominal_{n}".replace("mhe_gn", "mhe_gn_n20").replace("mhe_rti", "mhe_rti_n20"))
            for n in names]


def prediction_cases() -> list[Case]:
    """10,000 predictions from a sample: finite, UNRELIABLE, and the next measurement recovers."""
    body = '''
    from learnest_codegen.errors import SolverError
    run = long_run()
    est = load("{folder}")
    x0 = np.array([0, 0, 0.3, 0.0])
    clean = est.run(run.u, run.y, x0)
    est.reset(x0)
    start, n = {start}, 10000
    X, codes = [], []
    for k in range(len(run.y)):
        u = run.u[max(k - 1, 0)]
        if start <= k < start + n:
            X.append(est.predict(u))
        else:
            X.append(est.step(u, run.y[k]))
        codes.append(est.last_status)
    X = np.array(X)
    pred = X[start:start + n]
    finite = bool(np.isfinite(pred).all())
    flagged = bool(codes[start + n - 1] & 4)
    first = codes[start + n]
    back = band_entry(X, clean, run.x, start + n)
    verdict(finite and flagged and not first & 4 and back is not None,
            f"finite {{finite}}, status 4 at the end of the predictions {{flagged}}, first valid "
            f"step status {{first}}, back in the clean band after {{back}} samples")
    '''
    out = []
    for label, folder in _builds():
        for start in (0, 500, 1500):
            out.append(_case(f"predict/10000-from-{start}-{label}", "c-api", RESULT,
                             f"10,000 predictions from sample {start}, {label}: finite, status "
                             "UNRELIABLE (4), and the next measurements recover within 1 s",
                             body.format(folder=folder, start=start), timeout=240))
    out.append(_case("predict/status-bit-run", "c-api", RESULT,
                     "control: a C run whose samples are all invalid returns the bit UNRELIABLE", '''
                     run = long_run()
                     est = load("cartpole_nominal_ukf")
                     X = est.run(run.u[:100], run.y[:100], np.array([0, 0, 0.3, 0.0]),
                                 valid=np.zeros((100, 2), dtype=bool))
                     verdict(np.isfinite(X).all() and est.last_status & 4, f"status {est.last_status}")
                     '''))
    return out


def gap_cases() -> list[Case]:
    """learnest estimate on a run whose every y cell is empty over a long stretch."""
    body = '''
    lines = LONG.read_text().splitlines()
    head = lines[0].split(",")
    ys = [i for i, c in enumerate(head) if c.startswith("y_")]
    rows = [l.split(",") for l in lines[1:]]
    for r in rows[500:500 + {gap}]:
        for i in ys:
            r[i] = ""
    (CASE / "gap.csv").write_text("\\n".join([lines[0]] + [",".join(r) for r in rows]) + "\\n")
    step(cartpole_estimate(LIB / "{folder}", LONG, CASE / "clean.csv"))
    def check(out):
        run, est, clean = table(LONG), table(CASE / "e.csv"), table(CASE / "clean.csv")
        xs = [i for i, c in enumerate(head) if c.startswith("x_")]
        tail = slice(500 + {gap} + 500, None)
        e = np.median(np.abs(est[tail, 1:] - run[tail][:, xs]))
        e_clean = np.median(np.abs(clean[tail, 1:] - run[tail][:, xs]))
        said = "longest gap" in out
        return said and e <= 2 * e_clean + 1e-3, (f"median error from 1 s after the gap {{e:.3g}} "
                                                  f"(clean {{e_clean:.3g}}), gap named {{said}}")
    final(cartpole_estimate(LIB / "{folder}", CASE / "gap.csv", CASE / "e.csv"), check=check)
    '''
    out = []
    for label, folder in _builds():
        for gap in (1000, 4000, 10000):
            out.append(_case(f"gaps/estimate-{gap}-{label}", "c-api", RESULT,
                             f"estimate with every y empty for {gap} samples, {label}: exit 0, "
                             "back to the clean run's error 1 s after, the gap said",
                             body.format(folder=folder, gap=gap), timeout=300))
    return out


def lap_cases() -> list[Case]:
    """The run repeated: the state jumps ~45 rad at the wrap; the estimate must re-acquire it."""
    body = '''
    from learnest_codegen import get_system
    from learnest_codegen.simulation import simulate
    system = get_system("cartpole")
    run = simulate(system, seed=1, duration=10.0)
    n = len(run.y)
    U, Y, X = (np.concatenate([a] * 3) for a in (run.u, run.y, run.x))
    est = load("{folder}")
    Xh = est.run(U, Y, np.asarray(system.x0, float))
    half = n // 2
    mse = [float(np.mean((Xh[k * n + half:(k + 1) * n] - X[k * n + half:(k + 1) * n]) ** 2))
           for k in range(3)]
    verdict(max(mse[1:]) <= 2 * mse[0], f"second-half MSE per lap {{[round(m, 4) for m in mse]}}")
    '''
    return [_case(f"laps/wrap-{label}", "c-api", RESULT,
                  f"the seed-1 run three times in a row (a 45 rad wrap of the angle), {label}: "
                  "every lap within 2x of the first", body.format(folder=folder), timeout=240)
            for label, folder in _builds()]


def noise_cases() -> list[Case]:
    """set_noise / set_arrival on a running estimator: the same rule in every estimator."""
    head = '''
    est = load("{folder}")
    est.reset(np.array([0, 0, 0.3, 0.0]))
    '''
    bad = [("R-zero", "R=np.zeros((2, 2))", ("R", "positive definite")),
           ("R-1e-300", "R=1e-300 * np.eye(2)", ("R", "range")),
           ("R-nan", "R=np.full((2, 2), np.nan)", ("R",)),
           ("R-asymmetric", "R=np.array([[1e-4, 1e-5], [0.0, 1e-4]])", ("R", "symmetric")),
           ("R-shape", "R=np.eye(3)", ("R", "shape")),
           ("Q-negative", "Q=-np.eye(4)", ("Q",)),
           ("Q-1e250", "Q=1e250 * np.eye(4)", ("Q", "range"))]
    out = []
    for label, folder in _builds():
        for name, call, needles in bad:
            out.append(_case(f"noise/{name}-{label}", "boundaries", ERROR, f"set_noise({call}), {label}",
                             head.format(folder=folder), f"est.set_noise({call})", needles=needles))
        if label.startswith("mhe"):
            out.append(_case(f"noise/P_arrival-1e-300-{label}", "boundaries", ERROR,
                             f"set_noise(P_arrival=1e-300 I), {label} (an error of 14.7 before)",
                             head.format(folder=folder), "est.set_noise(P_arrival=1e-300 * np.eye(4))",
                             needles=("P_arrival", "range")))
    out += [
        _case("noise/R-zero-ukf-python", "data", ERROR, "the Python UKF: set_noise(R=0)", '''
              from learnest_codegen.pipeline import make_estimator
              est = make_estimator("nominal", "ukf", backend="python", system="cartpole")
              est.reset(np.array([0, 0, 0.3, 0.0]))
              est.set_noise(R=np.zeros((2, 2)))
              ''', needles=("R",)),
        _case("noise/P_arrival-ukf", "boundaries", ERROR, "set_noise(P_arrival=...) on a UKF", '''
              est = load("cartpole_nominal_ukf")
              est.reset(np.array([0, 0, 0.3, 0.0]))
              est.set_noise(P_arrival=np.eye(4))
              ''', needles=("P_arrival",)),
        _case("noise/c-set-arrival-1e-300", "c-api", ERROR,
              "C <prefix>_set_arrival(P = 1e-300 I) on mhe_gn", '''
              est = load("cartpole_nominal_mhe_gn_n20")
              est.reset(np.array([0, 0, 0.3, 0.0]))
              code = est._c["set_arrival"](est._handle, np.ascontiguousarray(1e-300 * np.eye(4)))
              if code < 0:
                  mark("ERROR", type="C", message=f"set_arrival returned {code}")
              verdict(False, f"accepted ({code})")
              '''),
        _case("noise/c-ukf-R-zero", "c-api", ERROR, "C <prefix>_set_noise(R = 0) on the UKF", '''
              est = load("cartpole_nominal_ukf")
              est.reset(np.array([0, 0, 0.3, 0.0]))
              code = est._c["set_noise"](est._handle, None, np.zeros((2, 2)).ctypes.data)
              if code < 0:
                  mark("ERROR", type="C", message=f"set_noise returned {code}")
              verdict(False, f"accepted ({code})")
              '''),
        _case("noise/valid-retune", "boundaries", RESULT,
              "control: set_noise(R=4 R) on a running mhe_rti keeps tracking", '''
              run = long_run()
              est = load("cartpole_nominal_mhe_rti_n20")
              clean = est.run(run.u[:2000], run.y[:2000], np.array([0, 0, 0.3, 0.0]))
              est.reset(np.array([0, 0, 0.3, 0.0]))
              X = []
              for k in range(2000):
                  if k == 500:
                      est.set_noise(R=4e-4 * np.eye(2))
                  X.append(est.step(run.u[max(k - 1, 0)], run.y[k]))
              e = np.abs(np.array(X) - run.x[:2000])[1000:].max()
              verdict(e < 5 * np.abs(clean - run.x[:2000])[1000:].max(), f"max error {e:.3g}")
              '''),
    ]
    return out


def mask_cases() -> list[Case]:
    """The validity mask: flags, shapes and samples without any output."""
    head = '''
    est = load("{folder}")
    est.reset(np.array([0, 0, 0.3, 0.0]))
    '''
    cases = []
    for label in ("ukf", "mhe_gn_float32"):
        folder = f"cartpole_nominal_{label}".replace("mhe_gn", "mhe_gn_n20")
        cases += [
            _case(f"mask/flag-2-{label}", "boundaries", ERROR, f"valid = [2, 1], {label}",
                  head.format(folder=folder), "est.step(np.zeros(1), np.zeros(2), valid=[2, 1])",
                  needles=("valid",)),
            _case(f"mask/shape-{label}", "boundaries", ERROR, f"valid of 3 flags, {label}",
                  head.format(folder=folder), "est.step(np.zeros(1), np.zeros(2), valid=[1, 1, 1])",
                  needles=("shape",)),
            _case(f"mask/nan-valid-{label}", "boundaries", ERROR, f"y = NaN marked valid, {label}",
                  head.format(folder=folder), "est.step(np.zeros(1), np.array([np.nan, 0.3]), valid=[1, 1])",
                  needles=("NaN",)),
            _case(f"mask/run-none-valid-{label}", "boundaries", RESULT,
                  f"control: run with every flag 0 (predictions), {label}: finite, bit 4", '''
                  run = long_run()
                  est = load("''' + folder + '''")
                  X = est.run(run.u[:300], run.y[:300], np.array([0, 0, 0.3, 0.0]),
                              valid=np.zeros((300, 2), dtype=bool))
                  verdict(np.isfinite(X).all() and est.last_status & 4, f"status {est.last_status}")
                  '''),
            _case(f"mask/garbage-masked-{label}", "boundaries", RESULT,
                  f"control: 1e300 in y where valid is 0 is never read, {label}", '''
                  run = long_run()
                  est = load("''' + folder + '''")
                  x0 = np.array([0, 0, 0.3, 0.0])
                  clean = est.run(run.u[:300], run.y[:300], x0)
                  Y = run.y[:300].copy()
                  valid = np.ones_like(Y, dtype=bool)
                  Y[100:120, 1], valid[100:120, 1] = 1e300, False
                  X = est.run(run.u[:300], Y, x0, valid=valid)
                  ref = run.y[:300].copy()
                  ref[100:120, 1] = np.nan
                  verdict(np.array_equal(X, est.run(run.u[:300], ref, x0)), "masked == NaN")
                  '''),
        ]
    cases.append(_case("mask/c-flag-byte-7", "c-api", ERROR, "C step with a valid byte of 7", '''
                       est = load("cartpole_nominal_mhe_rti_n20")
                       est.reset(np.array([0, 0, 0.3, 0.0]))
                       flags = np.array([7, 1], dtype=np.uint8)
                       code = est._c["step"](est._handle, np.zeros(1), np.zeros(2).ctypes.data,
                                             flags.ctypes.data)
                       if code < 0:
                           mark("ERROR", type="C", message=f"step returned {code}")
                       verdict(False, f"accepted ({code})")
                       '''))
    return cases


def start_cases() -> list[Case]:
    """--x0, --P0 and --horizon of learnest estimate."""
    est = 'final(cartpole_estimate(LIB / "{folder}", RUN, CASE / "e.csv", {args}))'
    bad = [("x0-1e300", "ukf", '"--x0", "1e300,0,0,0"', ("--x0",)),
           ("x0-1e300-mhe_gn", "mhe_gn", '"--x0", "1e300,0,0,0"', ("--x0",)),
           ("x0-nan", "ukf", '"--x0", "nan,0,0,0"', ("--x0",)),
           ("x0-count", "mhe_rti", '"--x0", "1,2"', ("--x0",)),
           ("x0-text", "ukf", '"--x0", "a,b,c,d"', ("--x0",)),
           ("P0-1e300", "mhe_gn", '"--P0", "1e300,1,1,1"', ("--P0",)),
           ("P0-negative", "ukf", '"--P0", "-1,1,1,1"', ("--P0",)),
           ("P0-asymmetric", "mhe_rti", '"--P0", "1,0.5,0,0,0,1,0,0,0,0,1,0,0,0,0,1"', ("--P0",)),
           ("P0-nan", "ukf", '"--P0", "nan,1,1,1"', ("--P0",)),
           ("P0-word", "ukf", '"--P0", "steady"', ("--P0",)),
           ("horizon-0", "mhe_gn", '"--horizon", "0"', ("horizon",)),
           ("horizon-negative", "mhe_gn", '"--horizon", "-3"', ("horizon",)),
           ("horizon-1e9", "mhe_rti", '"--horizon", "1000000000"', ("horizon",)),
           ("horizon-float", "mhe_rti", '"--horizon", "2.5"', ("horizon",)),
           ("horizon-ukf", "ukf", '"--horizon", "10"', ("horizon",)),
           ("horizon-vs-compiled", "mhe_gn", '"--horizon", "10"', ("horizon",))]
    cases = [_case(f"start/{name}", "boundaries", ERROR, f"estimate {args.replace(chr(34), '')} ({e})",
                   est.format(folder=f"cartpole_nominal_{e}" + ("" if e == "ukf" else "_n20"), args=args),
                   needles=needles)
             for name, e, args, needles in bad]
    cases.append(_case("start/x0-alone-mhe_gn", "boundaries", RESULT,
                       "--x0 3 initial stds off without --P0 (mhe_gn): as good as with --P0 initial "
                       "(4.3x the MSE and 26 good outputs gated out before)", '''
                       off = 3 * np.array([0.05, -0.1, 0.05, -0.1])
                       x0 = ",".join(str(v) for v in np.array([0, 0, 0.3, 0.0]) + off)
                       folder = LIB / "cartpole_nominal_mhe_gn_n20"
                       step(cartpole_estimate(folder, RUN, CASE / "p.csv", "--x0", x0, "--P0", "initial"))
                       def check(out):
                           run, a, b = table(RUN), table(CASE / "e.csv"), table(CASE / "p.csv")
                           mse = lambda e: float(np.mean((e[:, 1:] - run[:, 4:]) ** 2))
                           note = f"MSE {mse(a):.4g} vs {mse(b):.4g} with --P0 initial"
                           return mse(a) <= 1.1 * mse(b), note
                       final(cartpole_estimate(folder, RUN, CASE / "e.csv", "--x0", x0), check=check)
                       '''))
    return cases


def csv_stream_cases() -> list[Case]:
    """Run CSVs of the streams surface: empty columns, mixed rates, line endings, odd cells."""
    est = ('final(cartpole_estimate(LIB / "cartpole_nominal_ukf", CASE / "bad.csv", CASE / "e.csv"), '
           'check={check})')
    said = '''
    def said(out):
        return "{needle}" in out and np.isfinite(table(CASE / "e.csv")).all(), out.strip()[-120:]
    '''
    def blank(cols, every=1):
        return ('def blank(lines):\n'
                '    head = lines[0].split(",")\n'
                f'    idx = [head.index(c) for c in {cols!r}]\n'
                '    out = [lines[0]]\n'
                '    for k, l in enumerate(lines[1:]):\n'
                '        c = l.split(",")\n'
                f'        if k % {every} != 0 or {every} == 1:\n'
                '            for i in idx:\n'
                '                c[i] = ""\n'
                '        out.append(",".join(c))\n'
                '    return out\n'
                'edit_csv(RUN, CASE / "bad.csv", transform=blank)\n')
    cases = [
        _case("csv/empty-y-column", "data", RESULT,
              "a y column without a single sample: said (exit 0 with only '5000 missing' before)",
              blank(["y_alpha"]), '''
              code, out, err = run(cartpole_estimate(LIB / "cartpole_nominal_ukf", CASE / "bad.csv",
                                                     CASE / "e.csv"))
              if code != 0:
                  classify(code, out, err)
              verdict("y_alpha holds no sample" in err and np.isfinite(table(CASE / "e.csv")).all(),
                      err.strip()[-160:])
              ''', timeout=120),
        _case("csv/all-y-empty", "data", ERROR, "every y cell empty: nothing to estimate from",
              blank(["y_p", "y_alpha"]), 'final(cartpole_estimate(LIB / "cartpole_nominal_ukf", '
              'CASE / "bad.csv", CASE / "e.csv"))', needles=("no measurement",)),
        _case("csv/mixed-rate", "data", RESULT, "control: y_alpha every 4th sample only",
              said.format(needle="missing"), blank(["y_alpha"], every=4), est.format(check="said")),
        _case("csv/crlf", "data", RESULT, "control: CRLF line endings", said.format(needle="estimates"),
              '(CASE / "bad.csv").write_bytes(RUN.read_bytes().replace(b"\\n", b"\\r\\n"))',
              est.format(check="said")),
        _case("csv/trailing-blank-lines", "data", RESULT, "control: blank lines at the end",
              said.format(needle="estimates"),
              '(CASE / "bad.csv").write_text(RUN.read_text() + "\\n\\n\\n")', est.format(check="said")),
        _case("csv/extra-column", "data", RESULT, "control: an unknown column is ignored",
              said.format(needle="estimates"), '''
              edit_csv(RUN, CASE / "bad.csv", transform=lambda ls: [l + (",note" if i == 0 else ",x")
                                                                    for i, l in enumerate(ls)])
              ''', est.format(check="said")),
        _case("csv/empty-file", "data", ERROR, "a file of 0 bytes", '(CASE / "bad.csv").write_text("")',
              'final(cartpole_estimate(LIB / "cartpole_nominal_ukf", CASE / "bad.csv", CASE / "e.csv"))',
              needles=("empty",)),
        _case("csv/whitespace-only", "data", ERROR, "a file of blank lines",
              '(CASE / "bad.csv").write_text("\\n  \\n\\n")',
              'final(cartpole_estimate(LIB / "cartpole_nominal_ukf", CASE / "bad.csv", CASE / "e.csv"))',
              needles=("bad.csv",)),
        _case("csv/nan-u", "data", ERROR, "NaN in u_F (an input is what was applied)", '''
              edit_csv(RUN, CASE / "bad.csv", row=10, column="u_F", value="nan")
              final(cartpole_estimate(LIB / "cartpole_nominal_ukf", CASE / "bad.csv", CASE / "e.csv"))
              ''', needles=("u_F",)),
        _case("csv/empty-t", "data", ERROR, "an empty time cell", '''
              edit_csv(RUN, CASE / "bad.csv", row=10, column="t", value="")
              final(cartpole_estimate(LIB / "cartpole_nominal_ukf", CASE / "bad.csv", CASE / "e.csv"))
              ''', needles=("'t'",)),
        _case("csv/inf-y", "data", ERROR, "inf in y_p", '''
              edit_csv(RUN, CASE / "bad.csv", row=10, column="y_p", value="inf")
              final(cartpole_estimate(LIB / "cartpole_nominal_ukf", CASE / "bad.csv", CASE / "e.csv"))
              ''', needles=("y_p",)),
        _case("csv/ragged-late", "data", ERROR, "a short row near the end", '''
              cut = lambda ls: ls[:-3] + [ls[-3].rsplit(",", 1)[0]] + ls[-2:]
              edit_csv(RUN, CASE / "bad.csv", transform=cut)
              final(cartpole_estimate(LIB / "cartpole_nominal_ukf", CASE / "bad.csv", CASE / "e.csv"))
              ''', needles=("row",)),
        _case("csv/quoted-numbers", "data", RESULT, "control: every cell in double quotes",
              said.format(needle="estimates"), '''
              edit_csv(RUN, CASE / "bad.csv", transform=lambda ls: [",".join(f'"{c}"' for c in l.split(","))
                                                                    for l in ls])
              ''', est.format(check="said")),
    ]
    return cases


def train_cases() -> list[Case]:
    """Training data without measurements."""
    blank = '''
    lines = RUN.read_text().splitlines()
    head = lines[0].split(",")
    ys = [i for i, c in enumerate(head) if c.startswith("y_")]
    rows = [l.split(",") for l in lines[1:]]
    for r in rows:
        for i in ys:
            r[i] = ""
    (CASE / "noy.csv").write_text("\\n".join([lines[0]] + [",".join(r) for r in rows]) + "\\n")
    '''
    return [
        _case("train/no-measurement", "data", ERROR,
              "train on a run whose every y cell is empty (a model was written before)", blank,
              'final(["train", "--data", CASE / "noy.csv", "--out", CASE / "m", "--epochs", 2, '
              '"--refine", 0])', needles=("no measurement",), timeout=180),
        _case("train/full-state-no-y", "data", RESULT,
              "control: --full-state trains on x_ columns, without any y", blank, '''
              final(["train", "--data", CASE / "noy.csv", "--out", CASE / "m", "--epochs", 2,
                     "--refine", 0, "--full-state"],
                    check=lambda out: ((CASE / "m" / "model.json").is_file(), out.strip()[-80:]))
              ''', timeout=240),
    ]


def system_path_cases() -> list[Case]:
    """System files that moved, or whose path is not UTF-8."""
    return [
        _case("sysfile/moved-after-compile", "boundaries", ERROR,
              "a folder compiled from a system file that was moved since", '''
              path = system_file("my.py")
              must(["simulate", "--system", path, "--out", CASE / "run.csv"])
              must(["--nominal", "--system", path, "--estimator", "ukf", "--out", CASE / "gen"], compile=True)
              path.rename(CASE / "moved.py")
              final(["estimate", "--data", CASE / "run.csv", "--estimator", "ukf", "--compiled",
                     CASE / "gen" / "my_pendulum_nominal_ukf", "--out", CASE / "e.csv"])
              ''', needles=("my.py", "--system"), timeout=240),
        _case("sysfile/non-utf8-path", "boundaries", ERROR,
              "--system given a path with a Latin-1 byte in its name", '''
              good = system_file("good.py")
              bad = os.fsencode(str(CASE)) + b"/caf\\xe9.py"
              with open(bad, "wb") as fh:
                  fh.write(good.read_bytes())
              proc = subprocess.run([os.fsencode(sys.executable), b"-m", b"learnest_codegen.cli",
                                     b"simulate", b"--system", bad, b"--out",
                                     os.fsencode(str(CASE / "r.csv"))],
                                    capture_output=True)
              out, err = proc.stdout.decode(errors="replace"), proc.stderr.decode(errors="replace")
              if proc.returncode == 0:
                  verdict(True, "simulated")
              classify(proc.returncode, out, err)
              ''', needles=("caf",), timeout=120),
        _case("sysfile/missing", "boundaries", ERROR, "control: --system names a file that does not exist",
              'final(["simulate", "--system", CASE / "nope.py", "--out", CASE / "r.csv"])',
              needles=("nope.py",)),
    ]


def handle_thread_cases() -> list[Case]:
    """One handle stepped from two Python threads: never a crash (the binding locks it)."""
    body = '''
    import threading
    from learnest_codegen.errors import SolverError
    run = long_run()
    est = load("{folder}")
    errors = []
    for round_ in range({rounds}):
        est.reset(np.array([0, 0, 0.3, 0.0]))
        def work(offset):
            for k in range(200):
                try:
                    est.step(run.u[k + offset], run.y[k + offset])
                except SolverError as exc:  # a clear error is an answer too
                    errors.append(str(exc))
        before = len(errors)
        threads = [threading.Thread(target=work, args=(o,)) for o in (0, 3000)]
        for t in threads: t.start()
        for t in threads: t.join()
        if est.samples + len(errors) - before != 400 or not np.isfinite(est.x).all():
            verdict(False, f"round {{round_}}: {{est.samples}} samples taken and "
                    f"{{len(errors) - before}} errors of 400 steps")
    verdict(True, f"{{len(errors)}} clear errors, no crash")
    '''
    folders = [*(f for _, f in _builds()), "cartpole_nominal_mhe_n20"]
    return [_case(f"threads/one-handle-{f.replace('cartpole_nominal_', '')}", "boundaries", RESULT,
                  f"one {f.replace('cartpole_nominal_', '')} handle stepped from two threads, "
                  "10 rounds (segfaulted in 3 of 12 runs before)",
                  body.format(folder=f, rounds=3 if f.endswith("_mhe_n20") else 10), timeout=300)
            for f in folders]


def unlimited_input_cases() -> list[Case]:
    """Inputs far outside the range of a system that declares no input limits (ground robot)."""
    body = '''
    run = long_run("ground_robot")
    est = load("{folder}")
    x0 = np.asarray(run.x[0], float)
    clean, _ = step_through(est, run.u, run.y, x0)
    U = run.u.copy()
    U[{k} - 1] = {size}
    X, failed = step_through(est, U, run.y, x0)
    rms = np.sqrt(np.mean((clean - run.x) ** 2, axis=0))
    after = float((np.abs(X - clean) / rms)[{k} + 60:].max())
    verdict(after <= 1.0 and failed == 0 and est.input_rejections >= 1,
            f"deviation 60 samples after {{after:.3g}} clean RMS errors, {{failed}} failed steps, "
            f"{{est.input_rejections}} input(s) replaced")
    '''
    out = []
    for e in ("ukf", "mhe_gn", "mhe_rti"):
        horizon = "" if e == "ukf" else "_n20"
        for p in ("", "_float32"):
            for size in ("1e30", "1e6"):
                out.append(_case(f"inputs/ground-robot-u-{size}-{e}{p}", "c-api", RESULT,
                                 f"ground robot (no input limits), one u = {size}, {e}{p}: recovered "
                                 "within 60 samples",
                                 body.format(folder=f"ground_robot_nominal_{e}{horizon}{p}", k=800,
                                             size=size),
                                 timeout=240))
    return out


def all_cases() -> list[Case]:
    return [*system_cases(), *simulate_cases(), *option_cases(), *file_cases(), *library_cases(),
            *thread_cases(), *csv_cases(), *input_cases(), *prediction_cases(), *gap_cases(),
            *lap_cases(), *noise_cases(), *mask_cases(), *start_cases(), *csv_stream_cases(),
            *train_cases(), *system_path_cases(), *handle_thread_cases(), *unlimited_input_cases()]


# ---- running ---------------------------------------------------------------------------------

def _env(workdir: Path, casedir: Path, timeout: float) -> dict:
    env = dict(os.environ, HOSTILE_WORKDIR=str(workdir), HOSTILE_CASEDIR=str(casedir),
               HOSTILE_TIMEOUT=str(timeout), PYTHONPATH=str(ROOT), PYTHONWARNINGS="ignore",
               LEARNEST_TRACEBACK="")
    env.pop("LEARNEST_TRACEBACK")
    return env


def _execute(code: str, workdir: Path, casedir: Path, timeout: float) -> tuple[int | None, str, str]:
    casedir.mkdir(parents=True, exist_ok=True)
    script = casedir / "case.py"
    script.write_text(PRELUDE + "\n" + code)
    wrapper = casedir / "wrapper.py"
    wrapper.write_text(WRAPPER)
    proc = subprocess.Popen([sys.executable, str(wrapper), str(script)], cwd=casedir,
                            env=_env(workdir, casedir, timeout), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout + 60)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        return None, out, err
    return proc.returncode, out, err


def judge(case: Case, code: int | None, out: str, err: str) -> tuple[str, str]:
    """(outcome, detail) of a finished case process."""
    marks = [line for line in out.splitlines() if line.startswith("HOSTILE_")]
    if "HOSTILE_SETUP_FAILED" in err:
        return "battery error", err.strip().splitlines()[-1][-200:]
    if code is None:
        return "hang", f"no answer within {case.timeout + 60:.0f} s"
    if not marks:
        if code < 0:
            return "crash", f"killed by {signal.Signals(-code).name}"
        tail = (err.strip().splitlines() or ["(no output)"])[-1]
        return ("traceback" if "Traceback" in err else "unclear error"), tail[-200:]
    kind, _, payload = marks[-1].partition(" ")
    data = json.loads(payload or "{}")
    if kind == "HOSTILE_RESULT":
        return ("correct result" if data["ok"] else "wrong result"), data["note"]
    if kind == "HOSTILE_ACCEPTED":
        return ("correct result" if RESULT <= case.expect else "wrong result"), \
            "accepted: " + (data.get("output") or "no error")[-160:]
    if kind == "HOSTILE_ERROR":
        message = data["message"]
        low = message.lower()
        missing = [n for n in case.needles if n.lower() not in low]
        present = [a for a in case.avoid if a.lower() in low]
        detail = (f"[{data['type']}] " if data.get("type") not in ("cli", None) else "") + message
        if missing or present:
            return "unclear error", detail[:300]
        return "clear error", detail[:300]
    if kind == "HOSTILE_TRACEBACK":
        return "traceback", " ".join(data.get("tail", []))[-200:]
    if kind == "HOSTILE_HANG":
        return "hang", f"command killed after {case.timeout:.0f} s"
    if kind == "HOSTILE_SKIP":
        return "skipped", data.get("reason", "")
    if kind == "HOSTILE_CRASH":
        return "crash", f"command killed by {signal.Signals(data['signal']).name}"
    return "unclear error", data.get("output", "")[-200:]


def setup(workdir: Path) -> None:
    if (workdir / "lib" / "cartpole_true_mhe_n20" / "manifest.json").is_file() \
            and (workdir / "lib" / "ground_robot_nominal_mhe_rti_n20_float32" / "manifest.json").is_file() \
            and (workdir / "run.csv").is_file() and (workdir / "robot.csv").is_file():
        return
    code, out, err = _execute(SETUP, workdir, workdir / "setup", 1800)
    if code != 0 or "fixtures ready" not in out:
        raise SystemExit(f"fixtures failed:\n{out}\n{err}")


def run_case(case: Case, workdir: Path, baseline: dict | None = None) -> dict:
    """Run one case in its own folder and process; its result row."""
    start = time.perf_counter()
    casedir = workdir / "cases" / case.id.replace("/", "__")
    if casedir.exists():
        subprocess.run(["rm", "-rf", str(casedir)], check=True)
    code, out, err = _execute(case.code, workdir, casedir, case.timeout)
    outcome, detail = judge(case, code, out, err)
    row = {"id": case.id, "group": case.group, "owner": case.owner, "what": case.what,
           "expect": sorted(case.expect), "outcome": outcome,
           "passed": outcome in case.expect or outcome == "skipped",
           "detail": detail, "seconds": round(time.perf_counter() - start, 1)}
    if baseline and case.id in baseline:
        row["before"] = baseline[case.id]["outcome"]
    print(f"{'ok ' if row['passed'] else 'BAD'} {case.id:48s} {case.owner:8s} {outcome:15s} "
          f"{detail[:110]}", flush=True)
    return row


def run_cases(cases: list[Case], workdir: Path, baseline: dict | None = None,
              jobs: int = 1) -> list[dict]:
    """Every case, ``jobs`` at a time (each in its own process); rows in the cases' order."""
    if jobs <= 1:
        return [run_case(case, workdir, baseline) for case in cases]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=jobs) as pool:
        return list(pool.map(lambda case: run_case(case, workdir, baseline), cases))


def verdicts(results: list[dict]) -> dict[str, int]:
    """The counts the reliability benchmark reports: *silent* (a wrong result accepted, or an
    error expected and none given), *crash*, *hang*, *confusing* (an error that does not name
    its cause and remedy, or a traceback), and the cases as expected."""
    return {"cases": len(results), "as_expected": sum(r["passed"] for r in results),
            "silent": sum(r["outcome"] == "wrong result" for r in results),
            "crash": sum(r["outcome"] == "crash" for r in results),
            "hang": sum(r["outcome"] == "hang" for r in results),
            "confusing": sum(r["outcome"] in ("unclear error", "traceback") for r in results),
            "battery_errors": sum(r["outcome"] == "battery error" for r in results)}


def summary(results: list[dict]) -> dict:
    by_owner: dict = {}
    for r in results:
        o = by_owner.setdefault(r["owner"], {"cases": 0, "passed": 0})
        o["cases"] += 1
        o["passed"] += r["passed"]
    outcomes = {k: sum(r["outcome"] == k for r in results) for k in OUTCOMES}
    return {"cases": len(results), "passed": sum(r["passed"] for r in results),
            "outcomes": outcomes, "by_owner": by_owner}


def markdown(results: list[dict]) -> str:
    """The table of docs/reports/reliability.md: case, owner, expected, before (if known), outcome."""
    lines = ["| case | owner | expected | before | after | detail (after) |",
             "| --- | --- | --- | --- | --- | --- |"]
    for r in results:
        detail = r["detail"].replace("|", "/")[:120]
        lines.append(f"| {r['id']} | {r['owner']} | {' or '.join(r['expect'])} | {r.get('before', '-')} "
                     f"| {r['outcome']} | {detail} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("hostile_inputs.json"))
    parser.add_argument("--workdir", type=Path, default=None,
                        help="fixtures and per-case folders (default: a new temporary folder)")
    parser.add_argument("--only", default="", help="run the cases whose id contains this text")
    parser.add_argument("--baseline", type=Path, default=None, help="an earlier --out to compare with")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the table as Markdown")
    parser.add_argument("--jobs", type=int, default=1, help="cases run at a time")
    args = parser.parse_args(argv)
    workdir = (args.workdir or Path(tempfile.mkdtemp(prefix="hostile_"))).resolve()
    workdir.mkdir(parents=True, exist_ok=True)
    cases = [c for c in all_cases() if args.only in c.id]
    ids = [c.id for c in cases]
    assert len(ids) == len(set(ids)), "case ids must be unique"
    baseline = None
    if args.baseline:
        baseline = {r["id"]: r for r in json.loads(args.baseline.read_text())["results"]}
    print(f"workdir {workdir}; {len(cases)} cases", flush=True)
    start = time.perf_counter()
    setup(workdir)
    results = run_cases(cases, workdir, baseline, args.jobs)
    report = {"summary": summary(results), "verdicts": verdicts(results),
              "seconds": round(time.perf_counter() - start, 1),
              "commit": subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                                       capture_output=True, text=True).stdout.strip(),
              "results": results}
    args.out.write_text(json.dumps(report, indent=1))
    if args.markdown:
        args.markdown.write_text(markdown(results) + "\n")
    s = report["summary"]
    print(f"{s['passed']} of {s['cases']} cases as expected; outcomes {s['outcomes']}; "
          f"by owner {s['by_owner']}; {report['verdicts']}")
    return report


if __name__ == "__main__":
    main(sys.argv[1:])
