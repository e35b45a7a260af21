"""Generated estimators on a Cortex-M4F in QEMU: instructions per step, flash, RAM and stack.

Two models, each estimator (the UKF, the EKF, ``mhe_rti`` and ``mhe_gn`` at the system's horizon) in
float32 (the M4F's FPU is single precision), generated as ``learnest-compile`` generates them
and run in ``examples/cortex_m``'s firmware loop (``mps2-an386``, ``-icount shift=0``: one
nanosecond of the virtual clock per executed instruction) and in the same loop built for the
host:

- the cartpole: the demo's trained KNODE model (``bench_demo.model_dir()``) over the demo's
  whole test run (seed 1, 5000 samples);
- the quadrotor: the grey-box prior fitted on the NanoBench figure-eight flights
  (``learnest reproduce quadrotor --features linear_prior``'s model of the leave-type-out fold
  that tests the circles), over the circle flight ``B2_circle_medium_rep1``.

Per build: instructions per step (mean, max, and max after the first step, which linearises
the whole window), the parity of QEMU and the host (largest relative difference, steps
bit-identical), the ``.text`` of the generated objects and the adapter ("estimator code"),
the firmware's flash without its run data, RAM (``.data + .bss``), the workspace, and the stack
(the deepest static chain of ``-fstack-usage`` frames and the measured high-water mark).

Beside them, the quadrotor's KNODE ``mhe_rti`` (N = 20, float32) on trained nets, counted step by
step over whole runs (mean, median, 99th percentile, worst step, worst step once the window is
full, steps above :data:`STEP_TARGET`):

- a net trained by the package's default training (``learnest_codegen.pipeline.train``) on the
  simulated quadrotor's seed-0 run, tested on its seed-1 run;
- when the NanoBench flights are there, the flights study's ``thrust`` KNODE model with a net of
  :data:`FLIGHT_UNITS` units (the study's training otherwise), trained on the figure-eights
  and tested on the circle flight.

Both trained models are kept in :data:`MODELS`, keyed on the package's code and the training.
"""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import figures
import numpy as np

MINUTES = 20
ORDER = 30
EXAMPLE = figures.ROOT / "examples" / "cortex_m"
BUILD = figures.ROOT / "build" / "bench" / "cortex_m"
PRECISION = "float32"
MACHINE = "mps2-an386"
QUADROTOR_FLIGHT = "B2_circle_medium_rep1"
MODELS = figures.ROOT / "build" / "bench" / "cortex_m_models"
KNODE_ESTIMATOR, KNODE_HORIZON = "mhe_rti", 20
TRAIN_SEED, TEST_SEED = 0, 1  # the simulated quadrotor's training and test runs
FLIGHT_UNITS = 8
#: instructions a step that leave 3x spare in the quadrotor's 10 ms period on the M4F
STEP_TARGET = 335_000
#: a 168 MHz Cortex-M4F taking 1.5 cycles an instruction: an assumption for the budget column,
#: not a measurement (QEMU counts instructions, not cycles)
CLOCK_HZ, CYCLES_PER_INSTRUCTION = 168e6, 1.5


def add_arguments(parser) -> None:
    parser.add_argument("--steps", type=int, default=None,
                        help="the first STEPS samples of each run only (development; default: the whole run)")
    parser.add_argument("--data", default=None,
                        help="the recordings' folder (default: $LEARNEST_DATA or ../shared/data)")


def example():
    return figures.load_file(EXAMPLE / "build_and_compare.py", "build_and_compare")


def quadrotor_model(data: str | None, out: Path):
    """The grey-box prior fitted on the figure-eights, and the circle flight it is tested on;
    ``None`` without the NanoBench flights."""
    from learnest_codegen.compilation import knode_model
    from learnest_codegen.experiments.quadrotor import StudySettings, flight_cases, trained_model
    from learnest_codegen.experiments.quadrotor_report import trajectory_type

    root = _nanobench(data)
    if root is None:
        return None
    cases = flight_cases(root)
    train = [c for c in cases if trajectory_type(c.name) != trajectory_type(QUADROTOR_FLIGHT)]
    trained = trained_model(train, "linear_prior", out / "study", StudySettings(), out / "model",
                            progress=False)
    test = next(c for c in cases if c.name == QUADROTOR_FLIGHT)
    return knode_model(trained)[0], test.run, [c.name for c in train]


def generate(bc, model, run, out: Path, estimator: str, steps: int | None, *, model_hash: str | None = None,
             horizon: int | None = None):
    """``examples/cortex_m``'s folder for ``estimator`` of ``model`` over ``run`` (its first
    ``steps`` samples; all when ``None``)."""
    from learnest_codegen.compilation import compile_estimators

    gen = compile_estimators(model, out, model_hash=model_hash or f"bench-{model.kind}",
                             estimators=(estimator,), precision=PRECISION, horizon=horizon)[estimator]
    T = min(steps or len(run.y), len(run.y))
    U, Y = run.u[:T], run.y[:T]
    bc.write_run_header(gen.directory / "run_data.h", U, Y, model.system.dt)
    bc.write_estimator_config(gen.directory / "estimator_config.h", gen.prefix, estimator=estimator,
                              precision=PRECISION)
    x0 = np.asarray(model.system.x0, dtype=float)
    return bc.Generated(gen.directory, gen.prefix, estimator, PRECISION, U, Y,
                        run.x[:T] if run.x is not None else None, x0,
                        bc.workspace_bytes(gen.header_path, gen.prefix)), gen


def measure_one(bc, model, run, out: Path, estimator: str, steps: int | None) -> dict:
    gen, generated = generate(bc, model, run, out / "gen", estimator, steps)
    build_dir = out / f"build_{estimator}"
    paths = bc.build(gen.directory, build_dir, machine=MACHINE)
    fw = bc.run_qemu(paths["elf"], model.nx, machine=MACHINE, timeout=3600)
    host = bc.run_host(paths["host"], model.nx)
    per_tick = 1e9 / fw.summary["tick_hz"]  # instructions per tick at -icount shift=0
    sections, objects = bc.section_sizes(paths["elf"]), bc.object_sizes(build_dir)
    generated_objects = {Path(s).stem + ".o" for s in generated.sources} | {"estimator.o"}
    run_bytes = 8 * len(gen.U) * (gen.U.shape[1] + gen.Y.shape[1])
    stack = bc.worst_stack_path(build_dir)
    rel = bc.relative_difference(fw.X, host.X)
    return {
        "system": model.system.name, "estimator": estimator, "precision": PRECISION,
        "horizon": generated.horizon, "steps": len(gen.Y), "status": fw.summary["status"],
        "instructions_per_step": {"mean": float(fw.busy_ticks.mean() * per_tick),
                                  "max": float(fw.busy_ticks.max() * per_tick),
                                  "max_after_first": float(fw.busy_ticks[1:].max(initial=0) * per_tick)},
        "qemu_vs_host": {"max_relative_difference": float(rel.max()),
                         "bit_identical_steps": int(np.all(fw.X == host.X, axis=1).sum())},
        "estimator_code_bytes": sum(v["text"] for k, v in objects.items() if k in generated_objects),
        "flash_bytes_without_run_data": sections["flash"] - run_bytes,
        "ram_bytes": sections["ram"], "workspace_bytes": gen.workspace_bytes,
        "stack_static_chain_bytes": stack["bytes"],
        "stack_static_chain": [name for name, _ in stack["path"]],
        "stack_peak_bytes": fw.summary["stack_peak_bytes"],
        "period_s": model.system.dt,
    }


def simulated_knode():
    """The quadrotor KNODE model of the default training on the seed-:data:`TRAIN_SEED` run
    (trained once per code and kept in :data:`MODELS`), and the seed-:data:`TEST_SEED` run."""
    import torch

    from learnest_codegen import get_system
    from learnest_codegen.config import DEFAULT_TRAINING
    from learnest_codegen.experiments.store import code_hash, content_hash
    from learnest_codegen.learning.model import load_model
    from learnest_codegen.pipeline import train
    from learnest_codegen.simulation import simulate

    system = get_system("quadrotor")
    directory = MODELS / f"quadrotor_seed{TRAIN_SEED}"
    key = content_hash({"code": code_hash(), "seed": TRAIN_SEED, "training": DEFAULT_TRAINING.to_json()})
    meta = directory / "model.json"
    if meta.is_file() and json.loads(meta.read_text()).get("bench_training") == key:
        model = load_model(directory, system)
    else:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # one thread: the same net on every machine
        try:
            model = train(simulate(system, seed=TRAIN_SEED), system, progress=False)
        finally:
            torch.set_num_threads(threads)
        model.meta["bench_training"] = key
        model.save(directory)
    return directory, simulate(system, seed=TEST_SEED)


def flight_knode(data: str | None):
    """The flights study's ``thrust`` KNODE model (a net of :data:`FLIGHT_UNITS` units) trained
    on the figure-eights, and the circle flight; ``None`` without the NanoBench flights."""
    from learnest_codegen.compilation import knode_model
    from learnest_codegen.config import NetworkSettings
    from learnest_codegen.experiments.quadrotor import StudySettings, flight_cases, trained_model
    from learnest_codegen.experiments.quadrotor_report import trajectory_type

    root = _nanobench(data)
    if root is None:
        return None
    cases = flight_cases(root)
    train = [c for c in cases if trajectory_type(c.name) != trajectory_type(QUADROTOR_FLIGHT)]
    study = StudySettings()
    settings = dataclasses.replace(study, training=dataclasses.replace(
        study.training, network=NetworkSettings(layers=2, hidden=FLIGHT_UNITS, activation="Tanh")))
    out = MODELS / f"flight_thrust_{FLIGHT_UNITS}"
    trained = trained_model(train, "thrust", out / "study", settings, out / "model", progress=False)
    test = next(c for c in cases if c.name == QUADROTOR_FLIGHT)
    return (*knode_model(trained), test.run, [c.name for c in train], settings)


def _nanobench(data: str | None) -> Path | None:
    from learnest_codegen.recordings import data_root

    root = Path(data) if data else data_root()
    if root is None:
        return None
    root = root / "nanobench" if (root / "nanobench").is_dir() else root
    return root if any(root.glob("*")) else None


def whole_run(bc, model, run, out: Path, model_hash: str) -> dict:
    """:data:`KNODE_ESTIMATOR` at N = :data:`KNODE_HORIZON` in float32 on the M4F over the whole
    ``run``, step by step."""
    _, gen = generate(bc, model, run, out / "gen", KNODE_ESTIMATOR, None, model_hash=model_hash,
                      horizon=KNODE_HORIZON)
    paths = bc.build(gen.directory, out / "build", machine=MACHINE)
    fw = bc.run_qemu(paths["elf"], model.nx, machine=MACHINE, timeout=3600)
    host = bc.run_host(paths["host"], model.nx)
    steps = fw.busy_ticks * (1e9 / fw.summary["tick_hz"])
    full = steps[KNODE_HORIZON:]  # the window holds N + 1 samples from step N on
    statuses, counts = np.unique(fw.status, return_counts=True)
    return {"estimator": KNODE_ESTIMATOR, "horizon": KNODE_HORIZON, "precision": PRECISION,
            "steps": int(len(steps)),
            "instructions_per_step": {
                "mean": float(steps.mean()), "p50": float(np.percentile(steps, 50)),
                "p99": float(np.percentile(steps, 99)), "max": float(steps.max()),
                "argmax": int(steps.argmax()), "max_window_full": float(full.max()),
                "argmax_window_full": int(KNODE_HORIZON + full.argmax()),
                "first": float(steps[0])},
            "steps_above_target": int((steps > STEP_TARGET).sum()),
            "statuses": {str(int(k)): int(v) for k, v in zip(statuses, counts)},
            "qemu_equals_host": bool(np.array_equal(fw.X, host.X)),
            "model_instructions": json.loads((gen.directory / "manifest.json").read_text())
            .get("model_instructions")}


def measure_knode(bc, data: str | None) -> tuple[list[dict], dict]:
    """The trained quadrotor nets' whole runs, and their conditions."""
    from learnest_codegen import get_system
    from learnest_codegen.compilation import resolve_model

    rows, cond = [], {}
    directory, run = simulated_knode()
    model, model_hash = resolve_model(get_system("quadrotor"), str(directory))
    print(f"    quadrotor KNODE (simulated, seed {TRAIN_SEED}) {KNODE_ESTIMATOR} over seed {TEST_SEED}",
          flush=True)
    rows.append({"model": "simulated", **whole_run(bc, model, run, BUILD / "knode_simulated", model_hash)})
    cond["simulated"] = {
        "model": "the quadrotor KNODE net of the default training "
                 f"(learnest_codegen.config.DEFAULT_TRAINING) on the simulated seed-{TRAIN_SEED} run "
                 f"({directory.relative_to(figures.ROOT)})",
        "model_hash": model_hash, "run": f"the simulated seed-{TEST_SEED} run, {len(run.y)} samples"}
    flight = flight_knode(data)
    if flight is None:
        print("    no NanoBench flights: the flight's row is left out", flush=True)
        return rows, cond
    model, model_hash, run, trained_on, settings = flight
    print(f"    quadrotor KNODE ({FLIGHT_UNITS} units, figure-eights) {KNODE_ESTIMATOR} over "
          f"{QUADROTOR_FLIGHT}", flush=True)
    rows.append({"model": "flight", **whole_run(bc, model, run, BUILD / "knode_flight", model_hash)})
    cond["flight"] = {
        "model": f"the flights study's thrust KNODE model ({model.system.name}, a net of one hidden layer "
                 f"of {FLIGHT_UNITS} tanh units; the study's training otherwise: "
                 f"{settings.training.epochs} epochs, observer {settings.observer}) "
                 f"trained on {', '.join(trained_on)}",
        "model_hash": model_hash, "run": f"the flight {QUADROTOR_FLIGHT}, {len(run.y)} samples"}
    return rows, cond


def measure(args) -> tuple[dict, dict]:
    import bench_demo

    from learnest_codegen import get_system
    from learnest_codegen.compilation import resolve_model
    from learnest_codegen.simulation import simulate

    bc = example()
    missing = bc.missing_tools()
    if missing:
        raise SystemExit(f"bench cortex_m: {', '.join(missing)} not found "
                         "(scripts/setup_tools.sh installs them)")
    steps = getattr(args, "steps", None)
    shutil.rmtree(BUILD, ignore_errors=True)  # make rebuilds nothing whose flags alone changed
    cartpole = get_system("cartpole")
    model_dir = bench_demo.model_dir()
    cart_model, cart_hash = resolve_model(cartpole, str(model_dir))
    cart_run = simulate(cartpole, seed=1)
    quadrotor = quadrotor_model(getattr(args, "data", None), BUILD / "quadrotor")
    tools = {tool: subprocess.run([tool, "--version"], capture_output=True, text=True).stdout.splitlines()[0]
             for tool in ("arm-none-eabi-gcc", "qemu-system-arm")}
    partial = "" if not steps else f" (the first {steps} samples only: development)"
    models = {"cartpole": f"the demo's trained KNODE cartpole ({model_dir.relative_to(figures.ROOT)})"}
    runs = {"cartpole": f"cartpole seed 1 (the demo's test run), {len(cart_run.y)} samples{partial}"}
    systems = [("cartpole", cart_model, cart_run)]
    if quadrotor is not None:
        quad_model, quad_run, trained_on = quadrotor
        models["quadrotor"] = ("the grey-box prior quadrotor_linear fitted on the figure-eight flights "
                               f"({', '.join(trained_on)})")
        runs["quadrotor"] = f"the flight {QUADROTOR_FLIGHT}, {len(quad_run.y)} samples{partial}"
        systems.append(("quadrotor", quad_model, quad_run))
    cond = figures.conditions(
        model=models, model_hash=cart_hash, run=runs,
        settings=f"each estimator as learnest-compile generates it ({PRECISION}, the system's horizon)",
        target=f"{MACHINE} (Cortex-M4F) in qemu-system-arm -icount shift=0,sleep=off; host loop gcc",
        tools=tools)
    rows = []
    for system, model, run in systems:
        for estimator in bc.ESTIMATORS:  # the table's float32 estimators
            print(f"    {system} {estimator} {PRECISION} on {MACHINE}", flush=True)
            rows.append(measure_one(bc, model, run, BUILD / system / estimator, estimator, steps))
    knode, cond["knode"] = measure_knode(bc, getattr(args, "data", None))
    return {"rows": rows, "knode": knode, "step_target": STEP_TARGET, "clock_hz_assumed": CLOCK_HZ,
            "cycles_per_instruction_assumed": CYCLES_PER_INSTRUCTION}, cond


# -- views -------------------------------------------------------------------------------------

def _budget(r: dict, data: dict) -> float:
    f = data["figures"]
    return r["instructions_per_step"]["mean"] * f["cycles_per_instruction_assumed"] / (
        f["clock_hz_assumed"] * r["period_s"])


def render_instructions(data: dict) -> str:
    """Instructions per step and QEMU against the host."""
    f = data["figures"]
    lines = ["| system | estimator | instructions per step: mean | max | max after the first step | "
             "share of the sample period* | QEMU vs host |", "|---|---|---:|---:|---:|---:|---|"]
    for r in f["rows"]:
        i, q = r["instructions_per_step"], r["qemu_vs_host"]
        parity = ("bit-identical on every step" if q["bit_identical_steps"] == r["steps"] else
                  f"{q['max_relative_difference']:.1e} relative, {q['bit_identical_steps']} of "
                  f"{r['steps']} steps bit-identical")
        lines.append(f"| {r['system']} | `{r['estimator']}`{_n(r)} | {i['mean']:,.0f} | {i['max']:,.0f} | "
                     f"{i['max_after_first']:,.0f} | "
                     f"{100 * _budget(r, data):.0f} % of {1e3 * r['period_s']:g} ms | "
                     f"{parity} |")
    return ("\n".join(lines) + f"\n\n\\* at {f['clock_hz_assumed'] / 1e6:g} MHz and "
            f"{f['cycles_per_instruction_assumed']:g} cycles an instruction: an assumption, not a "
            "measurement (QEMU counts instructions, not cycles).\n\n" + render_conditions(data))


def render_knode(data: dict) -> str:
    """The quadrotor's trained KNODE nets over whole runs, step by step."""
    f, c = data["figures"], data["conditions"]["knode"]
    target = f["step_target"]
    lines = ["| model | run | steps | mean | median | 99th percentile | worst step | worst once the window "
             f"is full | steps above {target:,} |", "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for r in f["knode"]:
        i, cr = r["instructions_per_step"], c[r["model"]]
        what = {"simulated": f"default training, simulated seed {TRAIN_SEED}",
                "flight": f"flights study, {FLIGHT_UNITS} units, figure-eights"}[r["model"]]
        lines.append(f"| {what} | {cr['run']} | {r['steps']:,} | {i['mean']:,.0f} | {i['p50']:,.0f} | "
                     f"{i['p99']:,.0f} | {i['max']:,.0f} (step {i['argmax']}) | {i['max_window_full']:,.0f} "
                     f"(step {i['argmax_window_full']}) | {r['steps_above_target']:,} |")
    notes = [f"{r['model']}: {c[r['model']]['model']}; model hash {c[r['model']]['model_hash'][:12]}; "
             f"QEMU {'equals' if r['qemu_equals_host'] else 'differs from'} the host on every step"
             for r in f["knode"]]
    return ("\n".join(lines) + "\n\n`mhe_rti` N = 20, float32, instructions per step on the M4F. "
            + ". ".join(notes) + ". Measured by `" + data["command"] + "` on "
            + data["conditions"]["date"] + ".")


def _n(r: dict) -> str:
    return f" N = {r['horizon']}" if r["horizon"] else ""


def render_footprint(data: dict) -> str:
    """Flash, RAM and stack of each build."""
    lines = ["| system | estimator | estimator code | flash without the run data | RAM (.data + .bss) | "
             "workspace | stack: deepest static chain | measured peak |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in data["figures"]["rows"]:
        lines.append(f"| {r['system']} | `{r['estimator']}`{_n(r)} | {r['estimator_code_bytes']:,} | "
                     f"{r['flash_bytes_without_run_data']:,} | {r['ram_bytes']:,} | "
                     f"{r['workspace_bytes']:,} | "
                     f"{r['stack_static_chain_bytes']:,} | {r['stack_peak_bytes']:,} |")
    return "\n".join(lines) + "\n\nBytes, float32 builds for the Cortex-M4F (`arm-none-eabi-size`)."


def render_conditions(data: dict) -> str:
    c = data["conditions"]
    return (f"Measured by `{data['command']}` on {c['date']}; {c['target']}; "
            f"{c['tools']['arm-none-eabi-gcc']}. Cartpole: {c['model']['cartpole']}, "
            f"{c['run']['cartpole']}. "
            + (f"Quadrotor: {c['model']['quadrotor']}, {c['run']['quadrotor']}. " if "quadrotor" in c["model"]
               else "Quadrotor: no NanoBench flights, left out. ")
            + "Instruction counts do not depend on the host's load.")


if __name__ == "__main__":
    import bench

    sys.exit(bench.main(["cortex_m", *sys.argv[1:]]))
