"""Per-step cost of the embedded MHE (converged and RTI) next to the Ipopt MHE and the UKF.

On one simulated cartpole run with a KNODE model (trained briefly on another run: the timing
depends on the net's size, the iteration counts on a plausible model), for each horizon N:
the Ipopt C MHE (``mhe``), the embedded Gauss-Newton MHE iterated to convergence
(``mhe_gn``) and with one iteration per sample (``mhe_rti``), and the UKF. Each is timed as one
C call over the whole run (``run``), in CPU seconds of this process (``time.process_time``,
less disturbed by other load than wall time; the best of ``--repeat``), and the Gauss-Newton
iterations per step are recorded. The flops of one Gauss-Newton iteration are counted: the
model's CasADi instructions per stage (RK4 + Jacobian by AD, measurement) plus the dense
block algebra of the normal equations, so the achieved flop rate says how close to the
machine the solver runs. Usage::

    python scripts/bench_embedded_mhe.py --out bench_embedded_mhe.json [--horizons 20 50]
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
from learnest_codegen.codegen.mhe_gn import generate_embedded_mhe, model_instructions
from learnest_codegen.codegen.ukf import generate_ukf
from learnest_codegen.estimators.mhe_gn import GaussNewtonSettings
from learnest_codegen.estimators.mhe_problem import MHESettings, steady_state_arrival
from learnest_codegen.estimators.ukf import UKFSettings
from learnest_codegen.export import hybrid_model
from learnest_codegen.learning.training import TrainingSettings, train
from learnest_codegen.runtime.mhe import CompiledMHE
from learnest_codegen.runtime.mhe_gn import CompiledEmbeddedMHE
from learnest_codegen.runtime.ukf import CompiledUKF
from learnest_codegen.simulation import simulate

ACADOS_SQP_RTI_US = 52.0  # acados SQP-RTI on this NLP (cartpole KNODE, N=20), as measured for the project


def cpu_seconds(fn, repeat: int) -> float:
    """Least CPU time of ``repeat`` calls of ``fn``."""
    best = float("inf")
    for _ in range(repeat):
        start = time.process_time()
        fn()
        best = min(best, time.process_time() - start)
    return best


def flops_per_iteration(nx: int, ny: int, horizon: int, instructions: dict) -> dict:
    """Flops of one Gauss-Newton iteration: model evaluations and the block algebra."""
    stages, nodes = horizon, horizon + 1
    model = stages * instructions["dyn"] + nodes * instructions["meas"]
    per_stage = (4 * nx**3                       # Q A and A'Q A
                 + 2 * nx * ny * (nx + ny)       # R C and C'R C
                 + nx**3 // 3 + 2 * nx**3        # Cholesky, L^-1 E, D - B B'
                 + 12 * nx**2 + 4 * ny**2)       # gradient, solves, cost
    return {"model": model, "linear_algebra": nodes * per_stage, "total": model + nodes * per_stage}


def bench_horizon(model, U, Y, X, horizon: int, root: Path, repeat: int) -> dict:
    system = model.system
    settings = steady_state_arrival(model, MHESettings.from_system(system, horizon=horizon))
    x0 = np.asarray(system.x0, dtype=float)
    T = len(Y)
    out = {"horizon": horizon, "steps": T}
    ipopt = CompiledMHE(generate_mhe(model, settings, root / f"mhe_{horizon}").directory)
    X_ipopt = ipopt.run(U, Y, x0)
    out["mhe_ipopt_us"] = 1e6 * cpu_seconds(lambda: ipopt.run(U, Y, x0), 1) / T
    instructions = model_instructions(model)
    flops = flops_per_iteration(model.nx, model.ny, horizon, instructions)
    for mode in ("converged", "rti"):
        solver = GaussNewtonSettings(mode=mode)
        gen = generate_embedded_mhe(model, settings, root / f"{solver.estimator}_{horizon}",
                                    solver=solver)
        est = CompiledEmbeddedMHE(gen.directory)
        X_hat = est.run(U, Y, x0)
        seconds = cpu_seconds(lambda est=est: est.run(U, Y, x0), repeat)
        est.reset(x0)
        iterations = []
        for k in range(T):
            est.step(U[k - 1] if k else np.zeros(model.nu), Y[k])
            iterations.append(est.iterations)
        us = 1e6 * seconds / T
        mean_iter = float(np.mean(iterations))
        out[solver.estimator] = {
            "us_per_step": us,
            "iterations_mean": mean_iter,
            "iterations_histogram": {str(i): int(n) for i, n in enumerate(np.bincount(iterations)) if n},
            "max_abs_difference_to_ipopt": float(np.max(np.abs(X_hat - X_ipopt))),
            "mse": float(np.mean((X_hat - X) ** 2)),
            "us_per_iteration": us / mean_iter,
            "gflops": flops["total"] * mean_iter / (us * 1e3),
            "code_bytes": gen.code_bytes,
        }
    out["mhe_ipopt_mse"] = float(np.mean((X_ipopt - X) ** 2))
    out["flops_per_iteration"] = flops
    out["model_instructions"] = instructions
    return out


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench_embedded_mhe.json"))
    parser.add_argument("--horizons", type=int, nargs="+", default=[20, 50])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--epochs", type=int, default=20, help="training epochs of the KNODE")
    args = parser.parse_args(argv)
    system = get_system("cartpole")
    train_run = simulate(system, seed=0, duration=2000 * system.dt)
    torch.manual_seed(0)
    trained = train(system, train_run.x, train_run.u, train_run.dt,
                    TrainingSettings(epochs=args.epochs), progress=False)
    model = hybrid_model(system, trained.net)
    run = simulate(system, seed=1, duration=args.steps * system.dt)
    report = {"system": system.name, "model": "knode", "epochs": args.epochs,
              "machine": platform.platform(), "cpus": os.cpu_count(),
              "load_average_before": os.getloadavg(), "timer": "process_time (CPU)",
              "acados_sqp_rti_us_reference": ACADOS_SQP_RTI_US}
    with tempfile.TemporaryDirectory() as tmp:
        ukf_settings = UKFSettings.from_system(system)
        ukf = CompiledUKF(generate_ukf(model, ukf_settings, Path(tmp) / "ukf").directory)
        x0 = np.asarray(system.x0, dtype=float)
        report["ukf_us"] = 1e6 * cpu_seconds(lambda: ukf.run(run.u, run.y, x0), args.repeat) / len(run.y)
        report["results"] = [bench_horizon(model, run.u, run.y, run.x, n, Path(tmp), args.repeat)
                             for n in args.horizons]
    report["load_average_after"] = os.getloadavg()
    args.out.write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
