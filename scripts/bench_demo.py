"""The demo as a user runs it (`learnest demo`, its defaults): accuracy and time per step.

Runs ``learnest demo --out build/bench/demo`` in a fresh process (the README's main job, the
default training, seeds 0 and 1) and keeps its report. The trained model it leaves in
``build/bench/demo/model`` is the one the instruction-count benchmarks measure; its hash is
recorded as ``conditions.model_hash`` here and in theirs, and ``tests/test_figures.py`` checks
that they measured the model whose accuracy this benchmark quotes.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import figures

MINUTES = 5
ORDER = 10
OUT = figures.ROOT / "build" / "bench" / "demo"


def measure(args) -> tuple[dict, dict]:
    shutil.rmtree(OUT, ignore_errors=True)
    cond = figures.conditions(
        model="the demo's KNODE cartpole, default training (learnest_codegen.config.DEFAULT_TRAINING), "
              "trained on the seed-0 run", run="cartpole seed 1, 10 s at 500 Hz (5000 samples)",
        settings="learnest demo (every option at its default)")
    subprocess.run([sys.executable, "-m", "learnest_codegen.cli", "demo", "--out", str(OUT)], check=True)
    report = json.loads((OUT / "report.json").read_text())
    cond["model_hash"] = model_hash(OUT / "model")
    return {"rows": report["rows"], "train_seconds": report["meta"]["train_seconds"]}, cond


def model_dir() -> Path:
    """The demo's trained model, running the demo first if it has not run on this checkout."""
    if not (OUT / "model" / "model.json").exists():
        measure(None)
    return OUT / "model"


def model_hash(model: str | Path) -> str:
    """The hash a trained cartpole model directory compiles under (its weights and settings), or
    ``model`` itself for ``"nominal"`` and ``"true"``."""
    from learnest_codegen import get_system
    from learnest_codegen.compilation import resolve_model

    return resolve_model(get_system("cartpole"), str(model))[1]


def render_table(data: dict) -> str:
    from learnest_codegen.experiments.demo import accuracy_table
    return accuracy_table(data["figures"]["rows"])


def render_times(data: dict) -> str:
    rows = [r for r in data["figures"]["rows"]]
    lines = ["| estimator | backend | us/step |", "|---|---|---|"]
    lines += [f"| {r['method']} | {r['backend']} | {r['us_per_step']:.1f} |" for r in rows]
    m = data["conditions"]["machine"]
    lines.append(f"\nMeasured by `{data['command']}` on {data['conditions']['date']}: {m['cpu']}, "
                 f"{m['cores']} cores, load {m['load_1min']} before and {m.get('load_1min_at_end', '?')} "
                 "after.")
    return "\n".join(lines)
