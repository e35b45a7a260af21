"""The cost of the default training as a user meets it: cold and warm CPU seconds of ``ln.train``
on the demo run, beside a bare torch loop of the same net size on the same data.

Every figure comes from fresh processes, one torch thread each, run alternately in the same
minutes (``--rounds`` times; the shortest CPU time of each kind is kept, and every run's load
is recorded):

* ``train``: in a fresh process, ``import learnest_codegen``, simulate the demo's training run
  (cartpole, seed 0), then time ``ln.train(run, system, settings)`` twice: the first call is
  the cold one (it imports torch and pays every first-call set-up), the second the warm one.
  ``settings`` is ``replace(DEFAULT_TRAINING, refine=0, restarts=1, patience=None)``: the
  pre-training observer, then one net of the default's size trained for all 250 epochs in the
  default's batches, weight average, weight decay and precision, with its validation every
  epoch. This is the observer plus 250 epochs, the work the bare loop's 250 epochs are
  compared with.
* ``bare``: in a fresh process, ``import torch``, read the same observer's states and train one
  plain ``torch.nn.Sequential`` MLP of the default net's size (features in, hidden width,
  outputs) and structure (the same features, input correction and gains on the prior's
  accelerations), on the default's training pairs (the first 80 % of the run's pairs and their
  mirror images), in its batches, precision and optimiser (``torch.optim.AdamW``, rate and
  weight decay), for 250 epochs, on the one-step RK4 loss. It does nothing else: no
  validation, no weight average, no early stop. Timed cold (its imports included) and its
  epochs alone (after one optimiser step on a throwaway parameter, so that the epochs do not
  pay ``torch.optim``'s first-use imports).

Measured once each, after the alternating rounds, for what the default itself costs: its first
round as it runs (``refine=0``: three initialisations stacked, stopped 50 epochs after the best,
the likelihood's choice), the same three for all 250 epochs (``patience=None``), and the whole
default (every round).

The ratios are same-minute ratios: the cold and the warm ``train`` against the bare loop's
epochs, and the cold ``train`` against the cold bare loop. Table I's sweep has its own
benchmark (``python scripts/bench.py table1``).

    python scripts/bench.py training
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import figures

MINUTES = 5
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
out["epochs_run"] = len(model.meta["loss_history"])
if len(sys.argv) > 2:  # the observer's states and the net's structure, for the bare loop
    from learnest_codegen.observers import observe
    import numpy as np
    net = model.net
    signs = system.reflection_signs()
    np.savez(sys.argv[2], zeta=observe(run, system).zeta, u=run.u, dt=run.dt,
             inputs=[i for i in net.inputs if i not in net.periodic],
             periodic=[i for i in net.periodic if i in net.inputs], prior_features=list(net.prior_features),
             outputs=list(net.outputs), via=list(net.via), prior_gains=net.prior_gains,
             channels=net.channels, mean=net.in_mean.numpy(), scale=net.in_scale.numpy(),
             state_signs=signs[0], input_signs=signs[1])
out["final_loss"] = model.meta["final_loss"]
print(json.dumps(out))
"""

#: One fresh process: a bare torch loop of the same work on the same pairs.
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
zeta, u, dt = data["zeta"], data["u"], float(data["dt"])
n_train = len(zeta) - 1 - int(spec["validation_fraction"] * (len(zeta) - 1))
x, v, x_next = zeta[:n_train], u[:n_train], zeta[1:n_train + 1]
sx, su = data["state_signs"], data["input_signs"]  # the mirror image of every training pair
x, v, x_next = np.vstack([x, x * sx]), np.vstack([v, v * su]), np.vstack([x_next, x_next * sx])
x, v, step = (torch.as_tensor(a, dtype=dtype) for a in (x, v, x_next - x))
keep, periodic, extra, outputs, via = (torch.as_tensor(data[k], dtype=torch.long)
                                       for k in ("inputs", "periodic", "prior_features", "outputs", "via"))
mean, scale = (torch.as_tensor(data[k], dtype=dtype) for k in ("mean", "scale"))
channels, gains = int(data["channels"]), bool(data["prior_gains"])
n_out = channels * (1 + len(extra)) if gains else channels


def f(mlp, x, v):  # the prior plus the net, as the default's net acts
    xu, prior = torch.cat([x, v], dim=1), system.f(x, v)
    angles = xu[:, periodic]
    feats = torch.cat([xu[:, keep], torch.sin(angles), torch.cos(angles), prior[:, extra]], dim=1)
    out = mlp((feats - mean) / scale)
    c = out[:, :channels]
    if gains:  # each channel plus learned gains times the scaled prior features
        g = out[:, channels:].reshape(-1, channels, len(extra))
        c = c + (g * (prior[:, extra] / scale[-len(extra):])[:, None, :]).sum(dim=2)
    if len(via):  # the net corrects the inputs
        return system.f(x, v.index_add(1, via, c))
    return prior.index_add(1, outputs, c)


def increment(mlp, x, v):
    k1 = f(mlp, x, v)
    k2 = f(mlp, x + dt / 2 * k1, v)
    k3 = f(mlp, x + dt / 2 * k2, v)
    k4 = f(mlp, x + dt * k3, v)
    return dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


spare = torch.nn.Parameter(torch.zeros(1))  # torch.optim's first-use imports, before the epochs
spare.grad = torch.zeros(1)
torch.optim.AdamW([spare], lr=spec["learning_rate"], weight_decay=spec["weight_decay"]).step()
ready = time.process_time()
for net in range(spec["nets"]):
    torch.manual_seed(net)
    mlp = torch.nn.Sequential(torch.nn.Linear(len(mean), spec["hidden"]), torch.nn.Tanh(),
                              torch.nn.Linear(spec["hidden"], n_out)).to(dtype)
    optimiser = torch.optim.AdamW(mlp.parameters(), lr=spec["learning_rate"],
                                  weight_decay=spec["weight_decay"])
    generator = torch.Generator().manual_seed(net)
    for epoch in range(spec["epochs"]):
        for idx in torch.randperm(len(x), generator=generator).split(spec["batch_size"]):
            optimiser.zero_grad()
            loss = ((increment(mlp, x[idx], v[idx]) - step[idx]) ** 2).sum(dim=1).mean()
            loss.backward()
            optimiser.step()
done = time.process_time()
print(json.dumps({"load": os.getloadavg()[0], "cold": done - start, "epochs": done - ready,
                  "final_loss": float(loss)}))
"""

#: What the bare loop does, stated in the figures beside its times.
BARE_LOOP = ("one plain torch.nn.Sequential MLP of the default net's size and structure (its features, "
             "input correction and gains), on the default's training pairs (the first 80 % of the run's "
             "pairs and their mirror images), in its batches and precision, with torch.optim.AdamW at its "
             "rate and weight decay, for 250 epochs, on the one-step RK4 loss; no validation, weight "
             "average or early stop")
#: What ``ln.train`` is timed on against the bare loop: the observer plus 250 epochs of one net.
TIMED = {"refine": 0, "restarts": 1, "patience": None}
#: The default's own work, each timed once after the rounds: its first round as it runs, the same
#: three initialisations for every epoch, and every round.
ONCE = {"first_round": {"refine": 0}, "first_round_250_epochs": {"refine": 0, "patience": None},
        "whole_default": {}}


def add_arguments(parser) -> None:
    parser.add_argument("--rounds", type=int, default=3, help="fresh processes of each kind, alternating")


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
    from dataclasses import replace

    from learnest_codegen.config import DEFAULT_TRAINING

    d = replace(DEFAULT_TRAINING, **TIMED)
    spec = {"nets": 1, "precision": d.precision, "validation_fraction": d.validation_fraction,
            "hidden": d.network.hidden, "learning_rate": d.learning_rate, "weight_decay": d.weight_decay,
            "epochs": d.epochs, "batch_size": d.batch_size}
    runs: dict[str, list] = {"train": [], "bare": []}
    with tempfile.TemporaryDirectory() as tmp:
        data = str(Path(tmp) / "states.npz")
        _run(_TRAIN, json.dumps(TIMED), data)  # the data for the bare loop (not timed)
        for r in range(rounds):
            runs["train"].append(_run(_TRAIN, json.dumps(TIMED)))
            runs["bare"].append(_run(_BARE, data, json.dumps(spec)))
            print(f"round {r}: train {json.dumps(runs['train'][-1])}, bare {json.dumps(runs['bare'][-1])}",
                  flush=True)
    once = {}
    for name, change in ONCE.items():
        settings = {**DEFAULT_TRAINING.to_json(), **change}
        once[name] = {"settings": settings, **_run(_TRAIN, json.dumps(change))}
        print(f"{name}: {json.dumps(once[name])}", flush=True)
    train, bare = _best(runs["train"], "cold"), _best(runs["bare"], "cold")
    warm, bare_epochs = _best(runs["train"], "warm"), _best(runs["bare"], "epochs")
    return {"settings_timed": d.to_json(), "epochs_run": train["epochs_run"],
            "bare_loop": {**spec, "what": BARE_LOOP},
            "cold_cpu_seconds": train["cold"], "warm_cpu_seconds": warm["warm"],
            "bare_cold_cpu_seconds": bare["cold"], "bare_epochs_cpu_seconds": bare_epochs["epochs"],
            "ratio_cold_to_bare_epochs": train["cold"] / bare_epochs["epochs"],
            "ratio_warm_to_bare_epochs": warm["warm"] / bare_epochs["epochs"],
            "ratio_cold_to_bare_cold": train["cold"] / bare["cold"],
            "default": once, "loads": [r["load"] for kind in ("train", "bare") for r in runs[kind]],
            "runs": runs}


def measure(args) -> tuple[dict, dict]:
    cond = figures.conditions(model="the default training (learnest_codegen.config.DEFAULT_TRAINING)",
                              run="cartpole seed 0, 10 s at 500 Hz (the demo's training run)",
                              settings="fresh processes, one torch thread, alternating; "
                                       "shortest CPU time kept")
    return {"training": measure_training(args.rounds)}, cond


def render_cost(data: dict) -> str:
    t = data["figures"]["training"]
    m = data["conditions"]["machine"]
    loads, b, bare = t["loads"], t["bare_loop"], t["bare_epochs_cpu_seconds"]
    once = t["default"]
    return "\n".join([
        "| CPU seconds | `ln.train` (observer + 250 epochs) | bare torch loop (250 epochs) | ratio |",
        "|---|---|---|---|",
        f"| cold call / the loop's epochs | {t['cold_cpu_seconds']:.2f} | {bare:.2f} | "
        f"{t['ratio_cold_to_bare_epochs']:.2f} |",
        f"| warm call / the loop's epochs | {t['warm_cpu_seconds']:.2f} | {bare:.2f} | "
        f"{t['ratio_warm_to_bare_epochs']:.2f} |",
        f"| cold call / cold loop (imports included) | {t['cold_cpu_seconds']:.2f} | "
        f"{t['bare_cold_cpu_seconds']:.2f} | {t['ratio_cold_to_bare_cold']:.2f} |",
        "",
        f"`ln.train` ran the observer and {t['epochs_run']} epochs of one net (`refine=0, restarts=1, "
        f"patience=None`); the bare loop trains one net of the same size for {b['epochs']} epochs in batches "
        f"of {b['batch_size']} and does nothing else.",
        "",
        "| the default's own work | epochs (last round) | cold CPU s | warm CPU s |", "|---|---|---|---|",
        *(f"| {label} | {once[key]['epochs_run']} | {once[key]['cold']:.2f} | {once[key]['warm']:.2f} |"
          for key, label in (("first_round", "first round (three initialisations, patience 50)"),
                             ("first_round_250_epochs", "first round, every epoch (patience off)"),
                             ("whole_default", "every round (the default)"))),
        "",
        f"{m['cpu']}, {m['cores']} cores, load {min(loads):.1f}-{max(loads):.1f} during the alternating "
        "runs; "
        f"{data['conditions']['date']}, revision {data['conditions']['commit']}."])


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser)
    print(json.dumps(measure(parser.parse_args())[0], indent=1))
