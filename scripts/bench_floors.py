"""The accuracy floor of the default training: held-out MSE of the KNODE estimators it gives.

A floor suite of four systems: the cartpole demo's runs, the ground robot, the README's
own-system pendulum (``my_pendulum.py``, read from ``docs/guide/own_system.md``) and the
DC-motor-driven inertia-wheel pendulum ``examples/systems/wheel_pendulum.py`` (3 states, two
outputs, a torque constant 20 % off and unmodelled friction). Case ``s`` of a system simulates
its training run with seed ``2 s`` and its test run with seed ``2 s + 1`` and trains with
``TrainingSettings.seed = 2 s`` (case 0 is the demo's seeds 0/1); every case trains with the
default of the code measured (``ln.train(run, system)``, nothing passed) in a fresh process, and
today's compiled estimators score it on the test run: the KNODE UKF (``ukf``) and the KNODE MHE
(the embedded ``mhe_gn``, which solves the Ipopt MHE's problem to the same minimiser), beside the
nominal and true-dynamics ones for the share of the gap closed.

The reference code (``--reference``, by default :data:`REFERENCE`, unpacked with ``git archive``)
trains the same cases in the same session: its MSE is the floor, the standard deviation of its
MSE over the cases the margin. A floor holds when the mean over the cases of today's default is
at most the reference's mean plus that margin, for each system and estimator
(``tests/test_floors.py`` checks it with the same cases). ``--variants`` also trains settings
that differ from today's default in one thing each (the ablation, :data:`VARIANTS`).

    python scripts/bench.py floors                       # floors, default, ablation on case 0
    python scripts/bench.py floors --variants default    # the floors and the default only
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import figures

MINUTES = 30
ORDER = 30
ROOT = figures.ROOT
OUT = ROOT / "build" / "bench" / "floors"
#: The code whose default training set the floors.
REFERENCE = "5686e62"
#: Cases per system (``s = 0 .. CASES - 1``: training run ``2 s``, test run ``2 s + 1``).
CASES = 3
#: The floor suite: name -> the system (a built-in name or a path under the checkout; the
#: README's pendulum is written out from the guide's first code block).
SYSTEMS = {"cartpole": "cartpole", "ground_robot": "ground_robot", "my_pendulum": "my_pendulum.py",
           "wheel_pendulum": "examples/systems/wheel_pendulum.py"}
ESTIMATORS = {"mhe": "mhe_gn", "ukf": "ukf"}
#: Ablation: settings that differ from today's default in one thing each (``replace`` of
#: ``DEFAULT_TRAINING``); ``default`` is the default itself, ``full_batch`` the full-batch
#: recipe of one initialisation with no weight average and no patience.
VARIANTS: dict[str, dict] = {
    "default": {},
    "float64": {"precision": "float64"},
    "one_restart": {"restarts": 1},
    "no_weight_average": {"weight_average": 0.0},
    "no_weight_decay": {"weight_decay": 0.0},
    "no_patience": {"patience": None},
    "patience_25": {"patience": 25},
    "one_round": {"refine": 0},
    "full_batch": {"batch_size": 1_000_000, "weight_average": 0.0, "restarts": 1, "patience": None},
}

#: Trains one case in the code on PYTHONPATH: its default (the reference code has no
#: DEFAULT_TRAINING: its ``ln.train`` default is QUICK_TRAINING) with ``overrides``.
_TRAIN = r"""
import json, sys, time
from dataclasses import replace
spec = json.loads(sys.argv[1])
cpu = time.process_time()
import learnest_codegen as ln
from learnest_codegen import config
system = ln.get_system(spec["system"])
if spec.get("chains") and not system.kinematic_chains:  # code that cannot infer them: declared
    from learnest_codegen.systems.base import KinematicChain
    system = replace(system, kinematic_chains=tuple(KinematicChain(o, tuple(s)) for o, s in spec["chains"]))
run = ln.simulate(system, spec["train_seed"])
base = getattr(config, "DEFAULT_TRAINING", None) or config.QUICK_TRAINING
settings = replace(base, seed=spec["train_seed"], **spec["overrides"])
model = ln.train(run, system, settings, progress=False)
model.save(spec["out"])
info = json.dumps({"cpu_seconds": time.process_time() - cpu, "observer": model.meta["observer"],
                   "settings": settings.to_json()})
open(spec["info"], "w").write(info)
print(info)
"""


def add_arguments(parser) -> None:
    parser.add_argument("--reference", default=REFERENCE, help="the code whose default sets the floors")
    parser.add_argument("--cases", type=int, default=CASES, help="cases per system")
    parser.add_argument("--systems", default=",".join(SYSTEMS), help="systems of the suite")
    parser.add_argument("--variants", default="all",
                        help=f"today's settings to train, of {','.join(VARIANTS)} or 'all'")
    parser.add_argument("--variant-cases", type=int, default=1,
                        help="cases per system of the variants other than the default")
    parser.add_argument("--train-only", action="store_true",
                        help="train and score the variants' cases only (not the reference's), for a later "
                             "--keep run to gather")
    parser.add_argument("--gather", action="store_true",
                        help="with --keep: gather the cases earlier runs trained and scored, train none")
    parser.add_argument("--jobs", type=int, default=2, help="cases trained at once")
    parser.add_argument("--keep", action="store_true", help="reuse models already trained in build/")


def system_path(name: str, where: Path) -> str:
    """The system of the suite as ``get_system`` takes it; the README's pendulum written to
    ``where`` from the guide's first code block."""
    spec = SYSTEMS[name]
    if name == "my_pendulum":
        text = (ROOT / "docs" / "guide" / "own_system.md").read_text()
        code = re.search(r"```python\n(# my_pendulum.py\n.*?)```", text, re.S).group(1)
        path = where / "my_pendulum.py"
        path.write_text(code)
        return str(path)
    return spec if "/" not in spec else str(ROOT / spec)


def _python(tree: Path, code: str, *args: str, cwd: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    done = subprocess.run([sys.executable, "-c", code, *args], cwd=cwd, env=env, capture_output=True,
                          text=True)
    if done.returncode:
        raise RuntimeError(f"{code[:40]!r} in {tree} failed: {done.stderr.strip()[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def train_case(tree: Path, system: str, seed: int, overrides: dict, out: Path, keep: bool,
               chains: list | None = None) -> dict:
    """Train case ``seed`` in the code at ``tree`` (a fresh process); the model goes to ``out``."""
    info = out.parent / f"{out.name}.json"
    if keep and (out / "model.json").exists():
        if info.exists():
            return json.loads(info.read_text())
        meta = json.loads((out / "model.json").read_text())  # its process was cut off: no CPU time
        return {"cpu_seconds": None, "observer": meta["observer"], "settings": meta["training"]}
    out.parent.mkdir(parents=True, exist_ok=True)
    started = out.parent / f"{out.name}.started"
    if keep and started.exists():  # another run of this benchmark is training it: wait for it
        while not info.exists():
            time.sleep(10)
        return json.loads(info.read_text())
    started.touch()
    spec = {"system": system, "train_seed": 2 * seed, "overrides": overrides, "out": str(out),
            "chains": chains, "info": str(info)}
    return _python(tree, _TRAIN, json.dumps(spec), cwd=out.parent)


def score(model, system, seed: int, compiled: Path) -> dict:
    """MSE over every state of each estimator of ``model`` on case ``seed``'s test run."""
    import learnest_codegen as ln

    test = ln.simulate(system, 2 * seed + 1)
    out = {}
    for key, name in ESTIMATORS.items():
        est = ln.make_estimator(ln.resolve(model, system), name, out=compiled)
        out[key] = float(ln.evaluate(est, test).mse(test.x))
    return out


def _score_case(system: str, seed: int, model_dir: Path) -> dict:
    code = ("import json, sys; sys.path.insert(0, sys.argv[4]); import bench_floors as b; "
            "import learnest_codegen as ln; s = ln.get_system(sys.argv[1]); "
            "print(json.dumps(b.score(sys.argv[2], s, int(sys.argv[3]), b.Path(sys.argv[2]).parent / "
            "'compiled')))")
    return _python(ROOT, code, system, str(model_dir), str(seed), str(ROOT / "scripts"), cwd=model_dir.parent)


def gap_closed(mse: float, nominal: float, true: float) -> float:
    return (nominal - mse) / (nominal - true)


def summarise(values: list[float]) -> dict:
    import numpy as np

    a = np.asarray(values, float)
    spread = float(a.std(ddof=1)) if len(a) > 1 else 0.0
    return {"per_case": a.tolist(), "mean": float(a.mean()), "std": spread, "worst": float(a.max())}


def measure(args) -> tuple[dict, dict]:
    import learnest_codegen as ln

    variants = list(VARIANTS) if args.variants == "all" else [v for v in args.variants.split(",") if v]
    systems = [s for s in args.systems.split(",") if s]
    cond = figures.conditions(
        model="KNODE residual trained by ln.train(run, system) with each code's default, one fresh process "
              "per case",
        run=f"{args.cases} cases per system: training run 2s, test run 2s+1, training seed 2s",
        settings=f"reference code {args.reference} (git archive) and this checkout in the same session; "
                 f"estimators {ESTIMATORS} compiled by this checkout", jobs=args.jobs)
    OUT.mkdir(parents=True, exist_ok=True)
    reference = OUT / f"code_{args.reference}"
    if not (reference / "learnest_codegen").is_dir():
        reference.mkdir(parents=True, exist_ok=True)
        archive = subprocess.run(["git", "archive", args.reference], cwd=ROOT, capture_output=True,
                                 check=True).stdout
        subprocess.run(["tar", "-x", "-C", str(reference)], input=archive, check=True)
    paths = {name: system_path(name, OUT) for name in systems}
    # the nominal and true-dynamics estimators, once per system and test run (before any job)
    cache = OUT / "references.json"  # with --keep: scored once per system and case
    stored = json.loads(cache.read_text()) if args.keep and cache.exists() else {}
    references: dict = {}
    for name in systems:
        system = ln.get_system(paths[name])
        for seed in range(args.cases):
            for kind in ("nominal", "true"):
                key = f"{name}/{seed}/{kind}"
                if key not in stored:
                    stored[key] = score(kind, system, seed, OUT / "compiled" / name)
                references.setdefault(name, {}).setdefault(kind, []).append(stored[key])
        print(f"{name}: nominal and true-dynamics estimators scored", flush=True)
    cache.write_text(json.dumps(stored))
    # the reference code reads kinematic chains only where a system declares them: it is given
    # the chains this checkout reads from the equations, so both train on the same observer
    chains = {}
    for name in systems:
        from learnest_codegen.observers.kinematic import inferred_chains

        system = ln.get_system(paths[name])
        declared = system.kinematic_chains or inferred_chains(system)
        chains[name] = [[c.output, list(c.states)] for c in declared]
    trees = [("reference", reference, {})] + [(v, ROOT, VARIANTS[v]) for v in variants]
    # the floors and the default first, case by case; then the other variants' cases
    ablation = min(args.cases, args.variant_cases)
    jobs = [(label, tree, name, seed, overrides) for seed in range(args.cases) for name in systems
            for label, tree, overrides in trees if label in ("reference", "default")]
    jobs += [(label, tree, name, seed, overrides) for seed in range(ablation) for name in systems
             for label, tree, overrides in trees if label not in ("reference", "default")]

    def run(job):
        label, tree, name, seed, overrides = job
        model_dir = OUT / "models" / label / name / f"case_{seed}"
        start = time.perf_counter()
        info = train_case(tree, paths[name], seed, overrides, model_dir, args.keep,
                          chains[name] if label == "reference" else None)
        scored = model_dir.parent / f"{model_dir.name}.score.json"
        if args.keep and scored.exists():
            mse = json.loads(scored.read_text())
        else:
            mse = _score_case(paths[name], seed, model_dir)
            scored.write_text(json.dumps(mse))
        cpu = info["cpu_seconds"] or float("nan")
        print(f"{label} {name} case {seed}: {json.dumps(mse)} ({cpu:.1f} s CPU training, "
              f"{time.perf_counter() - start:.0f} s, load {os.getloadavg()[0]:.1f})", flush=True)
        return label, name, seed, info, mse

    if args.train_only:
        jobs = [job for job in jobs if job[0] != "reference"]
    if args.gather:  # only what earlier runs left, trained and scored
        jobs = [job for job in jobs
                if (OUT / "models" / job[0] / job[2] / f"case_{job[3]}.score.json").exists()]
    results: dict = {}
    with ThreadPoolExecutor(args.jobs) as pool:
        for label, name, seed, info, mse in pool.map(run, jobs):
            results.setdefault(label, {}).setdefault(name, {})[seed] = {"training": info, "mse": mse}
    if args.train_only:
        return {}, cond
    figs = {"reference": args.reference, "cases": args.cases, "estimators": ESTIMATORS,
            "systems": {name: paths[name].replace(str(ROOT) + "/", "").replace(str(OUT) + "/", "")
                        for name in systems},
            "references": {}, "floors": {}, "variants": {}}
    for name in systems:
        nominal, true = references[name]["nominal"], references[name]["true"]
        figs["references"][name] = {kind: {est: summarise([c[est] for c in references[name][kind]])
                                           for est in ESTIMATORS} for kind in ("nominal", "true")}
        for label, per in results.items():
            if name not in per:
                continue
            rows, cases = {}, sorted(per[name])
            for est in ESTIMATORS:
                values = [per[name][s]["mse"][est] for s in cases]
                gaps = [gap_closed(v, nominal[c][est], true[c][est]) for v, c in zip(values, cases)]
                rows[est] = {"mse": summarise(values), "gap_closed": summarise(gaps)}
            cpu = [per[name][s]["training"]["cpu_seconds"] for s in cases]
            rows["train_cpu_seconds"] = summarise([c for c in cpu if c is not None] or [float("nan")])
            rows["cases"] = len(cases)
            rows["observer"] = per[name][0]["training"]["observer"]
            target = figs["floors"] if label == "reference" else figs["variants"]
            if label == "reference":
                target[name] = rows
            else:
                target.setdefault(label, {})[name] = rows
    figs["holds"] = holds(figs)
    if not args.keep:
        shutil.rmtree(OUT / "models", ignore_errors=True)
    return figs, cond


def holds(figs: dict, variant: str = "default") -> dict:
    """Per system and estimator: does ``variant``'s mean MSE stay within the floor (the
    reference's mean) plus its margin (the reference's standard deviation over the cases)?"""
    out = {}
    for name, floor in figs["floors"].items():
        got = figs["variants"].get(variant, {}).get(name)
        if got is None:
            continue
        out[name] = {est: got[est]["mse"]["mean"] <= floor[est]["mse"]["mean"] + floor[est]["mse"]["std"]
                     for est in ESTIMATORS}
    return out


def render_table(data: dict, variant: str = "default") -> str:
    """The floor table: per system and estimator the reference's MSE (mean and spread over the
    cases) against today's default, and the share of the gap each closes."""
    f = data["figures"]
    lines = [f"| system | estimator | {f['reference']} MSE (mean +- std) | default MSE (mean +- std) | "
             f"gap closed {f['reference']} / default | holds |", "|---|---|---|---|---|---|"]
    for name, floor in f["floors"].items():
        got = f["variants"][variant][name]
        for est in ESTIMATORS:
            a, b = floor[est], got[est]
            ok = b["mse"]["mean"] <= a["mse"]["mean"] + a["mse"]["std"]
            lines.append(f"| {name} | KNODE-{est.upper()} | "
                         f"{a['mse']['mean']:.3e} +- {a['mse']['std']:.1e} | "
                         f"{b['mse']['mean']:.3e} +- {b['mse']['std']:.1e} | "
                         f"{100 * a['gap_closed']['mean']:.2f} / {100 * b['gap_closed']['mean']:.2f} % | "
                         f"{'yes' if ok else 'no'} |")
    return "\n".join(lines)


def render_demo(data: dict) -> str:
    """The cartpole's first case, the demo's runs (seeds 0/1): each KNODE estimator's MSE and
    share of the gap closed, the reference code's default against today's."""
    f = data["figures"]
    floor, got = f["floors"]["cartpole"], f["variants"]["default"]["cartpole"]
    lines = [f"| estimator | {f['reference']} MSE | default MSE | {f['reference']} gap closed | "
             "default gap closed |", "|---|---|---|---|---|"]
    for est in ESTIMATORS:
        a, b = floor[est]["mse"]["per_case"][0], got[est]["mse"]["per_case"][0]
        ga, gb = floor[est]["gap_closed"]["per_case"][0], got[est]["gap_closed"]["per_case"][0]
        lines.append(f"| KNODE-{est.upper()} | {a:.3e} | {b:.3e} | {100 * ga:.2f} % | {100 * gb:.2f} % |")
    n = f["references"]["cartpole"]["nominal"]
    lines.append(f"\nNominal MHE {n['mhe']['per_case'][0]:.3e}, nominal UKF {n['ukf']['per_case'][0]:.3e} "
                 "on the same test run.")
    return "\n".join(lines)


def _mean(summary: dict, cases: int) -> float:
    values = summary["per_case"][:cases]
    return sum(values) / len(values)


def render_ablation(data: dict) -> str:
    """On the cases every variant ran (the first ``n`` of each system): each variant's mean MSE
    relative to the reference's on the same cases, per system and estimator, and its training CPU
    seconds per system (mean per case); "-" where it was not measured."""
    f = data["figures"]
    systems = list(f["floors"])
    n = {s: min(per[s]["cases"] for per in f["variants"].values() if s in per) for s in systems}
    head = " | ".join(f"{s} {e.upper()}" for s in systems for e in ESTIMATORS)
    lines = [f"| variant | {head} | training CPU s ({' / '.join(systems)}) |",
             "|---|" + "---|" * (len(systems) * len(ESTIMATORS) + 1)]
    rows = [*f["variants"].items(), (f"{f['reference']} default", f["floors"])]
    for label, per in rows:
        cells = [f"{_mean(per[s][e]['mse'], n[s]) / _mean(f['floors'][s][e]['mse'], n[s]):.2f}"
                 if s in per else "-" for s in systems for e in ESTIMATORS]
        cpu = " / ".join(f"{_mean(per[s]['train_cpu_seconds'], n[s]):.1f}" if s in per else "-"
                         for s in systems)
        lines.append(f"| {label} | {' | '.join(cells)} | {cpu} |")
    return "\n".join(lines)


if __name__ == "__main__":  # one-off runs: python scripts/bench_floors.py [options]
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_arguments(parser)
    parser.add_argument("--out", type=Path, default=None, help="write the JSON here too")
    args = parser.parse_args()
    figs, cond = measure(args)
    text = json.dumps({"figures": figs, "conditions": figures.finish(cond)}, indent=1)
    if args.out:
        args.out.write_text(text)
    print(text[:4000])

