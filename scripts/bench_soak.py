"""Soak benchmark: millions of estimator steps on one handle; estimate drift and process RSS.

A simulated cartpole test run (seed 1, 5000 samples) is looped: pass 0 starts from init and is
the clean run; every later pass goes on from the previous pass's end on the same handle (the
measurements jump back to the start of the run, so each pass begins with a transient). After the
transient the estimates must come back to the clean run's: per pass we record the largest
``|x_pass - x_clean|`` over the second half of the run (flat over the passes = no drift), the
failed steps, and the process RSS (flat = no leak; read from /proc/self/status).

- UKF: 1e6 steps by the C ``<prefix>_run`` on one handle (the documented C API, through ctypes;
  each pass is one call), so the soak measures the C and not Python; float64 and float32 builds
  (``ukf``, ``ukf_float32``), the float32 one also against the float64 build's clean pass
  (soaked in lockstep: error vs float64, per pass), a failed step counted by its code (the pass goes on).
- Embedded MHE (mhe_gn, mhe_rti): 1e5 steps each through :class:`CompiledEmbeddedMHE.step`
  (its C ``run`` only starts from a fresh window).
- Ipopt MHE: 1e4 steps through :class:`CompiledMHE.step` (Ipopt allocates and frees its problem
  every step, so its RSS is the interesting line).

Usage::

    python scripts/bench_soak.py --out bench_soak.json [--ukf-steps 1000000 --mhe-steps 100000]
    python scripts/bench_soak.py --ukf-precisions float32 --mhe-steps 0 --ipopt-steps 0
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import platform
import resource
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from learnest_codegen import get_system
from learnest_codegen.compilation import compile_estimators, estimator_dir, estimator_kind
from learnest_codegen.errors import SolverError
from learnest_codegen.export import prior_model
from learnest_codegen.runtime.manifest import read_manifest
from learnest_codegen.simulation import simulate


def rss_kib() -> int:
    """Resident set size of this process [KiB] (Linux)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError("no VmRSS in /proc/self/status (Linux only)")


class UKFRun:
    """One UKF handle driven by the C ``<prefix>_run`` (sample k of a call uses U[max(k-1, 0)]).

    ``run`` stops at the first failed step (which changes nothing); the pass then goes on with
    a new ``run`` from the next sample (whose prediction uses that sample's own u, as the first
    sample of every ``run`` call does), the failed sample keeping the previous estimate; each
    failure's code is counted.
    """

    def __init__(self, directory: Path, x0: np.ndarray):
        kind = estimator_kind("ukf")
        self.binding = kind.compiled(directory)  # checks the manifest; gives P0, Q, R
        m = read_manifest(directory)
        self.dtype = np.float32 if m["precision"] == "float32" else np.float64
        lib = ctypes.CDLL(str(Path(directory) / m["library"]))
        vp = ctypes.c_void_p
        self._run = getattr(lib, f"{m['prefix']}_run")
        self._run.restype, self._run.argtypes = ctypes.c_int, [vp, ctypes.c_int, vp, vp, vp, vp]
        init = getattr(lib, f"{m['prefix']}_init")
        init.restype, init.argtypes = ctypes.c_int, [vp, ctypes.c_size_t, vp, vp, vp, vp, vp]
        size = getattr(lib, f"{m['prefix']}_workspace_size")
        size.restype = ctypes.c_size_t
        self.memory = np.zeros(size(), dtype=np.uint8)
        s = self.binding.settings
        args = [np.ascontiguousarray(a, dtype=self.dtype) for a in (x0, s.P0(), s.Q(), s.R())]
        self.handle = ctypes.c_void_p()
        code = init(self.memory.ctypes.data, self.memory.nbytes, *(a.ctypes.data for a in args),
                    ctypes.byref(self.handle))
        if code != 0:
            raise SolverError(f"UKF init returned {code}")
        self.codes: Counter = Counter()  # error code -> failed steps
        self.first_failure: int | None = None  # step number (over all passes) of the first one
        self.done = 0

    def run_pass(self, U: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, int]:
        U, Y = (np.ascontiguousarray(a, dtype=self.dtype) for a in (U, Y))
        X = np.full((len(Y), self.binding.nx), np.nan, dtype=self.dtype)
        k, failed = 0, 0
        while k < len(Y):
            code = self._run(self.handle, len(Y) - k, U[k:].ctypes.data, Y[k:].ctypes.data, None,
                             X[k:].ctypes.data)
            if code >= 0:
                break
            k += int(np.argmax(np.isnan(X[k:, 0])))  # the failed sample
            self.codes[int(code)] += 1
            if self.first_failure is None:
                self.first_failure = self.done + k
            X[k] = X[k - 1] if k else np.nan
            failed, k = failed + 1, k + 1
        self.done += len(Y)
        return X.astype(float), failed


class StepRun:
    """An MHE binding stepped sample by sample; a failed step keeps the previous estimate."""

    def __init__(self, estimator, x0: np.ndarray, reset_each_pass: bool = False):
        self.estimator, self.x0, self.reset_each_pass = estimator, x0, reset_each_pass
        estimator.reset(x0)
        self.started = False

    def run_pass(self, U: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, int]:
        X, failed = np.empty((len(Y), self.estimator.nx)), 0
        if self.reset_each_pass and self.started:
            self.estimator.reset(self.x0)
            self.started = False
        for k in range(len(Y)):
            u = U[k - 1] if k else (U[-1] if self.started else np.zeros(U.shape[1]))
            try:
                X[k] = self.estimator.step(u, Y[k])
            except SolverError:
                failed += 1
                X[k] = self.estimator.x
        self.started = True
        return X, failed


def soak(driver, U: np.ndarray, Y: np.ndarray, steps: int, twin=None) -> dict[str, Any]:
    """Loop the run through ``driver`` for ``steps`` samples; drift and RSS per pass.

    ``twin`` (a driver of the float64 build, for a float32 build) is soaked in lockstep: per
    pass also the largest ``|x_pass - x_twin_pass|`` over the whole pass and over its second
    half (the same transients in both, so this is the float32 error, wraps included).
    """
    passes = max(2, -(-steps // len(Y)))
    half, tail = len(Y) // 2, 3 * len(Y) // 4
    start_cpu, rows = time.process_time(), []
    X_clean = None
    for p in range(passes):
        X, failed = driver.run_pass(U, Y)
        if X_clean is None:
            X_clean = X
        drift = float(np.max(np.abs(X[half:] - X_clean[half:])))
        drift_tail = float(np.max(np.abs(X[tail:] - X_clean[tail:])))
        rows.append({"pass": p, "steps": (p + 1) * len(Y), "failed_steps": failed,
                     "drift_second_half": drift, "drift_last_quarter": drift_tail,
                     "rss_kib": rss_kib()})
        if twin is not None:
            error = np.abs(X - twin.run_pass(U, Y)[0])
            rows[-1]["error_vs_float64"] = float(np.nanmax(error)) if failed < len(Y) else np.inf
            rows[-1]["error_vs_float64_second_half"] = float(np.nanmax(error[half:]))
    cpu = time.process_time() - start_cpu
    rss = [r["rss_kib"] for r in rows]
    later = [r["drift_second_half"] for r in rows[1:]]
    result = {"steps": passes * len(Y), "passes": passes, "samples_per_pass": len(Y),
            "cpu_seconds": round(cpu, 3), "cpu_us_per_step": round(1e6 * cpu / (passes * len(Y)), 3),
            "failed_steps": sum(r["failed_steps"] for r in rows),
            "drift_max": max(later), "drift_first_wrap": later[0], "drift_last": later[-1],
            # the gated MHEs take up to ~2,500 samples to re-acquire the wrapped state
            "drift_max_last_quarter": max(r["drift_last_quarter"] for r in rows[1:]),
            "rss_kib_after_first_pass": rss[0], "rss_kib_max": max(rss), "rss_kib_last": rss[-1],
            "rss_growth_kib_after_first_pass": max(rss) - rss[0],
            "per_pass": rows if passes <= 400 else rows[:: passes // 200]}
    if twin is not None:
        result["error_vs_float64_max"] = max(r["error_vs_float64"] for r in rows)
        result["error_vs_float64_second_half_max"] = max(r["error_vs_float64_second_half"] for r in rows)
    if isinstance(driver, UKFRun):
        result["failed_codes"] = {str(k): v for k, v in sorted(driver.codes.items())}
        result["first_failed_step"] = driver.first_failure
    return result


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("bench_soak.json"))
    parser.add_argument("--build-dir", type=Path, default=Path("build_soak"))
    parser.add_argument("--ukf-steps", type=int, default=1_000_000)
    parser.add_argument("--ukf-precisions", nargs="+", default=["float64", "float32"],
                        choices=["float64", "float32"],
                        help="UKF builds soaked (a float32 one is also compared to float64's clean pass)")
    parser.add_argument("--mhe-steps", type=int, default=100_000, help="per embedded MHE")
    parser.add_argument("--ipopt-steps", type=int, default=10_000, help="Ipopt MHE; 0 skips it")
    parser.add_argument("--samples", type=int, default=5000, help="samples of the looped run")
    parser.add_argument("--reset-each-pass", nargs="*", default=[], choices=["mhe_gn", "mhe_rti", "mhe"],
                        help="MHEs reset to x0 before each pass (then every pass must equal the first)")
    args = parser.parse_args(argv)
    system = get_system("cartpole")
    model = prior_model(system)
    run = simulate(system, seed=1, duration=args.samples * system.dt)
    U, Y, x0 = np.ascontiguousarray(run.u), np.ascontiguousarray(run.y), np.asarray(system.x0, float)
    plan = {}
    if args.ukf_steps > 0:
        plan.update({"ukf" if p == "float64" else f"ukf_{p}": ("ukf", p, args.ukf_steps)
                     for p in args.ukf_precisions})
    plan.update({"mhe_gn": ("mhe_gn", "float64", args.mhe_steps),
                 "mhe_rti": ("mhe_rti", "float64", args.mhe_steps),
                 "mhe": ("mhe", "float64", args.ipopt_steps)})
    plan = {k: v for k, v in plan.items() if v[2] > 0}
    for precision in ("float64", "float32"):
        chosen = {e for e, p, _ in plan.values() if p == precision}
        if precision == "float64" and "ukf_float32" in plan:
            chosen.add("ukf")  # the float32 UKF is compared to it
        if chosen:
            compile_estimators(model, args.build_dir, model_hash="nominal", estimators=tuple(sorted(chosen)),
                               precision=precision)
    result = {"system": "cartpole", "model": "nominal", "seed": 1, "python": sys.version.split()[0],
              "machine": platform.machine(), "load_average": os.getloadavg(), "estimators": {}}
    for name, (estimator, precision, steps) in plan.items():
        directory = estimator_dir(args.build_dir, model, estimator, precision)
        driver = (UKFRun(directory, x0) if estimator == "ukf"
                  else StepRun(estimator_kind(estimator).compiled(directory), x0,
                               estimator in args.reset_each_pass))
        twin = (UKFRun(estimator_dir(args.build_dir, model, estimator), x0)
                if precision == "float32" else None)
        r = soak(driver, U, Y, steps, twin)
        r["precision"], r["reset_each_pass"] = precision, estimator in args.reset_each_pass
        result["estimators"][name] = r
        extra = (f"  |x - float64| max {r['error_vs_float64_max']:.3g}"
                 if "error_vs_float64_max" in r else "")
        print(f"{name:12s} {r['steps']:8d} steps  drift max {r['drift_max']:.3g}  failed {r['failed_steps']}"
              f"{extra}  RSS {r['rss_kib_after_first_pass']} -> {r['rss_kib_last']} KiB  "
              f"({r['cpu_us_per_step']} us CPU/step)", flush=True)
    result["max_rss_kib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
