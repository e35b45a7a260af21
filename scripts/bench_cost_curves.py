"""How the cost of each estimator grows with the net, the state dimension and the horizon.

Four sweeps around the demo's configuration (the cartpole, a KNODE net of one hidden layer of 8
tanh units, N = 20), each changing one thing:

- **width**: one hidden layer of 8, 16, 32, 64, 128 units;
- **depth**: 1, 2, 3 hidden layers of 8 units;
- **states**: the cartpole (4 states), the quadrotor (9), the quadrotor with thrust and gyro
  biases ``quadrotor_bias`` (12), each with its default inputs and outputs;
- **horizon**: N = 10, 20, 50, 100 (the MHEs only).

The nets are untrained, seeded initialisations (``make_net`` with the sweep's
``NetworkSettings``): the instructions of a step do not depend on the weights' values, only
the number of Gauss-Newton iterations of ``mhe_gn`` does, which each row records. Each
estimator (``ukf``, ``mhe_rti``, ``mhe_gn``) is generated as ``learnest-compile`` generates it
and stepped over the system's simulated run (seed 1):

- **host**: float64, the plain C main of ``bench_callgrind`` built with the package's flags;
  instructions per sample ``(I(T0 + T) - I(T0)) / T`` under callgrind (samples ``T0`` to
  ``T0 + T``: past the first, which linearises the whole window);
- **Cortex-M4F**: float32 in ``examples/cortex_m``'s firmware loop under QEMU
  (``-icount shift=0``: one instruction a nanosecond), the mean instructions per step after the
  first, the flash without the run data and the RAM (``.data + .bss``) of the firmware.

The rule of thumb compares the M4F count with a 1 kHz loop on a 168 MHz M4F at 1.5 cycles an
instruction (``bench_cortex_m``'s assumption: 112,000 instructions a step).
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import figures

MINUTES = 30
ORDER = 35
BUILD = figures.ROOT / "build" / "bench" / "cost_curves"
PLOT = figures.FIGURES / "cost_curves.png"
#: (sweep, system, hidden layers, width, horizon) of every point, sweep by sweep
BASE = ("cartpole", 1, 8, 20)
SWEEPS = {
    "width": [("cartpole", 1, w, 20) for w in (8, 16, 32, 64, 128)],
    "depth": [("cartpole", d, 8, 20) for d in (1, 2, 3)],
    "states": [(s, 1, 8, 20) for s in ("cartpole", "quadrotor", "quadrotor_bias")],
    "horizon": [("cartpole", 1, 8, n) for n in (10, 20, 50, 100)],
}
#: the axis each sweep varies: its index in a point
AXIS = {"width": 2, "depth": 1, "states": 0, "horizon": 3}
SKIP, SAMPLES = 20, 200  # host: samples SKIP..SKIP+SAMPLES; the M4F loop runs SKIP+SAMPLES steps
LOOP_HZ = 1000


def add_arguments(parser) -> None:
    parser.add_argument("--samples", type=int, default=SAMPLES,
                        help=f"samples counted per build (default {SAMPLES})")
    parser.add_argument("--sweeps", default=",".join(SWEEPS),
                        help="the sweeps to run, comma-separated (development; default: all)")


def points(sweeps) -> list[tuple]:
    """Every distinct (system, hidden layers, width, horizon) of the sweeps, in order."""
    seen = []
    for name in sweeps:
        for p in SWEEPS[name]:
            if p not in seen:
                seen.append(p)
    return seen


def model_of(system_name: str, layers: int, width: int):
    import torch

    from learnest_codegen import get_system
    from learnest_codegen.config import NetworkSettings
    from learnest_codegen.export import hybrid_model
    from learnest_codegen.learning.training import make_net

    system = get_system(system_name)
    torch.manual_seed(0)
    return hybrid_model(system, make_net(system, NetworkSettings(layers=layers + 1, hidden=width)))


def host_count(bc, model, run, estimator: str, horizon: int | None, root: Path, T: int) -> dict:
    """float64 on the host: instructions per sample and mhe_gn's iterations."""
    from learnest_codegen.compilation import compile_estimators

    gen = compile_estimators(model, root / "host", model_hash="cost-curves", estimators=(estimator,),
                             horizon=horizon)[estimator]
    bc.write_run(root / "run_data.h", run.u[:SKIP + T], run.y[:SKIP + T])
    exe = bc.build(gen, root / "run_data.h", root)
    with ThreadPoolExecutor(2) as pool:
        before, after = pool.map(lambda n: bc.instructions(exe, n), (SKIP, SKIP + T))
    _, its, _ = bc.timed_run(exe, SKIP + T, model.nx)
    out = {"host_instructions": (after - before) / T, "host_code_bytes": gen.code_bytes}
    if estimator == "mhe_gn":
        out["iterations_mean"] = float(its[SKIP:].mean())
        out["iterations_max"] = int(its[SKIP:].max())
    return out


def m4f_count(cm, ex, model, run, estimator: str, horizon: int | None, root: Path, T: int) -> dict:
    """float32 on the Cortex-M4F in QEMU: instructions per step after the first, flash, RAM."""
    gen, _ = cm.generate(ex, model, run, root / "m4f", estimator, SKIP + T, model_hash="cost-curves",
                         horizon=horizon)
    U, Y = gen.U, gen.Y
    paths = ex.build(gen.directory, root / "m4f_build", machine=cm.MACHINE)
    fw = ex.run_qemu(paths["elf"], model.nx, machine=cm.MACHINE, timeout=3600)
    per_tick = 1e9 / fw.summary["tick_hz"]
    sections = ex.section_sizes(paths["elf"])
    return {"m4f_instructions": float(fw.busy_ticks[1:].mean() * per_tick),
            "m4f_instructions_max": float(fw.busy_ticks[1:].max() * per_tick),
            "m4f_status": int(fw.summary["status"]),
            "flash_bytes": sections["flash"] - 8 * len(U) * (U.shape[1] + Y.shape[1]),
            "ram_bytes": sections["ram"]}


def measure(args) -> tuple[dict, dict]:
    import bench_callgrind as bc
    import bench_cortex_m as cm

    from learnest_codegen.simulation import simulate

    ex = cm.example()
    missing = ex.missing_tools()
    if missing:
        raise SystemExit(f"bench cost_curves: {', '.join(missing)} not found "
                         "(scripts/setup_tools.sh installs them)")
    T = getattr(args, "samples", None) or SAMPLES
    sweeps = [s for s in (getattr(args, "sweeps", None) or ",".join(SWEEPS)).split(",") if s]
    unknown = [s for s in sweeps if s not in SWEEPS]
    if unknown:
        raise SystemExit(f"bench cost_curves: unknown sweep {unknown[0]!r}; choose from {', '.join(SWEEPS)}")
    shutil.rmtree(BUILD, ignore_errors=True)
    tools = {tool: subprocess.run([tool, "--version"], capture_output=True, text=True).stdout.splitlines()[0]
             for tool in ("gcc", "arm-none-eabi-gcc", "qemu-system-arm", "valgrind")}
    cond = figures.conditions(
        model="untrained KNODE nets (seed 0) on each system's prior: one hidden layer of 8 tanh "
              "units unless the sweep changes it",
        run=f"each system's simulated run (seed 1): host samples {SKIP}-{SKIP + T - 1}, "
            f"M4F steps 1-{SKIP + T - 1}",
        settings="each estimator as learnest-compile generates it (defaults; N = 20 unless swept)",
        target=f"host float64 (callgrind); {cm.MACHINE} (Cortex-M4F) float32 in qemu-system-arm "
               "-icount shift=0,sleep=off",
        tools=tools)
    rows = []
    todo = points(sweeps)
    for k, (system_name, layers, width, horizon) in enumerate(todo):
        model = model_of(system_name, layers, width)
        run = simulate(model.system, seed=1, duration=(SKIP + T + 1) * model.system.dt)
        for estimator in estimators():
            if not _horizon(estimator) and horizon != BASE[3]:
                continue  # a Kalman filter has no horizon: measured once per net
            print(f"    [{k + 1}/{len(todo)}] {system_name} {layers} x {width} N = {horizon}: {estimator}",
                  flush=True)
            N = horizon if _horizon(estimator) else None
            root = BUILD / f"{system_name}_{layers}x{width}_N{horizon}" / estimator
            root.mkdir(parents=True)
            row = {"system": system_name, "nx": model.nx, "hidden_layers": layers, "width": width,
                   "horizon": N, "estimator": estimator}
            row.update(host_count(bc, model, run, estimator, N, root, T))
            row.update(m4f_count(cm, ex, model, run, estimator, N, root, T))
            rows.append(row)
    data = {"rows": rows, "sweeps": {s: [list(p) for p in SWEEPS[s]] for s in sweeps},
            "clock_hz_assumed": cm.CLOCK_HZ, "cycles_per_instruction_assumed": cm.CYCLES_PER_INSTRUCTION,
            "loop_hz": LOOP_HZ}
    plot(data, PLOT)
    return data, cond


# -- views -------------------------------------------------------------------------------------

def _rows(f: dict, sweep: str) -> list[tuple[tuple, list[dict]]]:
    """Each point of ``sweep`` with the rows measured at it (the UKF's at the base horizon)."""
    out = []
    for system_name, layers, width, horizon in f["sweeps"][sweep]:
        at = [r for r in f["rows"]
              if (r["system"], r["hidden_layers"], r["width"]) == (system_name, layers, width)
              and (r["horizon"] == horizon or (r["horizon"] is None and sweep != "horizon"))]
        out.append(((system_name, layers, width, horizon), at))
    return out


def budget(f: dict) -> float:
    """Instructions a step that fill one period of the loop at the assumed clock and CPI."""
    return f["clock_hz_assumed"] / f["cycles_per_instruction_assumed"] / f["loop_hz"]


def _label(sweep: str, p: tuple) -> str:
    system_name, layers, width, horizon = p
    return {"width": f"{width}", "depth": f"{layers}", "horizon": f"{horizon}",
            "states": f"{system_name}"}[sweep]


def render_table(data: dict) -> str:
    """Every point: host and M4F instructions per step, flash and RAM."""
    f = data["figures"]
    lines = ["| sweep | system (nx) | net | N | estimator | host instructions, float64 | "
             "M4F instructions, float32 | M4F max | flash | RAM | "
             "`mhe_gn` iterations on the host (mean / max) |",
             "|---|---|---|---:|---|---:|---:|---:|---:|---:|---|"]
    for sweep in f["sweeps"]:
        for _, rows in _rows(f, sweep):
            for r in rows:
                its = (f"{r['iterations_mean']:.2f} / {r['iterations_max']}" if "iterations_mean" in r
                       else "–")
                lines.append(f"| {sweep} | {r['system']} ({r['nx']}) | {r['hidden_layers']} x "
                             f"{r['width']} | {r['horizon'] or '–'} | `{r['estimator']}` | "
                             f"{r['host_instructions']:,.0f} | {r['m4f_instructions']:,.0f} | "
                             f"{r['m4f_instructions_max']:,.0f} | {r['flash_bytes']:,} | "
                             f"{r['ram_bytes']:,} | {its} |")
    return "\n".join(lines) + "\n\n" + render_conditions(data)


def _largest(f: dict, sweep: str, estimator: str):
    """The largest value of the sweep's axis at which ``estimator`` fits the loop, or None."""
    fit = None
    for p, rows in _rows(f, sweep):
        r = next((r for r in rows if r["estimator"] == estimator), None)
        if r is not None and r["m4f_instructions_max"] <= budget(f):
            fit = _label(sweep, p)
    return fit


def estimators() -> tuple[str, ...]:
    """What the curves measure: the estimator table's float32 estimators (those a Cortex-M runs;
    ``examples/cortex_m``)."""
    from learnest_codegen.compilation import FLOAT32_NAMES

    return tuple(FLOAT32_NAMES)


def _horizon(estimator: str) -> bool:
    from learnest_codegen.compilation import estimator_kind

    return estimator_kind(estimator).horizon


def _measured(f: dict) -> list[str]:
    """The estimators the figures hold, in their order."""
    return list(dict.fromkeys(r["estimator"] for r in f["rows"]))


def render_rule(data: dict) -> str:
    """The one-line rule: what fits a 1 kHz loop on the M4F."""
    f = data["figures"]
    parts = []
    for estimator in _measured(f):
        fits = []
        if "width" in f["sweeps"]:
            width = _largest(f, "width", estimator)
            fits.append(f"up to {width} units at N = {BASE[3]}" if width and _horizon(estimator) else
                        f"up to {width} units" if width else
                        f"no width at N = {BASE[3]}" if _horizon(estimator) else "no width")
        if "horizon" in f["sweeps"] and _horizon(estimator):
            horizon = _largest(f, "horizon", estimator)
            fits.append(f"up to N = {horizon} at {BASE[2]} units" if horizon else
                        f"no horizon at {BASE[2]} units")
        parts.append(f"`{estimator}` {', '.join(fits)}")
    return (f"A {f['loop_hz'] / 1e3:g} kHz loop on a {f['clock_hz_assumed'] / 1e6:g} MHz Cortex-M4F "
            f"({budget(f):,.0f} instructions at {f['cycles_per_instruction_assumed']:g} cycles each, "
            "for the worst step) fits, for a 4-state system and a net of one hidden layer: "
            + "; ".join(parts) + ".")


def render_conditions(data: dict) -> str:
    c = data["conditions"]
    return (f"Measured by `{data['command']}` on {c['date']}: {c['model']}; {c['run']}; {c['target']}; "
            f"{c['tools']['gcc']}, {c['tools']['arm-none-eabi-gcc']}. Instruction counts do not "
            "depend on the host's load.")


def plot(data: dict, path: Path) -> None:
    """One panel per sweep: M4F (solid) and host (dashed) instructions per step, log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f = {**data, "loop_hz": data["loop_hz"]}
    sweeps = list(data["sweeps"])
    fig, axes = plt.subplots(1, len(sweeps), figsize=(4 * len(sweeps), 3.6), squeeze=False)
    titles = {"width": "net width (1 hidden layer)", "depth": "hidden layers (8 units)",
              "states": "system (states)", "horizon": "horizon N (8 units)"}
    for ax, sweep in zip(axes[0], sweeps):
        pts = _rows(f, sweep)
        ticks = [_label(sweep, p) if sweep != "states" else f"{p[0]}\n({rows[0]['nx'] if rows else '?'})"
                 for p, rows in pts]
        for k, estimator in enumerate(_measured(f)):
            xs, m4f, host = [], [], []
            for i, (_, rows) in enumerate(pts):
                r = next((r for r in rows if r["estimator"] == estimator), None)
                if r is not None:
                    xs.append(i)
                    m4f.append(r["m4f_instructions"])
                    host.append(r["host_instructions"])
            if xs:
                ax.plot(xs, m4f, "o-", color=f"C{k}", label=f"{estimator} (M4F, float32)")
                ax.plot(xs, host, "x--", color=f"C{k}", alpha=0.6, label=f"{estimator} (host, float64)")
        ax.axhline(budget(f), color="k", lw=0.8, ls=":", label=f"{data['loop_hz'] / 1e3:g} kHz on the M4F")
        ax.set_xticks(range(len(ticks)), ticks)
        ax.set_yscale("log")
        ax.set_title(titles[sweep])
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("instructions per step")
    axes[0][0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


if __name__ == "__main__":
    import bench

    sys.exit(bench.main(["cost_curves", *sys.argv[1:]]))
