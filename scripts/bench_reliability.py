"""Reliability of the compiled estimators: lost tracks, gaps, predictions, threads, hostile inputs.

Every part runs the nominal cartpole estimators as users build them (``learnest-compile
--nominal``, default settings and gate) in both precisions: ``ukf``, ``mhe_gn`` and ``mhe_rti``,
and the Ipopt ``mhe`` (float64 only; in the soak with ``--ipopt-soak-steps``, about 2.5 ms a
step), on simulated cartpole runs of seed 1 with the truth. The parts (``--parts=soak,gaps,...``;
the default runs all but ``hostile`` and ``outliers``, about 20 minutes on 2 idle cores;
``python scripts/bench.py reliability --parts=hostile`` runs the battery):

- ``soak``: the 5,000-sample run looped lap after lap on one handle, by the C ``<prefix>_run``
  (a failed step is counted and the loop goes on from the next sample), ``--soak-steps`` steps
  per build (1e6). At each wrap the state jumps back to the start (the pole angle by ~45 rad):
  the estimator must re-acquire it every lap. Per lap: failed steps, the MSE over the lap's
  second half (after the re-acquisition) against the first lap's, the MSE over the whole lap,
  and the samples from the wrap until the estimate stays within the first lap's band
  (``|e| <= |e_first| + rms_first`` per state) for the rest of the lap.
- ``gaps``: a 16,000-sample run whose every output is missing from sample 500 for 500 to
  10,000 samples, gate on: the samples from the first valid output until the estimate stays in
  the clean run's band (the same run without the gap, ``|e| <= |e_clean| + rms_clean``) for the
  rest of the run; failed steps.
- ``predictions``: 10,000 ``predict`` calls from several samples of that run, then the
  measurements again: every prediction finite, the status (UNRELIABLE, bit 4) at the end of
  them, the first measured step's status, and the samples until the estimate is back in the
  clean band.
- ``threads``: one handle stepped from two Python threads at once (200 steps each), 100 runs per
  build, in child processes so that a crash is counted: crashes, clear errors, runs.
- ``csv_memory``: the peak resident memory (``VmHWM``) of a fresh process that imports the
  package and reads a 1e6-row run CSV (``data.read_run``; the seed-1 run tiled, truth included).
- ``fuzz``: ``scripts/fuzz_c_api.py``, seeded plans of adversarial raw C calls in child
  processes, ``--fuzz-calls`` per target (10,000; the Ipopt MHE a tenth), the cartpole and
  ground-robot estimators in both precisions: crashes, hangs, success codes with non-finite
  outputs, failed calls that changed the estimate.
- ``hostile``: ``scripts/hostile_inputs.py`` (every case in its own process): silent, crash,
  hang and confusing counts, and the cases not as expected (an hour or more on 2 cores).
- ``outliers``: ``scripts/bench_outlier_recovery.py``: bursts of garbage in ``y`` and in ``u``
  (both systems, Python and C in both precisions): samples to recover and the deviation after.

A part not run keeps its figures from the last run that measured it (each part records its
own commit, date and load). Times are not what this benchmark measures.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import figures
import numpy as np

from learnest_codegen.compilation import FLOAT32_NAMES

MINUTES = 20
ORDER = 60
PARTS = ("soak", "gaps", "predictions", "threads", "csv_memory", "fuzz", "hostile", "outliers")
DEFAULT_PARTS = ("soak", "gaps", "predictions", "threads", "csv_memory", "fuzz")


def build_pairs() -> tuple[tuple[str, str], ...]:
    """``(estimator, precision)`` of every estimator the table generates in both precisions (the
    Ipopt MHE, float64 only, joins with ``--ipopt``)."""
    return tuple((name, p) for name in FLOAT32_NAMES for p in ("float64", "float32"))


LAP = 5000
LONG = 16_000
GAP_START = 500
GAPS = (500, 1000, 2000, 5000, 10_000)
PREDICTION_STARTS = (0, 500, 1500, 3000, 5000)
PREDICTIONS = 10_000
SETTLE = 500  # 1 s of cartpole samples
OUT = figures.ROOT / "build" / "bench" / "reliability"


def add_arguments(parser) -> None:
    parser.add_argument("--parts", type=_parts, default=list(DEFAULT_PARTS),
                        help=f"comma-separated, e.g. --parts=soak,hostile (of {', '.join(PARTS)})")
    parser.add_argument("--soak-steps", type=int, default=1_000_000, help="per build")
    parser.add_argument("--ipopt-soak-steps", type=int, default=0,
                        help="steps of the Ipopt MHE's soak (0: none; it takes ~2 ms a step)")
    parser.add_argument("--thread-runs", type=int, default=100, help="two-thread runs per build")
    parser.add_argument("--csv-rows", type=int, default=1_000_000)
    parser.add_argument("--hostile-jobs", type=int, default=2, help="hostile cases run at a time")
    parser.add_argument("--fuzz-calls", type=int, default=10_000, help="per target")


def _parts(text: str) -> list[str]:
    parts = [p for p in text.split(",") if p]
    unknown = [p for p in parts if p not in PARTS]
    if unknown or not parts:
        raise ValueError(f"unknown part(s) {unknown}; choose from {', '.join(PARTS)}")
    return parts


# ---- fixtures ----------------------------------------------------------------------------------

def cartpole():
    from learnest_codegen import get_system
    return get_system("cartpole")


def builds(with_ipopt: bool = False, lib: Path = OUT / "lib") -> dict[str, Path]:
    """The nominal cartpole estimators, compiled once into ``lib``."""
    from learnest_codegen.compilation import compile_estimators, estimator_dir
    from learnest_codegen.export import prior_model

    model = prior_model(cartpole())
    for precision in ("float64", "float32"):
        chosen = tuple(e for e, p in build_pairs() if p == precision) + (
            ("mhe",) if with_ipopt and precision == "float64" else ())
        compile_estimators(model, lib, model_hash="nominal", estimators=chosen, precision=precision)
    names = {f"{e}_{p}": estimator_dir(lib, model, e, p) for e, p in build_pairs()}
    if with_ipopt:
        names["mhe_float64"] = estimator_dir(lib, model, "mhe", "float64")
    return names


def simulated(samples: int):
    from learnest_codegen.simulation import simulate
    system = cartpole()
    return simulate(system, seed=1, duration=samples * system.dt)


def load(directory: Path):
    from learnest_codegen.pipeline import load_estimator
    return load_estimator(directory)


# ---- driving a handle --------------------------------------------------------------------------

class Driver:
    """One handle driven by the C ``<prefix>_run`` from Python's reset: sample k of a call uses
    ``U[max(k - 1, 0)]``; a failed step keeps the previous estimate, is counted by its code, and
    the next call starts at the next sample."""

    def __init__(self, directory: Path, x0: np.ndarray):
        self.est = load(directory)
        self.est.reset(x0)
        self.failures: dict[int, int] = {}
        self.first_failure: int | None = None
        self.done = 0

    def run(self, U: np.ndarray, Y: np.ndarray, valid: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        est = self.est
        U, Y = est.real_array(U), est.real_array(np.where(np.isnan(Y), 0.0, Y))
        flags = None if valid is None else np.ascontiguousarray(valid, dtype=np.uint8)
        X = np.full((len(Y), est.nx), np.nan, dtype=est.dtype)
        k, failed, status = 0, 0, 0
        while k < len(Y):
            code = est._c["run"](est._handle, len(Y) - k, np.ascontiguousarray(U[k:]),
                                 np.ascontiguousarray(Y[k:]),
                                 None if flags is None else flags[k:].ctypes.data, X[k:])
            if code >= 0:
                status |= code
                break
            k += int(np.argmax(np.isnan(X[k:, 0])))
            self.failures[int(code)] = self.failures.get(int(code), 0) + 1
            if self.first_failure is None:
                self.first_failure = self.done + k
            X[k] = X[k - 1] if k else est.x
            failed, k = failed + 1, k + 1
        self.done += len(Y)
        return X.astype(float), failed


def band_exit(X: np.ndarray, X_clean: np.ndarray, truth: np.ndarray, start: int) -> int:
    """Samples from ``start`` until the estimate stays, to the end, in the clean band
    ``|e| <= |e_clean| + rms_clean`` per state (rms over the samples from ``start`` on)."""
    e, ec = np.abs(X - truth)[start:], np.abs(X_clean - truth)[start:]
    rms = np.sqrt(np.mean(ec ** 2, axis=0))
    out = np.flatnonzero(np.any(~(e <= ec + rms), axis=1))
    return 0 if not len(out) else int(out[-1]) + 1


def measured() -> dict:
    """When and where a part was measured (each part keeps its own)."""
    cond = figures.conditions()
    return {"commit": cond["commit"], "date": cond["date"], "load_1min": cond["machine"]["load_1min"]}


# ---- parts -------------------------------------------------------------------------------------

def soak(folders: dict[str, Path], steps: int, ipopt_steps: int) -> dict:
    system = cartpole()
    run = simulated(LAP)
    U, Y, X = np.ascontiguousarray(run.u), np.ascontiguousarray(run.y), run.x
    x0 = np.asarray(system.x0, float)
    half = LAP // 2
    out = {}
    for name, directory in folders.items():
        budget = ipopt_steps if name.startswith("mhe_float64") else steps
        if budget <= 0:
            continue
        driver, laps = Driver(directory, x0), -(-budget // LAP)
        first, rows = None, []
        for lap in range(laps):
            Xh, failed = driver.run(U, Y)
            err = Xh - X
            if first is None:
                first = Xh
            back = band_exit(Xh, first, X, 0) if lap else 0
            rows.append({"failed": failed, "mse_second_half": float(np.mean(err[half:] ** 2)),
                         "mse_lap": float(np.mean(err ** 2)), "reacquired_after": back})
        ref = rows[0]["mse_second_half"]
        later = rows[1:]
        out[name] = {
            "steps": laps * LAP, "laps": laps, "failed_steps": sum(r["failed"] for r in rows),
            "failed_codes": {str(k): v for k, v in sorted(driver.failures.items())},
            "first_failed_step": driver.first_failure,
            "failed_steps_last_lap": rows[-1]["failed"],
            "mse_second_half_first_lap": ref,
            "mse_second_half_max_later": max(r["mse_second_half"] for r in later),
            "worst_ratio_to_first": max(r["mse_second_half"] for r in later) / ref,
            "laps_within_2x": sum(r["mse_second_half"] <= 2 * ref for r in later),
            "mse_lap_first": rows[0]["mse_lap"],
            "mse_lap_median_later": float(np.median([r["mse_lap"] for r in later])),
            "mse_lap_max_later": max(r["mse_lap"] for r in later),
            "reacquired_after_max": max(r["reacquired_after"] for r in later),
            "reacquired_after_median": float(np.median([r["reacquired_after"] for r in later])),
            "first_laps": rows[:4],
        }
        print(f"    soak {name}: {out[name]['steps']} steps, {out[name]['failed_steps']} failed, worst "
              f"lap {out[name]['worst_ratio_to_first']:.3g}x, re-acquired within "
              f"{out[name]['reacquired_after_max']} samples", flush=True)
    return {"lap_samples": LAP, "builds": out, "measured": measured()}


def gaps(folders: dict[str, Path], lengths: tuple[int, ...] = GAPS) -> dict:
    system = cartpole()
    run = simulated(LONG)
    x0 = np.asarray(system.x0, float)
    out = {}
    for name, directory in folders.items():
        clean, _ = Driver(directory, x0).run(run.u, run.y)
        rows = {}
        for gap in lengths:
            valid = np.ones_like(run.y, dtype=bool)
            valid[GAP_START:GAP_START + gap] = False
            Xg, failed = Driver(directory, x0).run(run.u, run.y, valid)
            first = GAP_START + gap
            back = band_exit(Xg, clean, run.x, first)
            rows[str(gap)] = {"back_in_band_after": back, "seconds": back * system.dt,
                              "failed_steps": failed, "within_1s": back <= SETTLE and failed == 0}
        out[name] = rows
        print(f"    gaps {name}: " + ", ".join(f"{g}: {r['back_in_band_after']}" for g, r in rows.items()),
              flush=True)
    return {"gap_start": GAP_START, "run_samples": LONG, "builds": out, "measured": measured()}


def predictions(folders: dict[str, Path], starts: tuple[int, ...] = PREDICTION_STARTS) -> dict:
    from learnest_codegen.errors import SolverError

    system = cartpole()
    run = simulated(LONG)
    x0 = np.asarray(system.x0, float)
    out = {}
    for name, directory in folders.items():
        clean, _ = Driver(directory, x0).run(run.u, run.y)
        rows = {}
        for start in starts:
            est = load(directory)
            est.reset(x0)
            X = np.empty((LONG, est.nx))
            status, failed, flagged_from = np.zeros(LONG, dtype=int), 0, None
            for k in range(LONG):
                u = run.u[max(k - 1, 0)]
                try:
                    X[k] = est.predict(u) if start <= k < start + PREDICTIONS else est.step(u, run.y[k])
                    status[k] = est.last_status
                except SolverError:
                    X[k], status[k], failed = est.x, -1, failed + 1
                if flagged_from is None and k >= start and status[k] > 0 and status[k] & 4:
                    flagged_from = k - start
            pred = X[start:start + PREDICTIONS]
            first = start + PREDICTIONS
            back = band_exit(X, clean, run.x, first)
            rows[str(start)] = {
                "finite": bool(np.isfinite(pred).all()), "largest_abs_state": float(np.abs(pred).max()),
                "failed_steps": failed, "unreliable_from_prediction": flagged_from,
                "unreliable_at_end": bool(status[first - 1] > 0 and status[first - 1] & 4),
                "first_measured_status": int(status[first]),
                "back_in_band_after": back, "recovered_within_1s": back <= SETTLE,
            }
        out[name] = rows
        print(f"    predictions {name}: " + ", ".join(
            f"{s}: {r['back_in_band_after']}{'' if r['finite'] else ' NONFINITE'}" for s, r in rows.items()),
            flush=True)
    return {"predictions": PREDICTIONS, "starts": list(starts), "builds": out,
            "measured": measured()}


THREAD_CHILD = r'''
import json, sys, threading
import numpy as np
from learnest_codegen.errors import LearnestError
from learnest_codegen.pipeline import load_estimator
from learnest_codegen.simulation import simulate
from learnest_codegen import get_system
system = get_system("cartpole")
run = simulate(system, seed=1, duration=1000 * system.dt)
est = load_estimator(sys.argv[1])
for r in range(int(sys.argv[2]), int(sys.argv[3])):
    est.reset(np.asarray(system.x0, float))
    errors = []
    def work(offset):
        for k in range(200):
            try:
                est.step(run.u[k + offset], run.y[k + offset])
            except LearnestError as exc:
                errors.append(str(exc))
    threads = [threading.Thread(target=work, args=(o,)) for o in (0, 500)]
    for t in threads: t.start()
    for t in threads: t.join()
    print(json.dumps({"run": r, "errors": len(errors), "samples": est.samples,
                      "finite": bool(np.isfinite(est.x).all())}), flush=True)
'''


def threads(folders: dict[str, Path], runs: int) -> dict:
    out = {}
    env = dict(os.environ, PYTHONPATH=str(figures.ROOT))
    for name, directory in folders.items():
        n = runs
        done, crashes, errors, complete, finite, signals = 0, 0, 0, 0, 0, []
        while done < n:
            proc = subprocess.run([sys.executable, "-c", THREAD_CHILD, str(directory), str(done), str(n)],
                                  capture_output=True, text=True, env=env, timeout=1800)
            rows = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
            done += len(rows)
            errors += sum(r["errors"] > 0 for r in rows)
            complete += sum(r["samples"] + r["errors"] == 400 for r in rows)
            finite += sum(r["finite"] for r in rows)
            if proc.returncode != 0:
                crashes += 1
                signals.append(proc.returncode)
                done += 1  # the run that crashed
        out[name] = {"runs": n, "crashes": crashes, "runs_with_clear_errors": errors,
                     "runs_every_step_accounted": complete, "runs_finite": finite,
                     "exit_codes_of_crashes": signals}
        print(f"    threads {name}: {n} runs, {crashes} crashes, {errors} with clear errors", flush=True)
    return {"steps_per_thread": 200, "builds": out, "measured": measured()}


MEMORY_CHILD = r'''
import json, sys, time
from pathlib import Path
from learnest_codegen import get_system
from learnest_codegen.data import read_run

def status_mb(key):  # this process image's own figures (ru_maxrss would carry the parent's)
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(key)

system = get_system("cartpole")
before = status_mb("VmRSS")
start = time.perf_counter()
run = read_run(sys.argv[1], system)
seconds = time.perf_counter() - start
numbers = sum(a.nbytes for a in (run.t, run.u, run.y, run.x))
print(json.dumps({"rows": len(run), "peak_rss_mb": status_mb("VmHWM"), "rss_before_read_mb": before,
                  "numbers_mb": numbers / 2**20, "seconds": seconds}))
'''


def csv_memory(rows: int) -> dict:
    from learnest_codegen.data import Run, write_run

    system = cartpole()
    path = OUT / f"run_{rows}.csv"
    if not path.exists():
        base = simulated(LAP)
        reps = -(-rows // LAP)
        tile = lambda a: np.tile(a, (reps, 1))[:rows]  # noqa: E731
        run = Run(np.arange(rows) * system.dt, tile(base.u), tile(base.y), tile(base.x), system.name)
        OUT.mkdir(parents=True, exist_ok=True)
        write_run(run, system, path)
    env = dict(os.environ, PYTHONPATH=str(figures.ROOT))
    proc = subprocess.run([sys.executable, "-c", MEMORY_CHILD, str(path)], capture_output=True, text=True,
                          env=env, check=True)
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    result["file_mb"] = path.stat().st_size / 2**20
    print(f"    csv: {result['rows']} rows, peak RSS {result['peak_rss_mb']:.0f} MB", flush=True)
    return {**result, "measured": measured()}


def hostile(jobs: int) -> dict:
    out = OUT / "hostile.json"
    env = dict(os.environ, PYTHONPATH=str(figures.ROOT))
    subprocess.run([sys.executable, str(figures.ROOT / "scripts" / "hostile_inputs.py"), "--out", str(out),
                    "--workdir", str(OUT / "hostile"), "--jobs", str(jobs)], check=True, env=env)
    report = json.loads(out.read_text())
    off = [{"id": r["id"], "expected": " or ".join(r["expect"]), "outcome": r["outcome"],
            "detail": r["detail"][:200]} for r in report["results"] if not r["passed"]]
    groups: dict[str, int] = {}
    for r in report["results"]:
        groups[r["group"]] = groups.get(r["group"], 0) + 1
    return {**report["verdicts"], "groups": groups, "not_as_expected": off, "measured": measured()}


def fuzz(calls: int) -> dict:
    sys.path.insert(0, str(figures.ROOT / "scripts"))
    import fuzz_c_api

    result = fuzz_c_api.main(["--calls", str(calls), "--ipopt-calls", str(max(1, calls // 10)),
                              "--build-dir", str(OUT / "fuzz"), "--out", str(OUT / "fuzz.json")])
    keep = ("calls", "crashes", "hangs", "nonfinite_ok", "changed_on_error", "handle_not_null_on_error",
            "accepted_bad_memory", "covariance_not_psd_ok")
    targets = {r["target"]: {**{k: r.get(k, 0) for k in keep}, "step_codes": r["codes"].get("step", {})}
               for r in result["targets"]}
    totals = {k: sum(t[k] for t in targets.values()) for k in keep}
    return {"seed": result["seed"], "calls_per_target": calls, "targets": targets, "totals": totals,
            "measured": measured()}


def outliers() -> dict:
    sys.path.insert(0, str(figures.ROOT / "scripts"))
    import bench_outlier_recovery

    result = bench_outlier_recovery.main(["--build-dir", str(OUT / "outliers"),
                                          "--out", str(OUT / "outliers.json")])
    return {"tables": [bench_outlier_recovery.markdown(t) for t in result["tables"]],
            "measured": measured()}


def measure(args) -> tuple[dict, dict]:
    cond = figures.conditions(
        model="the nominal (prior) cartpole model, estimators compiled with their default settings "
              "and gate (ukf, mhe_gn, mhe_rti in float64 and float32)",
        run="simulated cartpole runs of seed 1 (5,000 samples looped for the soak, 16,000 for gaps and "
            "predictions), truth included",
        settings=f"parts {' '.join(args.parts)}; soak {args.soak_steps} steps per build")
    previous = {}
    path = figures.FIGURES / "reliability.json"
    if path.exists():
        previous = json.loads(path.read_text()).get("figures", {})
    result = dict(previous)
    ipopt = args.ipopt_soak_steps > 0 or bool({"gaps", "predictions", "threads"} & set(args.parts))
    folders = builds(with_ipopt=ipopt)
    start = time.perf_counter()
    for part in args.parts:
        print(f"  {part}", flush=True)
        if part == "soak":
            result["soak"] = soak(folders, args.soak_steps, args.ipopt_soak_steps)
        elif part == "gaps":
            result["gaps"] = gaps(folders)
        elif part == "predictions":
            result["predictions"] = predictions(folders)
        elif part == "threads":
            result["threads"] = threads(folders, args.thread_runs)
        elif part == "csv_memory":
            result["csv_memory"] = csv_memory(args.csv_rows)
        elif part == "hostile":
            result["hostile"] = hostile(args.hostile_jobs)
        elif part == "fuzz":
            result["fuzz"] = fuzz(args.fuzz_calls)
        elif part == "outliers":
            result["outliers"] = outliers()
        result.setdefault("part_seconds", {})[part] = round(time.perf_counter() - start, 1)
        start = time.perf_counter()
    result["max_rss_mb_of_the_benchmark"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return result, cond


# ---- views -------------------------------------------------------------------------------------

def _label(name: str) -> str:
    """``mhe_gn_float32`` -> ``mhe_gn float32``."""
    estimator, precision = name.rsplit("_", 1)
    return f"{estimator} {precision}"


def _when(part: dict) -> str:
    m = part.get("measured", {})
    return f"revision {m.get('commit', '?')}, {m.get('date', '?')}, load {m.get('load_1min', '?')}"


def render_soak(data: dict) -> str:
    s = data["figures"]["soak"]
    lines = ["| build | steps | failed steps | lap MSE, 2nd half: first / worst later | worst / first "
             "| laps within 2x | lap MSE, whole lap: first / median later | re-acquired after (samples) |",
             "|---|---:|---:|---|---:|---|---|---:|"]
    for name, r in s["builds"].items():
        lines.append(f"| {_label(name)} | {r['steps']:,} | {r['failed_steps']} | "
                     f"{r['mse_second_half_first_lap']:.4g} / {r['mse_second_half_max_later']:.4g} | "
                     f"{r['worst_ratio_to_first']:.3f} | {r['laps_within_2x']} of {r['laps'] - 1} | "
                     f"{r['mse_lap_first']:.4g} / {r['mse_lap_median_later']:.4g} | "
                     f"{r['reacquired_after_median']:.0f} (max {r['reacquired_after_max']}) |")
    lines.append(f"\nLaps of {s['lap_samples']:,} samples; {_when(s)}.")
    return "\n".join(lines)


def render_gaps(data: dict) -> str:
    g = data["figures"]["gaps"]
    gaps_ = list(next(iter(g["builds"].values())))
    lines = ["| build | " + " | ".join(f"gap {int(x):,}" for x in gaps_) + " |",
             "|---|" + "---:|" * len(gaps_)]
    for name, rows in g["builds"].items():
        cells = [f"{r['back_in_band_after']}"
                 + (f" ({r['failed_steps']} failed)" if r["failed_steps"] else "") for r in rows.values()]
        lines.append(f"| {_label(name)} | " + " | ".join(cells) + " |")
    lines.append(f"\nSamples (at 500 Hz) from the first valid output after the gap until the estimate "
                 f"stays in the clean band; gaps from sample {g['gap_start']} of a "
                 f"{g['run_samples']:,}-sample run; {_when(g)}.")
    return "\n".join(lines)


def render_predictions(data: dict) -> str:
    p = data["figures"]["predictions"]
    lines = ["| build | from sample | finite | failed | UNRELIABLE from prediction | at the end | first "
             "measured step's status | back in band after |", "|---|---:|---|---:|---:|---|---:|---:|"]
    for name, rows in p["builds"].items():
        for start, r in rows.items():
            lines.append(f"| {_label(name)} | {start} | {'yes' if r['finite'] else 'NO'} | "
                         f"{r['failed_steps']} | {r['unreliable_from_prediction']} | "
                         f"{'yes' if r['unreliable_at_end'] else 'no'} | {r['first_measured_status']} | "
                         f"{r['back_in_band_after']} |")
    lines.append(f"\n{p['predictions']:,} predictions per row; {_when(p)}.")
    return "\n".join(lines)


def render_threads(data: dict) -> str:
    t = data["figures"]["threads"]
    lines = ["| build | runs | crashes | runs with a clear error | every step accounted |",
             "|---|---:|---:|---:|---:|"]
    for name, r in t["builds"].items():
        lines.append(f"| {_label(name)} | {r['runs']} | {r['crashes']} | "
                     f"{r['runs_with_clear_errors']} | {r['runs_every_step_accounted']} |")
    lines.append(f"\nTwo threads of {t['steps_per_thread']} steps each on one handle per run; {_when(t)}.")
    return "\n".join(lines)


def render_hostile(data: dict) -> str:
    h = data["figures"].get("hostile")
    if not h:
        return "(not measured yet: python scripts/bench.py reliability --parts hostile)"
    lines = ["| cases | as expected | silent | crash | hang | confusing |", "|---:|---:|---:|---:|---:|---:|",
             f"| {h['cases']} | {h['as_expected']} | {h['silent']} | {h['crash']} | {h['hang']} | "
             f"{h['confusing']} |"]
    if h["not_as_expected"]:
        lines += ["", "| case | expected | outcome | detail |", "|---|---|---|---|"]
        lines += [f"| `{r['id']}` | {r['expected']} | {r['outcome']} | "
                  f"{r['detail'][:140].replace('|', '/')} |" for r in h["not_as_expected"]]
    lines.append(f"\n{_when(h)}.")
    return "\n".join(lines)


def render_memory(data: dict) -> str:
    m = data["figures"]["csv_memory"]
    return (f"| rows | file | numbers read | process RSS before the read | peak RSS | seconds |\n"
            f"|---:|---:|---:|---:|---:|---:|\n"
            f"| {m['rows']:,} | {m['file_mb']:.0f} MB | {m['numbers_mb']:.0f} MB | "
            f"{m['rss_before_read_mb']:.0f} MB | {m['peak_rss_mb']:.0f} MB | {m['seconds']:.1f} |\n\n"
            f"{_when(m)}.")


def render_fuzz(data: dict) -> str:
    f = data["figures"].get("fuzz")
    if not f:
        return "(not measured yet: python scripts/bench.py reliability --parts=fuzz)"
    lines = ["| target | calls | crashes | hangs | non-finite with OK | changed on error "
             "| `step` codes seen |", "|---|---:|---:|---:|---:|---:|---|"]
    for name, t in f["targets"].items():
        order = sorted(t["step_codes"].items(), key=lambda kv: (not kv[0].lstrip("-").isdigit(), kv[0]))
        codes = " ".join(f"{c}:{n}" for c, n in order)
        lines.append(f"| {name} | {t['calls']:,} | {t['crashes']} | {t['hangs']} | {t['nonfinite_ok']} | "
                     f"{t['changed_on_error']} | {codes} |")
    tot = f["totals"]
    lines.append(f"| **total** | **{tot['calls']:,}** | **{tot['crashes']}** | **{tot['hangs']}** | "
                 f"**{tot['nonfinite_ok']}** | **{tot['changed_on_error']}** | |")
    lines.append(f"\nSeed {f['seed']}; {_when(f)}.")
    return "\n".join(lines)


def render_outliers(data: dict) -> str:
    o = data["figures"].get("outliers")
    if not o:
        return "(not measured yet: python scripts/bench.py reliability --parts=outliers)"
    return "\n\n".join(o["tables"]) + f"\n\n{_when(o)}."


def render_ranges(data: dict) -> str:
    """The option ranges (``runtime/limits.py``, the one table; not a measurement)."""
    from learnest_codegen.runtime.limits import LIMITS

    lines = ["| option | range | why |", "|---|---|---|"]
    lines += [f"| `{lim.name}` | {lim.describe()} | {lim.why} |" for lim in LIMITS.values()]
    return "\n".join(lines)
