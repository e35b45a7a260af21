"""Soak benchmark: millions of estimator steps on one handle; estimate drift and process RSS.

A simulated cartpole test run (seed 1, 5000 samples) is looped: pass 0 starts from init and is
the clean run; every later pass goes on from the previous pass's end on the same handle (the
measurements jump back to the start of the run, so each pass begins with a transient). After the
transient the estimates must come back to the clean run's: per pass we record the largest
``|x_pass - x_clean|`` over the second half of the run (flat over the passes = no drift), the
failed steps, and the process RSS (flat = no leak; read from /proc/self/status).

- UKF: 1e6 steps by the C ``<prefix>_run`` on one handle (the documented C API, through ctypes;
  each pass is one call), so the soak measures the C and not Python.
- Embedded MHE (mhe_gn, mhe_rti): 1e5 steps each through :class:`CompiledEmbeddedMHE.step`
  (its C ``run`` only starts from a fresh window).
- Ipopt MHE: 1e4 steps through :class:`CompiledMHE.step` (Ipopt allocates and frees its problem
  every step, so its RSS is the interesting line).

Usage::

    python scripts/bench_soak.py --out bench_soak.json [--ukf-steps 1000000 --mhe-steps 100000]
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
    """One UKF handle driven by the C ``<prefix>_run`` (sample k of a call uses U[max(k-1, 0)])."""

    def __init__(self, directory: Path, x0: np.ndarray):
        kind = estimator_kind("ukf")
        self.binding = kind.compiled(directory)  # checks the manifest; gives P0, Q, R
        m = read_manifest(directory)
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
        args = [np.ascontiguousarray(a, dtype=float) for a in (x0, s.P0(), s.Q(), s.R())]
        self.handle = ctypes.c_void_p()
        code = init(self.memory.ctypes.data, self.memory.nbytes, *(a.ctypes.data for a in args),
                    ctypes.byref(self.handle))
        if code != 0:
            raise SolverError(f"UKF init returned {code}")

    def run_pass(self, U: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, int]:
        X = np.full((len(Y), self.binding.nx), np.nan)
        code = self._run(self.handle, len(Y), U.ctypes.data, Y.ctypes.data, None, X.ctypes.data)
        return X, int(np.isnan(X[:, 0]).sum()) if code else 0


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


def soak(driver, U: np.ndarray, Y: np.ndarray, steps: int) -> dict[str, Any]:
    """Loop the run through ``driver`` for ``steps`` samples; drift and RSS per pass."""
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
    cpu = time.process_time() - start_cpu
    rss = [r["rss_kib"] for r in rows]
    later = [r["drift_second_half"] for r in rows[1:]]
    return {"steps": passes * len(Y), "passes": passes, "samples_per_pass": len(Y),
            "cpu_seconds": round(cpu, 3), "cpu_us_per_step": round(1e6 * cpu / (passes * len(Y)), 3),
            "failed_steps": sum(r["failed_steps"] for r in rows),
            "drift_max": max(later), "drift_first_wrap": later[0], "drift_last": later[-1],
            # the gated MHEs take up to ~2,500 samples to re-acquire the wrapped state
            "drift_max_last_quarter": max(r["drift_last_quarter"] for r in rows[1:]),
            "rss_kib_after_first_pass": rss[0], "rss_kib_max": max(rss), "rss_kib_last": rss[-1],
            "rss_growth_kib_after_first_pass": max(rss) - rss[0],
            "per_pass": rows if passes <= 400 else rows[:: passes // 200]}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("bench_soak.json"))
    parser.add_argument("--build-dir", type=Path, default=Path("build_soak"))
    parser.add_argument("--ukf-steps", type=int, default=1_000_000)
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
    plan = {"ukf": args.ukf_steps, "mhe_gn": args.mhe_steps, "mhe_rti": args.mhe_steps,
            "mhe": args.ipopt_steps}
    plan = {k: v for k, v in plan.items() if v > 0}
    compile_estimators(model, args.build_dir, model_hash="nominal", estimators=tuple(plan))
    result = {"system": "cartpole", "model": "nominal", "seed": 1, "python": sys.version.split()[0],
              "machine": platform.machine(), "load_average": os.getloadavg(), "estimators": {}}
    for name, steps in plan.items():
        directory = estimator_dir(args.build_dir, model, name)
        driver = (UKFRun(directory, x0) if name == "ukf"
                  else StepRun(estimator_kind(name).compiled(directory), x0, name in args.reset_each_pass))
        result["estimators"][name] = soak(driver, U, Y, steps)
        result["estimators"][name]["reset_each_pass"] = name in args.reset_each_pass
        r = result["estimators"][name]
        print(f"{name:8s} {r['steps']:8d} steps  drift max {r['drift_max']:.3g}  failed {r['failed_steps']}  "
              f"RSS {r['rss_kib_after_first_pass']} -> {r['rss_kib_last']} KiB  "
              f"({r['cpu_us_per_step']} us CPU/step)", flush=True)
    result["max_rss_kib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main(sys.argv[1:])
