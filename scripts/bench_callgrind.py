"""Instructions and time per sample of every compiled estimator on the demo's trained model.

The model is the demo's trained KNODE cartpole (``bench_demo.model_dir()``: ``learnest demo``
with every option at its default); the run is the demo's test run, the whole of it (seed 1,
5000 samples). Each estimator (the UKF and the EKF; ``mhe_rti`` and ``mhe_gn`` at N = 20 and 50) in each
precision is generated as ``learnest-compile`` generates it (its defaults: the float32 UKF
with alpha 0.5, ``mhe_gn`` iterated to its tolerance), and a plain C main steps it over the run
from the folder's sources, built with the package's flags (``toolchain.CFLAGS``):

- **instructions per sample**: ``(I(T) - I(0)) / T`` under ``valgrind --tool=callgrind``, where
  ``I(T)`` counts the whole process stepping ``T`` samples (so start-up and ``init`` cancel);
  independent of the machine's load;
- **time per step**: the same binary run natively, each step timed with
  ``clock_gettime(CLOCK_MONOTONIC)``: the median and the mean over the run, with the load;
- **Gauss-Newton iterations** of ``mhe_gn`` per sample (``<prefix>_iterations``): the share of
  samples at each count, the mean and the maximum;
- **accuracy**: the MSE of each state against the truth, and the largest difference to the
  Ipopt MHE (``mhe``, the reference, at the same N; its time per step through the Python
  bindings beside it) and, in float32, to the same estimator in float64.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import figures
import numpy as np

MINUTES = 40
ORDER = 20
#: (estimator, horizon) of every row, in the order of the tables
HORIZONS = (20, 50)


def plan() -> list[tuple[str, int | None]]:
    """``(estimator, horizon)`` of every build: each estimator of the table generated in
    float32 (the embedded ones; the Ipopt MHE is timed apart), an MHE at each of
    :data:`HORIZONS`."""
    from learnest_codegen.compilation import FLOAT32_NAMES, MHE_NAMES

    return [(name, n) for name in FLOAT32_NAMES for n in (HORIZONS if name in MHE_NAMES else (None,))]


def _measured(data: dict) -> list[tuple[str, int | None]]:
    """``(estimator, horizon)`` of the rows the figures hold, in their order."""
    return list(dict.fromkeys((r["estimator"], r["horizon"]) for r in data["figures"]["rows"]))
PRECISIONS = ("float64", "float32")
BUILD = figures.ROOT / "build" / "bench" / "callgrind"

MAIN = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "@HEADER@"
typedef @PREFIX@_real real;
#include "run_data.h"
int main(int argc, char** argv) {
  static unsigned char mem[@WS@];
  real u[RUN_NU], y[RUN_NY], x[@NX@];
  @PREFIX@_t* h;
  int T = argc > 1 ? atoi(argv[1]) : RUN_T, timed = argc > 2, k, i;
  double sum = 0;
  struct timespec t0, t1;
  if (T > RUN_T || @PREFIX@_init_default(mem, sizeof mem, &h) != 0) return 1;
  for (k = 0; k < T; ++k) {
    for (i = 0; i < RUN_NU; ++i) u[i] = (real)run_u[k ? k - 1 : 0][i];
    for (i = 0; i < RUN_NY; ++i) y[i] = (real)run_y[k][i];
    if (timed) clock_gettime(CLOCK_MONOTONIC, &t0);
    if (@PREFIX@_step(h, u, y, 0) < 0) return 2;
    if (timed) clock_gettime(CLOCK_MONOTONIC, &t1);
    @PREFIX@_get_state(h, x);
    if (timed) {
      printf("%ld %d", (long)((t1.tv_sec - t0.tv_sec) * 1000000000L + (t1.tv_nsec - t0.tv_nsec)),
             @ITERATIONS@);
      for (i = 0; i < @NX@; ++i) printf(" %a", (double)x[i]);
      printf("\n");
    } else {
      for (i = 0; i < @NX@; ++i) sum += x[i];
    }
  }
  if (!timed) printf("%.17g\n", sum);
  return 0;
}
"""


def add_arguments(parser) -> None:
    parser.add_argument("--model", default=None,
                        help="a trained model directory (default: the demo's, running the demo first)")
    parser.add_argument("--samples", type=int, default=None,
                        help="the first SAMPLES of the run only (development; default: the whole run)")
    parser.add_argument("--jobs", type=int, default=2, help="callgrind runs at a time (default 2)")


def c_array(name: str, values: np.ndarray) -> str:
    rows = ",\n".join("{" + ",".join(float(v).hex() for v in row) + "}" for row in values)
    return f"static const double {name}[{values.shape[0]}][{values.shape[1]}] = {{\n{rows}}};\n"


def write_run(path: Path, U: np.ndarray, Y: np.ndarray) -> None:
    """``run_data.h``: the run's inputs and outputs as exact hex-float constants."""
    path.write_text(f"#define RUN_T {len(Y)}\n#define RUN_NU {U.shape[1]}\n#define RUN_NY {Y.shape[1]}\n"
                    + c_array("run_u", U) + c_array("run_y", Y))


def build(gen, run_header: Path, work: Path) -> Path:
    """The C main over the generated folder ``gen`` and the run, built with the package's flags."""
    from learnest_codegen.toolchain import CFLAGS

    header = (gen.directory / f"{gen.prefix}.h").read_text()
    size = re.search(rf"#define {gen.prefix.upper()}_WORKSPACE_BYTES \(?(\d+)", header).group(1)
    iterations = f"{gen.prefix}_iterations(h)" if f"{gen.prefix}_iterations(" in header else "1"
    source = MAIN
    for key, value in {"HEADER": f"{gen.prefix}.h", "PREFIX": gen.prefix, "WS": size,
                       "NX": str(gen.nx), "ITERATIONS": iterations}.items():
        source = source.replace(f"@{key}@", value)
    main_c = work / f"main_{gen.prefix}_N{gen.horizon or 0}_{gen.precision}.c"
    main_c.write_text(source)
    exe = main_c.with_suffix("")
    command = ["gcc", *CFLAGS, f"-I{gen.directory}", f"-I{run_header.parent}", str(main_c),
               *(str(gen.directory / s) for s in gen.sources), "-lm", "-o", str(exe)]
    proc = subprocess.run(command, capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"{' '.join(command)}\n{proc.stderr}")
    return exe


def instructions(exe: Path, T: int) -> int:
    """Instructions of the whole process stepping ``T`` samples, counted by callgrind."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "callgrind.out"
        subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", str(exe), str(T)],
                       check=True, capture_output=True)
        return int(re.search(r"^summary: (\d+)", out.read_text(), re.M).group(1))


def timed_run(exe: Path, T: int, nx: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ns per step, iterations per step, estimates (T, nx)) of one native run."""
    lines = subprocess.run([str(exe), str(T), "time"], check=True, capture_output=True,
                           text=True).stdout.splitlines()
    rows = [line.split() for line in lines]
    ns = np.array([int(r[0]) for r in rows])
    its = np.array([int(r[1]) for r in rows])
    X = np.array([[float.fromhex(v) for v in r[2:2 + nx]] for r in rows])
    return ns, its, X


def histogram(its: np.ndarray) -> dict:
    counts = np.bincount(its)
    return {"share": {str(i): float(n / len(its)) for i, n in enumerate(counts) if n},
            "mean": float(its.mean()), "max": int(its.max())}


def ipopt_reference(model, model_hash: str, run, T: int, horizon: int, root: Path) -> dict:
    """The Ipopt MHE at ``horizon`` through the Python bindings: estimates and time per step."""
    from learnest_codegen.compilation import compile_estimators
    from learnest_codegen.pipeline import load_estimator

    gen = compile_estimators(model, root / f"mhe_N{horizon}", model_hash=model_hash,
                             estimators=("mhe",), horizon=horizon)["mhe"]
    est = load_estimator(gen.directory)
    est.reset(model.system.x0)
    X, ns = np.empty((T, model.nx)), np.empty(T)
    for k in range(T):
        start = time.perf_counter_ns()
        X[k] = est.step(run.u[max(k - 1, 0)], run.y[k])
        ns[k] = time.perf_counter_ns() - start
    return {"X": X, "ns": ns}


def measure(args) -> tuple[dict, dict]:
    import bench_demo

    from learnest_codegen import get_system
    from learnest_codegen.compilation import compile_estimators, resolve_model
    from learnest_codegen.simulation import simulate

    system = get_system("cartpole")
    model_dir = Path(args.model) if args and args.model else bench_demo.model_dir()
    model, model_hash = resolve_model(system, str(model_dir))
    run = simulate(system, seed=1)
    T = min(args.samples or len(run.y), len(run.y)) if args else len(run.y)
    where = (f"the demo's trained KNODE cartpole ({model_dir.relative_to(figures.ROOT)}, "
             "written by python scripts/bench.py demo)" if not (args and args.model) else str(model_dir))
    gcc = subprocess.run(["gcc", "--version"], capture_output=True, text=True).stdout.splitlines()[0]
    valgrind = subprocess.run(["valgrind", "--version"], capture_output=True, text=True).stdout.strip()
    from learnest_codegen.toolchain import CFLAGS
    cond = figures.conditions(
        model=where, model_hash=model_hash,
        run=f"cartpole seed 1 (the demo's test run), samples 0-{T - 1} of {len(run.y)}"
            + ("" if T == len(run.y) else " (a partial run: development only)"),
        settings="each estimator as learnest-compile generates it (defaults)",
        compiler=f"{gcc} {' '.join(CFLAGS)}", counter=valgrind)
    shutil.rmtree(BUILD, ignore_errors=True)
    root = BUILD
    root.mkdir(parents=True)
    write_run(root / "run_data.h", run.u[:T], run.y[:T])
    gens = {}
    for name, horizon in plan():
        for precision in PRECISIONS:
            gens[name, horizon, precision] = compile_estimators(
                model, root / f"{name}_N{horizon or 0}_{precision}", model_hash=model_hash,
                estimators=(name,), precision=precision, horizon=horizon)[name]
    exes = {key: build(gen, root / "run_data.h", root) for key, gen in gens.items()}
    print(f"    counting instructions of {len(exes)} builds over {T} samples (callgrind)", flush=True)
    with ThreadPoolExecutor(max(1, args.jobs if args else 2)) as pool:
        counts = dict(zip(exes, pool.map(lambda exe: (instructions(exe, 0), instructions(exe, T)),
                                         exes.values())))
    load_before = os.getloadavg()[0]
    timed = {key: timed_run(exe, T, model.nx) for key, exe in exes.items()}
    references = {N: ipopt_reference(model, model_hash, run, T, N, root) for N in (20, 50)}
    load_after = os.getloadavg()[0]
    truth = run.x[:T]
    rows = []
    for (name, horizon, precision), gen in gens.items():
        ns, its, X = timed[name, horizon, precision]
        i0, i1 = counts[name, horizon, precision]
        row = {"estimator": name, "horizon": horizon, "precision": precision,
               "instructions_per_sample": (i1 - i0) / T, "instructions_init": i0,
               "ns_per_step_median": float(np.median(ns)), "ns_per_step_mean": float(ns.mean()),
               "ns_per_step_max": int(ns.max()),
               "mse": float(np.mean((X - truth) ** 2)),
               "mse_per_state": np.mean((X - truth) ** 2, axis=0).tolist(),
               "code_bytes": gen.code_bytes}
        if horizon is not None:  # an MHE: the Ipopt MHE at the same N is its reference
            X_ref = references[horizon]["X"]
            row["max_abs_difference_to_ipopt"] = float(np.abs(X - X_ref).max())
            row["mse_relative_to_ipopt"] = row["mse"] / float(np.mean((X_ref - truth) ** 2)) - 1
        if name == "mhe_gn":
            row["iterations"] = histogram(its)
        if precision == "float32":
            X64 = timed[name, horizon, "float64"][2]
            row["max_abs_difference_to_float64"] = float(np.abs(X - X64).max())
            row["mse_relative_to_float64"] = row["mse"] / float(np.mean((X64 - truth) ** 2)) - 1
        rows.append(row)
    ipopt = [{"estimator": "mhe", "horizon": N, "precision": "float64",
              "ns_per_step_median": float(np.median(r["ns"])), "ns_per_step_mean": float(r["ns"].mean()),
              "mse": float(np.mean((r["X"] - truth) ** 2)),
              "mse_per_state": np.mean((r["X"] - truth) ** 2, axis=0).tolist(),
              "timed": "through the Python bindings (ctypes), each step"} for N, r in references.items()]
    cond["timing"] = {"load_1min_before": round(load_before, 2), "load_1min_after": round(load_after, 2),
                      "clock": "CLOCK_MONOTONIC around each step of the native C main"}
    return {"samples": T, "states": list(system.state_names), "rows": rows, "ipopt": ipopt}, cond


# -- views -------------------------------------------------------------------------------------

def _row(data: dict, name: str, horizon, precision: str = "float64") -> dict:
    return next(r for r in data["figures"]["rows"]
                if (r["estimator"], r["horizon"], r["precision"]) == (name, horizon, precision))


def _label(r: dict) -> str:
    return f"`{r['estimator']}`" + (f" N = {r['horizon']}" if r["horizon"] else "")


def render_instructions(data: dict) -> str:
    """Instructions per sample and time per step, float64 and float32."""
    lines = ["| estimator | instructions per sample, float64 | float32 | µs per step (median / mean), "
             "float64 | float32 |", "|---|---:|---:|---:|---:|"]
    for name, horizon in _measured(data):
        a, b = (_row(data, name, horizon, p) for p in PRECISIONS)
        lines.append(f"| {_label(a)} | {a['instructions_per_sample']:,.0f} | "
                     f"{b['instructions_per_sample']:,.0f} | "
                     f"{a['ns_per_step_median'] / 1e3:.1f} / {a['ns_per_step_mean'] / 1e3:.1f} | "
                     f"{b['ns_per_step_median'] / 1e3:.1f} / {b['ns_per_step_mean'] / 1e3:.1f} |")
    for r in data["figures"]["ipopt"]:
        lines.append(f"| `mhe` (Ipopt) N = {r['horizon']} | – | – | {r['ns_per_step_median'] / 1e3:,.0f} / "
                     f"{r['ns_per_step_mean'] / 1e3:,.0f} (Python bindings) | – |")
    return "\n".join(lines) + "\n\n" + render_conditions(data)


def render_iterations(data: dict) -> str:
    """mhe_gn's Gauss-Newton iterations per sample: the share of samples at each count."""
    counts = sorted({int(k) for r in data["figures"]["rows"] if "iterations" in r
                     for k in r["iterations"]["share"]})
    low = [c for c in counts if c <= 3]
    lines = ["| `mhe_gn` | " + " | ".join(f"{c}" for c in low) + " | 4 or more | mean | max |",
             "|---|" + "---:|" * (len(low) + 3)]
    for horizon in (20, 50):
        for precision in PRECISIONS:
            it = _row(data, "mhe_gn", horizon, precision)["iterations"]
            share = {int(k): v for k, v in it["share"].items()}
            more = sum(v for c, v in share.items() if c > 3)
            cells = [f"{100 * share.get(c, 0.0):.1f} %" for c in low] + [f"{100 * more:.1f} %"]
            lines.append(f"| N = {horizon}, {precision} | " + " | ".join(cells)
                         + f" | {it['mean']:.3f} | {it['max']} |")
    return "\n".join(lines)


def render_accuracy(data: dict) -> str:
    """MSE per estimator and precision, against Ipopt and float64."""
    names = data["figures"]["states"]
    lines = ["| estimator | precision | MSE | " + " | ".join(f"MSE {s}" for s in names)
             + " | max difference to Ipopt | MSE change vs Ipopt | max difference to float64 | "
             "MSE change vs float64 |",
             "|---|---|---:|" + "---:|" * len(names) + "---:|---:|---:|---:|"]
    def rel(r, key):
        return "–" if r.get(key) is None else f"{r[key]:+.1e}"

    def num(r, key):
        return "–" if r.get(key) is None else f"{r[key]:.1e}"

    for r in data["figures"]["ipopt"]:
        lines.append(f"| `mhe` (Ipopt) N = {r['horizon']} | float64 | {r['mse']:.4e} | "
                     + " | ".join(f"{v:.3e}" for v in r["mse_per_state"]) + " | – | – | – | – |")
    for name, horizon in _measured(data):
        for precision in PRECISIONS:
            r = _row(data, name, horizon, precision)
            lines.append(f"| {_label(r)} | {precision} | {r['mse']:.4e} | "
                         + " | ".join(f"{v:.3e}" for v in r["mse_per_state"])
                         + f" | {num(r, 'max_abs_difference_to_ipopt')}"
                         f" | {rel(r, 'mse_relative_to_ipopt')}"
                         f" | {num(r, 'max_abs_difference_to_float64')}"
                         f" | {rel(r, 'mse_relative_to_float64')} |")
    return "\n".join(lines)


def render_summary(data: dict) -> str:
    """The short table of results.md: N = 20, float64."""
    lines = ["| estimator | instructions per sample | µs per step (median) | agreement with the Ipopt MHE |",
             "|---|---:|---:|---|"]
    for name, horizon in (e for e in _measured(data) if e[1] in (None, 20)):
        r = _row(data, name, horizon)
        agree = ("–" if horizon is None else
                 f"every estimate within {r['max_abs_difference_to_ipopt']:.1e}, MSE "
                 f"{r['mse_relative_to_ipopt']:+.1e} (relative)")
        lines.append(f"| {_label(r)} | {r['instructions_per_sample']:,.0f} | "
                     f"{r['ns_per_step_median'] / 1e3:.1f} | {agree} |")
    ref = next(r for r in data["figures"]["ipopt"] if r["horizon"] == 20)
    lines.append(f"| `mhe` (Ipopt) N = 20 | – | {ref['ns_per_step_median'] / 1e3:,.0f} | reference |")
    return "\n".join(lines) + "\n\n" + render_conditions(data)


def render_conditions(data: dict) -> str:
    c = data["conditions"]
    m, t = c["machine"], c.get("timing", {})
    return (f"Measured by `{data['command']}` on {c['date']}: {c['model']}; {c['run']}. "
            f"Built with {c['compiler']}; instructions counted by {c['counter']} (independent of the "
            f"load); times on {m['cpu']} ({m['cores']} cores) at a 1-minute load of "
            f"{t.get('load_1min_before', m['load_1min'])} before and {t.get('load_1min_after', '?')} "
            "after the timed runs.")


if __name__ == "__main__":
    import sys

    import bench

    sys.exit(bench.main(["callgrind", *sys.argv[1:]]))
