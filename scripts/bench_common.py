"""What the estimator benchmarks share: timing, the sample-by-sample loop and the command line.

Each ``scripts/bench_<estimator>.py`` defines only ``bench_model(model, U, Y, build_dir,
repeat) -> dict`` and calls :func:`main` with it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from learnest_codegen import get_system
from learnest_codegen.export import hybrid_model, prior_model
from learnest_codegen.learning.network import ResidualNet
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


def main(name: str, description: str, bench_model: Callable[..., dict], *, repeat: int,
         extra: dict | None = None, argv: list[str] | None = None) -> dict:
    """Parse ``--out --models --steps --repeat --build-dir``, bench each model, write the JSON."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--out", type=Path, default=Path(f"bench_{name}.json"))
    parser.add_argument("--models", nargs="+", choices=["nominal", "knode"],
                        default=["nominal", "knode"])
    parser.add_argument("--steps", type=int, default=None, help="default: one full run")
    parser.add_argument("--repeat", type=int, default=repeat, help="repeats of the C timings")
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
              "python": platform.python_version(), **(extra or {}), "results": results}
    args.out.write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return report
