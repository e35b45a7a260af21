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
"""

from __future__ import annotations

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
    """The grey-box prior fitted on the figure-eights, and the circle flight it is tested on."""
    from learnest_codegen.compilation import knode_model
    from learnest_codegen.experiments.quadrotor import StudySettings, flight_cases, trained_model
    from learnest_codegen.experiments.quadrotor_report import trajectory_type
    from learnest_codegen.recordings import data_root

    root = Path(data) if data else data_root()
    if root is None:
        raise SystemExit("bench cortex_m: no NanoBench flights found: pass --data DIR or set $LEARNEST_DATA")
    cases = flight_cases(root / "nanobench" if (root / "nanobench").is_dir() else root)
    train = [c for c in cases if trajectory_type(c.name) != trajectory_type(QUADROTOR_FLIGHT)]
    trained = trained_model(train, "linear_prior", out / "study", StudySettings(), out / "model",
                            progress=False)
    test = next(c for c in cases if c.name == QUADROTOR_FLIGHT)
    return knode_model(trained)[0], test.run, [c.name for c in train]


def generate(bc, model, run, out: Path, estimator: str, steps: int | None):
    """``examples/cortex_m``'s folder for ``estimator`` of ``model`` over ``run``."""
    from learnest_codegen.compilation import compile_estimators

    gen = compile_estimators(model, out, model_hash=f"bench-{model.kind}", estimators=(estimator,),
                             precision=PRECISION)[estimator]
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
    quad_model, quad_run, trained_on = quadrotor_model(getattr(args, "data", None), BUILD / "quadrotor")
    tools = {tool: subprocess.run([tool, "--version"], capture_output=True, text=True).stdout.splitlines()[0]
             for tool in ("arm-none-eabi-gcc", "qemu-system-arm")}
    partial = "" if not steps else f" (the first {steps} samples only: development)"
    cond = figures.conditions(
        model={"cartpole": f"the demo's trained KNODE cartpole ({model_dir.relative_to(figures.ROOT)})",
               "quadrotor": "the grey-box prior quadrotor_linear fitted on the figure-eight flights "
                            f"({', '.join(trained_on)})"},
        model_hash=cart_hash,
        run={"cartpole": f"cartpole seed 1 (the demo's test run), {len(cart_run.y)} samples{partial}",
             "quadrotor": f"the flight {QUADROTOR_FLIGHT}, {len(quad_run.y)} samples{partial}"},
        settings=f"each estimator as learnest-compile generates it ({PRECISION}, the system's horizon)",
        target=f"{MACHINE} (Cortex-M4F) in qemu-system-arm -icount shift=0,sleep=off; host loop gcc",
        tools=tools)
    rows = []
    for system, model, run in (("cartpole", cart_model, cart_run), ("quadrotor", quad_model, quad_run)):
        for estimator in bc.ESTIMATORS:  # the table's float32 estimators
            print(f"    {system} {estimator} {PRECISION} on {MACHINE}", flush=True)
            rows.append(measure_one(bc, model, run, BUILD / system / estimator, estimator, steps))
    return {"rows": rows, "clock_hz_assumed": CLOCK_HZ,
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
            f"{c['run']['cartpole']}. Quadrotor: {c['model']['quadrotor']}, {c['run']['quadrotor']}. "
            "Instruction counts do not depend on the host's load.")


if __name__ == "__main__":
    import bench

    sys.exit(bench.main(["cortex_m", *sys.argv[1:]]))
