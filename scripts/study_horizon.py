"""How the embedded MHE's accuracy depends on its horizon N, beside its cost per sample.

For a system (default: the quadrotor), a KNODE model is trained on a simulated run (seed 0,
the default training) and ``mhe_rti`` is built for several horizons in the chosen precision;
each is scored by its state MSE over simulated test runs (seeds 1..S), paired with the
same runs' N = 20 figure, and the UKF is scored beside them. Instructions per sample on the
Cortex-M4F come from ``examples/cortex_m`` (``--cortex-m``, QEMU ``-icount``). Usage::

    python scripts/study_horizon.py --system quadrotor --horizons 4 6 8 10 20 --out study.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

import learnest_codegen as ln

ROOT = Path(__file__).resolve().parents[1]


def cortex_m_instructions(system: str, horizon: int, out: Path) -> dict:
    """Mean and max M4F instructions a step of the float32 ``mhe_rti`` at ``horizon`` (QEMU)."""
    sys.path.insert(0, str(ROOT / "examples" / "cortex_m"))
    import build_and_compare as bc  # noqa: PLC0415 (example glue, imported on demand)

    folder = out / f"cm_{horizon}"
    bc.main(["--system", system, "--model", "untrained", "--precision", "float32",
             "--estimator", "mhe_rti", "--steps", "200", "--horizon", str(horizon), "--out", str(folder)])
    report = json.loads(next(folder.glob("report_*.json")).read_text())
    return report["qemu_instructions_per_step"]


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", default="quadrotor")
    parser.add_argument("--horizons", type=int, nargs="+", default=[4, 6, 8, 10, 20])
    parser.add_argument("--seeds", type=int, default=5, help="test runs (seeds 1..S)")
    parser.add_argument("--precision", choices=("float64", "float32"), default="float32")
    parser.add_argument("--cortex-m", action="store_true", help="also count M4F instructions")
    parser.add_argument("--out", type=Path, default=Path("study_horizon.json"))
    args = parser.parse_args(argv)
    system = ln.get_system(args.system)
    model = ln.train(ln.simulate(system, seed=0), system)
    runs = [ln.simulate(system, seed=s) for s in range(1, args.seeds + 1)]
    report = {"system": system.name, "precision": args.precision, "seeds": list(range(1, args.seeds + 1)),
              "model": "knode, default training on seed 0", "mse": {}}
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.horizons:
            est = ln.make_estimator(model, "mhe_rti", out=tmp, precision=args.precision, horizon=n)
            report["mse"][f"mhe_rti N={n}"] = [ln.evaluate(est, r).mse(r.x) for r in runs]
        ukf = ln.make_estimator(model, "ukf", out=tmp, precision=args.precision)
        report["mse"]["ukf"] = [ln.evaluate(ukf, r).mse(r.x) for r in runs]
        if args.cortex_m:
            report["cortex_m4f_instructions"] = {n: cortex_m_instructions(system.name, n, Path(tmp))
                                                 for n in args.horizons}
    ref = np.array(report["mse"][f"mhe_rti N={max(args.horizons)}"])
    report["relative_to_longest"] = {
        k: {"mean": float(np.mean(np.array(v) / ref - 1)), "worst": float(np.max(np.array(v) / ref - 1))}
        for k, v in report["mse"].items()}
    args.out.write_text(json.dumps(report, indent=1))
    for k, v in report["relative_to_longest"].items():
        print(f"{k:14s} mean MSE {np.mean(report['mse'][k]):.4g}  vs longest: mean {v['mean']:+.1%}, "
              f"worst {v['worst']:+.1%}")
    return report


if __name__ == "__main__":
    main()
