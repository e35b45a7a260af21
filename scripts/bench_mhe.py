"""Per-step time of the Python MHE (CasADi nlpsol) and of the compiled MHE on a cartpole run.

Times, on the same simulated run: the Python reference sample by sample (``MHE.step``, also
recording Ipopt's iterations per step), the whole run in C (``CompiledMHE.run``, one ctypes
call) and sample-by-sample ctypes calls (``CompiledMHE.step``); records the build time and code
size of a fresh build. Usage::

    python scripts/bench_mhe.py --out bench_mhe.json --models nominal knode

(from the repository root with the package installed, e.g. ``pip install -e .``).
"""

from __future__ import annotations

import time
from pathlib import Path

import bench_common
import numpy as np
from bench_common import best_seconds, steps

from learnest_codegen.codegen.mhe import generate_mhe
from learnest_codegen.compilation import estimator_kind
from learnest_codegen.estimators.mhe import MHE
from learnest_codegen.estimators.mhe_problem import IPOPT_OPTIONS
from learnest_codegen.runtime.mhe import CompiledMHE


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
        "code_bytes": gen.code_bytes, "library_bytes": gen.library_path.stat().st_size,
    }


def main(argv: list[str] | None = None) -> None:
    bench_common.main("mhe", __doc__.splitlines()[0], bench_model, repeat=5,
                      extra={"ipopt_options": dict(IPOPT_OPTIONS)}, argv=argv)


if __name__ == "__main__":
    main()
