"""Per-step time of the FilterPy UKF and of the compiled UKF on a cartpole run.

Times three things on the same simulated run: the Python reference (``UKF.run``), the whole run
in C (``CompiledUKF.run``, one ctypes call) and sample-by-sample ctypes calls
(``CompiledUKF.step``), and records the build time and sizes of the library. Usage::

    python scripts/bench_ukf.py --out bench_ukf.json --models nominal knode

(from the repository root with the package installed, e.g. ``pip install -e .``).
"""

from __future__ import annotations

import time
from pathlib import Path

import bench_common
import numpy as np
from bench_common import best_seconds

from learnest_codegen.codegen.ukf import generate_ukf
from learnest_codegen.compilation import estimator_kind
from learnest_codegen.estimators.ukf import UKF
from learnest_codegen.runtime.ukf import CompiledUKF


def bench_model(model, U, Y, build_dir: Path, repeat: int) -> dict:
    settings = estimator_kind("ukf").default_settings(model)  # what compile/estimate use
    gen = generate_ukf(model, settings, build_dir / model.kind, force=True)
    x0, T = model.system.x0, len(Y)
    compiled, reference = CompiledUKF(gen.directory), UKF(model, settings)
    start = time.perf_counter()
    X_ref = reference.run(U, Y, x0)
    python_s = time.perf_counter() - start
    c_run_s = best_seconds(lambda: compiled.run(U, Y, x0), repeat)
    X_c = compiled.run(U, Y, x0)

    def ctypes_steps():
        compiled.reset(x0)
        for k in range(T):
            compiled.step(U[max(k - 1, 0)], Y[k])

    ctypes_s = best_seconds(ctypes_steps, max(1, repeat // 5))
    rel = np.abs(X_c - X_ref).max(axis=1) / np.maximum(np.abs(X_ref).max(axis=1), 1e-6)
    return {
        "model_kind": model.kind, "steps": T,
        "python_us_per_step": 1e6 * python_s / T,
        "c_run_us_per_step": 1e6 * c_run_s / T,
        "ctypes_step_us_per_step": 1e6 * ctypes_s / T,
        "speedup_c_run": python_s / c_run_s,
        "max_relative_state_difference": float(rel.max()),
        "generate_seconds": gen.generate_seconds, "build_seconds": gen.build_seconds,
        "code_bytes": gen.code_bytes, "library_bytes": gen.library_path.stat().st_size,
    }


def main(argv: list[str] | None = None) -> None:
    bench_common.main("ukf", __doc__.splitlines()[0], bench_model, repeat=20, argv=argv)


if __name__ == "__main__":
    main()
