"""Per-step time of the Python MHE (CasADi nlpsol) and of the compiled MHE on a cartpole run.

Times, on the same simulated run: the Python reference sample by sample (``MHE.step``, also
recording Ipopt's iterations per step), the whole run in C (``CompiledMHE.run``, one ctypes
call) and sample-by-sample ctypes calls (``CompiledMHE.step``); records the build time and code
size of a fresh build. Usage::

    python scripts/bench_mhe.py --out bench_mhe.json --models nominal knode

(from the repository root with the package installed, e.g. ``pip install -e .``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from learnest_codegen import get_system
from learnest_codegen.codegen.mhe import generate_mhe
from learnest_codegen.compilation import estimator_kind
from learnest_codegen.estimators.mhe import MHE
from learnest_codegen.estimators.mhe_problem import IPOPT_OPTIONS
from learnest_codegen.export import hybrid_model, prior_model
from learnest_codegen.network import ResidualNet
from learnest_codegen.runtime.mhe import CompiledMHE
from learnest_codegen.simulation import simulate


def best_seconds(fn, repeat: int) -> float:
    """Shortest wall time of ``repeat`` calls (the least disturbed by the machine)."""
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def steps(estimator, U, Y, x0, record=None) -> np.ndarray:
    """The run sample by sample (``run``'s convention); ``record(estimator)`` after each step."""
    estimator.reset(x0)
    X = np.empty((len(Y), len(x0)))
    for k in range(len(Y)):
        X[k] = estimator.step(U[k - 1] if k else np.zeros(U.shape[1]), Y[k])
        if record:
            record(estimator)
    return X


def bench_model(model, U, Y, build_dir: Path, repeat: int) -> dict:
    settings = estimator_kind("mhe").default_settings(model)  # what compile/estimate use
    x0 = np.asarray(model.system.x0, dtype=float)
    start = time.perf_counter()
    gen = generate_mhe(model, settings, build_dir / model.kind)  # a fresh folder: a real build
    generate_total_s = time.perf_counter() - start
    compiled, reference, iterations = CompiledMHE(gen.directory), MHE(model, settings), []
    start = time.perf_counter()
    X_ref = steps(reference, U, Y, x0, lambda mhe: iterations.append(mhe.iterations))
    python_s = time.perf_counter() - start
    c_run_s = best_seconds(lambda: compiled.run(U, Y, x0), repeat)
    ctypes_s = best_seconds(lambda: steps(compiled, U, Y, x0), max(1, repeat // 5))
    T = len(Y)
    return {
        "model_kind": model.kind, "steps": T, "horizon": settings.horizon,
        "python_us_per_step": 1e6 * python_s / T,
        "c_run_us_per_step": 1e6 * c_run_s / T,
        "ctypes_step_us_per_step": 1e6 * ctypes_s / T,
        "speedup_c_run": python_s / c_run_s,
        "ipopt_iterations_mean": float(np.mean(iterations)),
        "ipopt_iterations_histogram": {str(i): int(n)
                                       for i, n in enumerate(np.bincount(iterations)) if n},
        "max_abs_state_difference": float(np.max(np.abs(compiled.run(U, Y, x0) - X_ref))),
        "generate_seconds": generate_total_s - gen.build_seconds, "build_seconds": gen.build_seconds,
        "code_bytes": gen.code_bytes, "library_bytes": gen.library.stat().st_size,
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench_mhe.json"))
    parser.add_argument("--models", nargs="+", choices=["nominal", "knode"],
                        default=["nominal", "knode"])
    parser.add_argument("--steps", type=int, default=None, help="default: one full run")
    parser.add_argument("--repeat", type=int, default=5, help="repeats of the C timings")
    parser.add_argument("--build-dir", type=Path, default=None, help="default: a temporary folder")
    args = parser.parse_args(argv)
    system = get_system("cartpole")
    run = simulate(system, seed=0, duration=(args.steps or system.n_samples) * system.dt)
    torch.manual_seed(0)  # random KNODE weights: timing depends on the size, not the values
    models = {"nominal": lambda: prior_model(system),
              "knode": lambda: hybrid_model(system, ResidualNet(system.nx, system.nu))}
    with tempfile.TemporaryDirectory() as tmp:
        build_dir = args.build_dir or Path(tmp)
        results = [bench_model(models[kind](), run.u, run.y, build_dir, args.repeat)
                   for kind in args.models]
    report = {"system": system.name, "machine": platform.platform(), "cpus": os.cpu_count(),
              "python": platform.python_version(), "ipopt_options": dict(IPOPT_OPTIONS),
              "results": results}
    args.out.write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
