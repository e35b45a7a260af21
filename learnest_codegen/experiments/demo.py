"""The end-to-end demo: simulate, train KNODE, compile, and compare estimators on a test run.

Steps (each printed as it runs): simulate a training run and an independent test run; turn the
training measurements into state observations with the pre-training observer; train the residual
net; compile the MHE, the UKF and the EKF for the nominal and KNODE models; run the Python references and the
compiled libraries on the test run; print MSE and per-step time; write PNG figures.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import click
import numpy as np

from ..config import DEFAULT_TRAINING, TrainingSettings
from ..data import write_run
from ..evaluation import EstimateResult, format_table, mse_per_state, run_estimator
from ..learning.training import train_on_run
from ..pipeline import make_estimator, resolve
from ..plotting import plot_errors, plot_estimates, plot_loss
from ..simulation import simulate
from ..systems import System

LABELS = {"nominal": "", "knode": "KNODE-", "true": ""}
#: The estimators the demo compiles for each model, in the order its table lists them: the
#: reference MHE (Ipopt) and the two Kalman filters.
DEMO_ESTIMATORS = ("mhe", "ukf", "ekf")


@dataclass
class DemoReport:
    """What the demo measured; ``rows`` holds one dict per estimator and backend."""

    rows: list[dict] = field(default_factory=list)
    figures: list[str] = field(default_factory=list)
    meta: dict = field(default_factory=dict)

    def table(self) -> str:
        """The accuracy of the compiled estimators (the README's table, to its digits) and, below
        it, the Python references and this machine's time per step."""
        return (accuracy_table(self.rows) + "\n\nPython references and time per step on this machine:\n\n"
                + format_table(self.rows, [
                    ("method", "method", "s"), ("backend", "backend", "s"), ("mse", "MSE", ".4e"),
                    ("us_per_step", "us/step", ".1f"), ("rejected", "gate rejections", "d")]))


def accuracy_table(rows: list[dict]) -> str:
    """The compiled estimators' accuracy on the test run as a Markdown table: MSE over every
    state, how many times lower than the nominal estimator's, and the share of the gap between
    the nominal and the true-dynamics estimator that the KNODE estimator closes. Deterministic
    for the seeds: the README shows this table, rendered from the benchmark's JSON."""
    lines = ["| estimator | MSE | x better than nominal | gap closed |", "|---|---|---|---|"]
    order = {"nominal": 0, "knode": 1, "true": 2}
    rank = {name: i for i, name in enumerate(DEMO_ESTIMATORS)}
    for row in sorted((r for r in rows if r["backend"] == "C"),
                      key=lambda r: (rank.get(r["estimator"], len(rank)), r["estimator"], order[r["model"]])):
        ratio = "-" if row.get("vs_nominal") is None else f"{row['vs_nominal']:.0f}"
        gap = "-" if row.get("gap_closed") is None else f"{100 * row['gap_closed']:.2f} %"
        lines.append(f"| {row['method']} | {row['mse']:.3e} | {ratio} | {gap} |")
    return "\n".join(lines)


def run_demo(system: System, out: str | Path, *, training: TrainingSettings = DEFAULT_TRAINING,
             observer: str | None = None, train_seed: int = 0, test_seed: int = 1,
             include_true: bool = True, python_mhe: bool = True,
             duration: float | None = None, x0: np.ndarray | None = None,
             P0: np.ndarray | None = None) -> DemoReport:
    """Run the whole pipeline on ``system`` and write everything under ``out``.

    ``training`` defaults to :data:`~learnest_codegen.config.DEFAULT_TRAINING`; its ``seed`` is
    replaced by ``train_seed``. Every estimator starts from ``x0`` (default: the system's) with
    covariance ``P0`` (default: each estimator's own).
    """
    out = Path(out)
    report = DemoReport()
    say = lambda msg: click.echo(click.style(f"==> {msg}", bold=True))  # noqa: E731

    say(f"simulating {system.name}: training run (seed {train_seed}), test run (seed {test_seed})")
    train_run = simulate(system, train_seed, duration=duration)
    test_run = simulate(system, test_seed, duration=duration)
    write_run(train_run, system, out / "train.csv")
    write_run(test_run, system, out / "test.csv")

    settings = replace(training, seed=train_seed)
    say(f"training the KNODE residual on {observer or 'the chosen'} observer's states "
        f"({settings.epochs} epochs, "
        f"{settings.refine} refinement rounds, {settings.restarts} initialisations each, weight decay "
        f"{settings.weight_decay:g}, weight average {settings.weight_average:g})")
    trained = train_on_run(train_run, system, settings, observer=observer)
    trained.save(out / "model")
    report.figures.append(str(plot_loss(trained.meta["loss_history"], trained.meta["prior_loss"],
                                        out / "training_loss.png")))
    report.meta["train_seconds"] = trained.meta["train_seconds"]

    models = [resolve("nominal", system), resolve(trained)]
    models += [resolve("true", system)] if include_true else []
    x0 = np.asarray(system.x0 if x0 is None else x0, dtype=float)
    report.meta["x0"] = x0.tolist()
    report.meta["P0"] = None if P0 is None else np.asarray(P0).tolist()
    results: dict[tuple[str, str, str], EstimateResult] = {}
    for model in models:
        kind = model.model.kind
        say(f"compiling {', '.join(n.upper() for n in DEMO_ESTIMATORS)} for the {kind} model")
        start = time.perf_counter()
        compiled = {name: make_estimator(model, name, out=out / "compiled") for name in DEMO_ESTIMATORS}
        report.meta[f"compile_seconds_{kind}"] = time.perf_counter() - start
        report.meta[f"build_{kind}"] = {
            name: {k: est.manifest.get(k) for k in ("build_seconds", "code_bytes")}
            for name, est in compiled.items()}
        for name, estimator in compiled.items():
            suffix = " (true dynamics)" if kind == "true" else ""
            label = f"{LABELS[kind]}{name.upper()}{suffix}"
            results[(kind, name, "C")] = run_estimator(estimator, test_run, x0, label, P0)
            if name != "mhe" or python_mhe:
                say(f"running the Python reference {label}")
                python = make_estimator(model, name, backend="python")
                results[(kind, name, "python")] = run_estimator(python, test_run, x0, label, P0)

    for (kind, name, backend), res in results.items():
        nominal, true = results.get(("nominal", name, backend)), results.get(("true", name, backend))
        mse = res.mse(test_run.x)
        gap = None
        if kind == "knode" and nominal and true:
            gap = (nominal.mse(test_run.x) - mse) / (nominal.mse(test_run.x) - true.mse(test_run.x))
        report.rows.append({
            "method": res.label, "estimator": name, "model": kind, "backend": backend, "mse": mse,
            "us_per_step": res.seconds_per_step * 1e6,
            "vs_nominal": nominal.mse(test_run.x) / mse if nominal else None, "gap_closed": gap,
            "mse_per_state": mse_per_state(res.x_hat, test_run.x).tolist(),
            "rejected": res.rejections,
        })
    chosen = [results[(k, n, "C")] for k in ("nominal", "knode") for n in DEMO_ESTIMATORS]
    report.figures.append(str(plot_estimates(test_run, system, chosen, out / "estimates.png")))
    report.figures.append(str(plot_errors(test_run, system, chosen, out / "errors.png")))
    (out / "report.json").write_text(json.dumps({"rows": report.rows, "meta": report.meta,
                                                  "figures": report.figures}, indent=2))
    return report

