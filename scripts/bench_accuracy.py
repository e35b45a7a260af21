"""Accuracy of the generated estimators in both precisions against each other and the Ipopt MHE.

KNODE cartpole (default net, seed-0 initialisation: the same C as a trained one), the seed-1
test run, MHE horizon 20: max |state difference| of mhe_rti and mhe_gn (float64 and float32)
to the Ipopt MHE, of each float32 build to its float64 build (UKF: float32 at alpha 0.5, the
float32 minimum), and every estimate's MSE against the true state. The Cortex-M runs
(examples/cortex_m) equal the host builds bit for bit in float32, so these are also the
firmware's figures (docs/reports/cortex_m.md). Usage::

    python scripts/bench_accuracy.py --out bench_accuracy.json [--steps 300]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from learnest_codegen import get_system
from learnest_codegen.codegen.mhe import generate_mhe
from learnest_codegen.codegen.mhe_gn import generate_embedded_mhe
from learnest_codegen.codegen.ukf import FLOAT32_MIN_ALPHA, generate_ukf
from learnest_codegen.estimators.mhe_gn import GaussNewtonSettings
from learnest_codegen.estimators.mhe_problem import MHESettings, steady_state_arrival
from learnest_codegen.estimators.ukf import UKFSettings
from learnest_codegen.export import hybrid_model
from learnest_codegen.learning.training import make_net
from learnest_codegen.runtime.mhe import CompiledMHE
from learnest_codegen.runtime.mhe_gn import CompiledEmbeddedMHE
from learnest_codegen.runtime.ukf import CompiledUKF
from learnest_codegen.simulation import simulate


def mse(X: np.ndarray, truth: np.ndarray) -> float:
    return float(np.mean((X - truth) ** 2))


def gap(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.max(np.abs(a - b)))


def measure(root: Path, T: int) -> dict:
    system = get_system("cartpole")
    torch.manual_seed(0)
    model = hybrid_model(system, make_net(system))
    run = simulate(system, seed=1, duration=T * system.dt)
    U, Y, x0 = run.u, run.y, np.asarray(system.x0, float)
    out: dict = {"system": "cartpole", "model": "knode (untrained, seed 0)", "steps": T,
                 "horizon": 20}
    settings = steady_state_arrival(model, MHESettings.from_system(system, horizon=20))
    Xi = CompiledMHE(generate_mhe(model, settings, root / "mhe").directory).run(U, Y, x0)
    out["ipopt_mse"] = mse(Xi, run.x)
    for mode in ("rti", "converged"):
        X = {}
        for prec in ("float64", "float32"):
            solver = GaussNewtonSettings(mode=mode, precision=prec)
            gen = generate_embedded_mhe(model, settings, root / f"{mode}_{prec}", solver=solver)
            X[prec] = CompiledEmbeddedMHE(gen.directory).run(U, Y, x0)
        out[mode] = {"f64_vs_ipopt_max": gap(X["float64"], Xi),
                     "f32_vs_f64_max": gap(X["float32"], X["float64"]),
                     "f32_vs_ipopt_max": gap(X["float32"], Xi),
                     "mse_f64": mse(X["float64"], run.x), "mse_f32": mse(X["float32"], run.x)}
    X = {}
    for prec in ("float64", "float32"):
        ukf = UKFSettings.from_system(system)
        if prec == "float32":
            ukf = replace(ukf, alpha=max(ukf.alpha, FLOAT32_MIN_ALPHA))
        gen = generate_ukf(model, ukf, root / f"ukf_{prec}", precision=prec)
        X[prec] = CompiledUKF(gen.directory).run(U, Y, x0)
    out["ukf"] = {"f32_vs_f64_max": gap(X["float32"], X["float64"]),
                  "mse_f64": mse(X["float64"], run.x), "mse_f32": mse(X["float32"], run.x)}
    return out


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench_accuracy.json"))
    parser.add_argument("--steps", type=int, default=300)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        report = measure(Path(tmp), args.steps)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
