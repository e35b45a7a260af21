"""The cost of the default training as a user meets it: cold and warm CPU seconds of ``ln.train``
on the demo run, beside a bare torch loop of the same net size on the same data.

Every figure comes from fresh processes, one torch thread each, run alternately in the same
minutes (``--rounds`` times; the shortest CPU time of each kind is kept, and every run's load
is recorded):

* ``train``: in a fresh process, ``import learnest_codegen``, simulate the demo's training run
  (cartpole, seed 0), then time ``ln.train(run, system, settings)`` twice: the first call is
  the cold one (it imports torch and pays every first-call set-up), the second the warm one.
  ``settings`` is the default's first round (``replace(DEFAULT_TRAINING, refine=0)``: the
  pre-training observer plus one round of the default's epochs); the whole default (every
  round) is timed the same way.
* ``bare``: in a fresh process, ``import torch``, read the same observer's states and train a
  plain ``torch.nn.Sequential`` MLP of the default net's size (the same features in, hidden
  width and outputs) on the one-step RK4 loss of the same training pairs with
  ``torch.optim.AdamW``, as many epochs and in the same precision and batches as the default;
  cold (import included) and the epochs alone.

The ratios are same-minute ratios: the cold ``train`` against the cold bare loop, the warm one
against the bare loop's epochs. ``--sweep`` also times ``learnest reproduce table1 --jobs 2``
(wall and CPU seconds, children included, the load before and after).

    python scripts/bench.py training                 # the training's cost
    python scripts/bench.py training --sweep         # + Table I (about 40 min)
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import figures

MINUTES = 3
ORDER = 31
ROOT = figures.ROOT

#: One fresh process: the demo's training run, ``ln.train`` cold then warm (CPU seconds).
_TRAIN = r"""
import json, os, sys, time
from dataclasses import replace
start = time.process_time()
import learnest_codegen as ln
system = ln.get_system("cartpole")
run = ln.simulate(system, 0)
settings = replace(ln.DEFAULT_TRAINING, **json.loads(sys.argv[1]))
ready = time.process_time()
out = {"load": os.getloadavg()[0], "import_and_simulate": ready - start}
for kind in ("cold", "warm"):
    cpu, wall = time.process_time(), time.perf_counter()
    model = ln.train(run, system, settings, progress=False)
    out[kind] = time.process_time() - cpu
    out[kind + "_wall"] = time.perf_counter() - wall
if len(sys.argv) > 2:  # the observer's states and the net's shape, for the bare loop
    from learnest_codegen.observers import observe
    import numpy as np
    net = model.net
    np.savez(sys.argv[2], zeta=observe(run, system).zeta, u=run.u, dt=run.dt,
             inputs=[i for i in net.inputs if i not in net.periodic],
             periodic=[i for i in net.periodic if i in net.inputs], prior_features=list(net.prior_features),
             outputs=list(net.outputs), mean=net.in_mean.numpy(), scale=net.in_scale.numpy())
out["final_loss"] = model.meta["final_loss"]
print(json.dumps(out))
"""

#: One fresh process: a bare torch loop of the same size on the same pairs.
_BARE = r"""
import json, os, sys, time
start = time.process_time()
import numpy as np
import torch
torch.set_num_threads(1)
from learnest_codegen import get_system
spec = json.loads(sys.argv[2])
data = np.load(sys.argv[1])
dtype = getattr(torch, spec["precision"])
system = get_system("cartpole")
n_train = len(data["zeta"]) - 1 - int(spec["validation_fraction"] * (len(data["zeta"]) - 1))
zeta = torch.as_tensor(data["zeta"][:n_train], dtype=dtype)
u = torch.as_tensor(data["u"][:n_train], dtype=dtype)
target = torch.as_tensor(data["zeta"][1:n_train + 1], dtype=dtype)
dt = float(data["dt"])
torch.manual_seed(0)
keep, periodic, extra, outputs = (torch.as_tensor(data[k], dtype=torch.long)
                                  for k in ("inputs", "periodic", "prior_features", "outputs"))
mean, scale = (torch.as_tensor(data[k], dtype=dtype) for k in ("mean", "scale"))
mlp = torch.nn.Sequential(torch.nn.Linear(len(mean), spec["hidden"]), torch.nn.Tanh(),
                          torch.nn.Linear(spec["hidden"], len(outputs))).to(dtype)
optimiser = torch.optim.AdamW(mlp.parameters(), lr=spec["learning_rate"], weight_decay=spec["weight_decay"])


def f(x, v):  # prior plus the net on the same features (inputs, sin and cos of the angles, prior)
    xu, prior = torch.cat([x, v], dim=1), system.f(x, v)
    angles = xu[:, periodic]
    feats = torch.cat([xu[:, keep], torch.sin(angles), torch.cos(angles), prior[:, extra]], dim=1)
    return prior.index_add(1, outputs, mlp((feats - mean) / scale))


def rk4(x, v):
    k1 = f(x, v)
    k2 = f(x + dt / 2 * k1, v)
    k3 = f(x + dt / 2 * k2, v)
    k4 = f(x + dt * k3, v)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


ready = time.process_time()
for epoch in range(spec["epochs"]):
    for idx in torch.arange(n_train).split(spec["batch_size"]):
        optimiser.zero_grad()
        loss = ((rk4(zeta[idx], u[idx]) - target[idx]) ** 2).sum(dim=1).mean()
        loss.backward()
        optimiser.step()
done = time.process_time()
print(json.dumps({"load": os.getloadavg()[0], "cold": done - start, "epochs": done - ready,
                  "final_loss": float(loss)}))
"""


def add_arguments(parser) -> None:
    parser.add_argument("--rounds", type=int, default=3, help="fresh processes of each kind, alternating")
    parser.add_argument("--sweep", action="store_true", help="also time learnest reproduce table1 --jobs 2")
    parser.add_argument("--sweep-out", type=Path, default=None, help="the sweep's results directory")


def _run(code: str, *args: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", code, *args], cwd=ROOT, env=env, capture_output=True,
                          text=True)
    if done.returncode:
        raise RuntimeError(f"timing failed: {done.stderr.strip()[-1500:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _best(runs: list[dict], key: str) -> dict:
    return min(runs, key=lambda r: r[key])


def measure_training(rounds: int) -> dict:
    from learnest_codegen.config import DEFAULT_TRAINING

    first_round = {"refine": 0}
    d = DEFAULT_TRAINING
    spec = {"precision": d.precision, "validation_fraction": d.validation_fraction,
            "hidden": d.network.hidden,
            "learning_rate": d.learning_rate, "weight_decay": d.weight_decay, "epochs": d.epochs,
            "batch_size": d.batch_size}
    runs: dict[str, list] = {"train": [], "bare": [], "whole": []}
    with tempfile.TemporaryDirectory() as tmp:
        data = str(Path(tmp) / "states.npz")
        _run(_TRAIN, json.dumps(first_round), data)  # the data for the bare loop (not timed)
        for r in range(rounds):
            runs["train"].append(_run(_TRAIN, json.dumps(first_round)))
            runs["bare"].append(_run(_BARE, data, json.dumps(spec)))
            print(f"round {r}: train {json.dumps(runs['train'][-1])}, bare {json.dumps(runs['bare'][-1])}",
                  flush=True)
        runs["whole"].append(_run(_TRAIN, json.dumps({})))
    train, bare = _best(runs["train"], "cold"), _best(runs["bare"], "cold")
    warm, bare_epochs = _best(runs["train"], "warm"), _best(runs["bare"], "epochs")
    return {"settings_timed": {**DEFAULT_TRAINING.to_json(), "refine": 0}, "bare_loop": spec,
            "cold_cpu_seconds": train["cold"], "warm_cpu_seconds": warm["warm"],
            "bare_cold_cpu_seconds": bare["cold"], "bare_epochs_cpu_seconds": bare_epochs["epochs"],
            "ratio_cold": train["cold"] / bare["cold"], "ratio_warm": warm["warm"] / bare_epochs["epochs"],
            "whole_default": {"settings": DEFAULT_TRAINING.to_json(),
                              "cold_cpu_seconds": runs["whole"][0]["cold"],
                              "warm_cpu_seconds": runs["whole"][0]["warm"]},
            "loads": [r["load"] for kind in ("train", "bare") for r in runs[kind]], "runs": runs}


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def measure_sweep(out_dir: Path) -> dict:
    """``learnest reproduce table1 --jobs 2 --force`` in a subprocess: wall and CPU seconds
    (children included), the load, and the table's cells against the paper."""
    cmd = [sys.executable, "-m", "learnest_codegen.cli", "reproduce", "table1", "--jobs", "2",
           "--out", str(out_dir), "--force"]
    load, cpu0, wall = os.getloadavg(), _children_cpu(), time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, cwd=ROOT,
                   env={**os.environ, "PYTHONPATH": str(ROOT)})
    summary = json.loads((out_dir / "summary.json").read_text())
    return {"command": "learnest reproduce table1 --jobs 2 --force",
            "wall_seconds": time.perf_counter() - wall, "cpu_seconds": _children_cpu() - cpu0,
            "load_at_start": list(load), "load_at_end": list(os.getloadavg()), "summary": summary}


def measure(args) -> tuple[dict, dict]:
    cond = figures.conditions(model="the default training (learnest_codegen.config.DEFAULT_TRAINING)",
                              run="cartpole seed 0, 10 s at 500 Hz (the demo's training run)",
                              settings="fresh processes, one torch thread, alternating; "
                                       "shortest CPU time kept")
    figs = {"training": measure_training(args.rounds)}
    if args.sweep:
        with tempfile.TemporaryDirectory() as tmp:
            figs["table1"] = measure_sweep(args.sweep_out or Path(tmp) / "table1")
    return figs, cond


def render_cost(data: dict) -> str:
    t = data["figures"]["training"]
    m = data["conditions"]["machine"]
    loads = t["loads"]
    return "\n".join([
        "| CPU seconds | `ln.train` (observer + one round) | bare torch loop | ratio |", "|---|---|---|---|",
        f"| cold (fresh process) | {t['cold_cpu_seconds']:.2f} | {t['bare_cold_cpu_seconds']:.2f} | "
        f"{t['ratio_cold']:.2f} |",
        f"| warm (second call) / the loop's epochs | {t['warm_cpu_seconds']:.2f} | "
        f"{t['bare_epochs_cpu_seconds']:.2f} | {t['ratio_warm']:.2f} |",
        f"| cold call / the loop's epochs | {t['cold_cpu_seconds']:.2f} | "
        f"{t['bare_epochs_cpu_seconds']:.2f} | {t['cold_cpu_seconds'] / t['bare_epochs_cpu_seconds']:.2f} |",
        "",
        "`ln.train` trains three initialisations (stacked) and scores each by the likelihood, and a round "
        "stops 50 epochs after its best; the bare loop trains one net for 250 epochs.",
        "",
        f"The whole default (every round): {t['whole_default']['cold_cpu_seconds']:.2f} s cold, "
        f"{t['whole_default']['warm_cpu_seconds']:.2f} s warm. {m['cpu']}, {m['cores']} cores, load "
        f"{min(loads):.1f}-{max(loads):.1f} during the runs; {data['conditions']['date']}, commit "
        f"{data['conditions']['commit']}."])


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser)
    print(json.dumps(measure(parser.parse_args())[0], indent=1))
