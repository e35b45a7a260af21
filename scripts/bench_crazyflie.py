"""The quadrotor estimator as the Crazyflie's out-of-tree estimator: memory, M4F time, flights.

Everything as a user meets it: the NanoBench flights (``$LEARNEST_DATA`` or ../shared/data),
the firmware tarball (examples/crazyflie/replay.py finds it), ``learnest-compile MODEL --target
crazyflie`` with its defaults (the UKF in float32, the system's tuning), the firmware's own build.

- **Models.** Leave one trajectory type out (docs/reports/flights.md): fitted on the eight
  figure-eights and replayed on the nine circles, and the reverse, so every flight is replayed
  on a model that never saw its type. ``greybox``: the grey-box prior alone (``quadrotor_linear``,
  ``adot = -k_v v - k_a a``, least squares; features ``linear_prior``); ``knode_net``: that prior
  with the KNODE net on top (features ``linear``, the study's training, kept only when it beats the
  prior on its validation data).
- **Memory.** ``make cf2_defconfig && make`` of the firmware as it comes (before), and of the apps
  of the models fitted on the figure-eights (after); the build's own size report.
- **Time.** Those apps' replay under QEMU's Cortex-M4F, compiled with the flags the firmware's
  build used for their files, over three circle flights from the ground up: instructions (40 a
  count of the 25 MHz sample clock under ``-icount shift=0``) in the tick that steps the
  estimator and in the other nine ticks of each 10 ms sample; the share of a 168 MHz M4F at 1.5
  cycles an instruction. The FreeRTOS semaphore calls and context switches are stubs there, not
  counted.
- **Flights.** Each flight replayed on the host: equality with the Python bindings given the app's
  own samples, and each state's RMS error against the Vicon reference (position; Savitzky-Golay
  velocity and acceleration) over the airborne part, beside the onboard EKF's logged estimate.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import figures
import numpy as np

MINUTES = 20
ORDER = 60
OUT = figures.ROOT / "build" / "bench" / "crazyflie"
EXAMPLE = figures.ROOT / "examples" / "crazyflie"
MODELS = {"greybox": "linear_prior", "knode_net": "linear"}
LABELS = {"greybox": "grey-box prior", "knode_net": "KNODE net on the prior"}
FOLDS = {"circles": ("B3_figure8", "B2_circle"), "figure-eights": ("B2_circle", "B3_figure8")}
TIMED = ("B2_circle_fast_rep1", "B2_circle_medium_rep3", "B2_circle_slow_rep2")
MHE_SHORT = 10  # a second horizon, for the MHE's workspace per stage
MHZ, CYCLES_PER_INSTRUCTION, SHARE_TARGET, RAM_RESERVE = 168, 1.5, 0.20, 8 * 1024
STATES = ("px", "py", "pz", "vx", "vy", "vz", "ax", "ay", "az")


def _replay_module():
    return figures.load_file(EXAMPLE / "replay.py", "crazyflie_replay")


def add_arguments(parser) -> None:
    parser.add_argument("--data", type=Path, default=None, help="data root (default: $LEARNEST_DATA "
                        "or ../shared/data)")


def _app(model_dir: Path, out: Path) -> tuple[Path, Path]:
    """``learnest-compile MODEL --system <its system> --target crazyflie`` in a fresh process:
    (estimator, app). The system is named: a study's model with a net records its fitted
    system as built in code, which the command does not load by itself."""
    from learnest_codegen.codegen.crazyflie import app_name

    system = json.loads((model_dir / "model.json").read_text())["system"]
    subprocess.run([sys.executable, "-m", "learnest_codegen.cli", "compile", str(model_dir),
                    "--system", system,
                    "--target", "crazyflie", "--out", str(out), "--force"], check=True, capture_output=True)
    estimator = next(p for p in out.iterdir() if p.is_dir() and not p.name.endswith("_crazyflie"))
    return estimator, out / app_name(estimator.name)


def _flight(rp, path: Path, binary: Path, estimator, model: str, fold: str, net_kept: bool) -> dict:
    flight = rp.flight_replay(path)
    replay = rp.run_replay(binary, flight.records)
    X = rp.bindings_estimates(estimator, replay)
    x0 = rp.start_state(replay)[1]
    pipeline = estimator.run(flight.u, flight.y, x0)  # the recordings pipeline's samples
    first, last = flight.span
    ours = replay.x[first:last + 1].astype(float)
    v = slice(3, 6)
    return {
        "flight": flight.name, "model": model, "replayed": fold, "net_kept": net_kept,
        "samples": len(replay.x),
        "airborne": last - first + 1, "errors": replay.summary["errors"],
        "rejected": replay.summary["rejected"],
        "equal_to_bindings": bool(np.array_equal(replay.x.astype(float), X, equal_nan=True)),
        "max_vs_pipeline": {g: float(np.max(np.abs(pipeline[:, s] - replay.x[:, s])))
                            for g, s in (("p", slice(0, 3)), ("v", v), ("a", slice(6, 9)))},
        "rms": dict(zip(STATES, rp.rms_errors(ours, flight.reference).tolist())),
        "onboard_rms": dict(zip(STATES[:6], rp.rms_errors(flight.onboard[:, :6], flight.reference[:, :6])
                                .tolist())),
        "v_rms": float(np.sqrt(np.mean((ours[:, v] - flight.reference[:, v]) ** 2))),
        "onboard_v_rms": float(np.sqrt(np.mean((flight.onboard[:, v] - flight.reference[:, v]) ** 2))),
    }


def _mhe_workspaces(work: Path) -> dict:
    """The embedded MHE's workspace bound (mhe_rti of the nominal ``quadrotor_linear`` in float32:
    the same sizes as a fitted one) at its default horizon and at :data:`MHE_SHORT`, and what
    ``--target crazyflie`` says of the default horizon (it refuses what the firmware cannot hold)."""
    import re
    import shutil

    from learnest_codegen.codegen.crazyflie import workspace_bytes

    def compile_(out: Path, *args: str) -> subprocess.CompletedProcess:
        shutil.rmtree(out, ignore_errors=True)
        return subprocess.run([sys.executable, "-m", "learnest_codegen.cli", "compile", "--nominal",
                               "--system", "quadrotor_linear", "--estimator", "mhe_rti", "--out", str(out),
                               *args], capture_output=True, text=True)

    sizes, default = {}, None
    for horizon in (None, MHE_SHORT):
        gen = work / f"n{horizon or 'default'}"
        done = compile_(gen, "--precision", "float32", *(("--horizon", str(horizon)) if horizon else ()))
        if done.returncode != 0:
            raise SystemExit(f"compiling mhe_rti failed:\n{done.stderr[-2000:]}")
        est = next(p for p in gen.iterdir() if p.is_dir())
        header = est / f"{est.name}.h"
        n = int(re.search(r"_HORIZON (\d+)", header.read_text()).group(1))
        sizes[n] = workspace_bytes(header, est.name)
        default = default or n
    refused = compile_(work / "target", "--target", "crazyflie")
    (n0, b0), (n1, b1) = sizes.items()
    return {"estimator": "mhe_rti", "default_horizon": default,
            "workspace_bytes": {str(n): b for n, b in sizes.items()},
            "bytes_per_stage": (b0 - b1) / (n0 - n1),
            "target_exit_code": refused.returncode,
            "target_message": refused.stderr.strip().splitlines()[-1] if refused.stderr.strip() else ""}


def _elsewhere(rp, firmware: Path, app: Path, work: Path):
    """The firmware's build with ``app``, both copied to a longer path under ``work`` (built
    again from clean: the file names compiled in must not depend on where they are)."""
    import shutil

    where = work / "another" / "checkout" / "path"
    shutil.rmtree(work / "another", ignore_errors=True)
    for folder in (firmware, app):  # without their build output (their top-level build/)
        shutil.copytree(folder, where / folder.name, symlinks=True,
                        ignore=lambda d, names, top=folder: ["build"] if Path(d) == top else [])
    return rp.build_firmware(where / firmware.name, where / app.name)


def _timing(rp, app: Path, firmware: Path, host: Path, folder: Path, work: Path, rate: int) -> dict:
    """QEMU's instruction counts over :data:`TIMED`: one sample every ``1 / rate`` s, 1000
    stabilizer ticks a second."""
    sample, other, samples, stack, equal = [], [], 0, 0, True
    for name in TIMED:
        flight = rp.flight_replay(folder / f"{name}.csv")
        m4f = rp.run_qemu(rp.build_qemu(app, firmware, flight.records, work / name))
        equal &= bool(np.array_equal(m4f.x, rp.run_replay(host, flight.records).x, equal_nan=True))
        sample.append(m4f.busy_sample * rp.INSTRUCTIONS_PER_TICK)
        other.append(m4f.busy_other * rp.INSTRUCTIONS_PER_TICK)
        samples += len(m4f.x)
        stack = max(stack, m4f.summary["stack_peak_bytes"])
    sample, other = np.concatenate(sample), np.concatenate(other)
    per_second = float((sample.sum() + other.sum()) / samples * rate)
    return {"flights": list(TIMED), "samples": samples, "equal_to_host": equal,
            "sample_tick": {"mean": float(sample.mean()), "max": int(sample.max())},
            "other_ticks": {"mean": float(other.mean() / (1000 // rate - 1)),
                            "max_per_sample": int(other.max())},
            "sample_rate_hz": rate,
            "instructions_per_second": per_second,
            "share": per_second * CYCLES_PER_INSTRUCTION / (MHZ * 1e6),
            "worst_sample_tick_us": float(sample.max() * CYCLES_PER_INSTRUCTION / MHZ),
            "stack_peak_bytes": stack}


def measure(args) -> tuple[dict, dict]:
    from learnest_codegen.codegen import crazyflie
    from learnest_codegen.experiments.quadrotor import StudySettings, flight_cases, trained_model
    from learnest_codegen.pipeline import load_estimator
    from learnest_codegen.recordings import data_root

    rp = _replay_module()
    missing = rp.missing_tools(qemu=True)
    if missing:
        raise SystemExit(f"bench crazyflie needs {', '.join(missing)}")
    root = data_root(args.data)
    folder = root / "nanobench"
    cond = figures.conditions(
        model="quadrotor_linear fitted on one trajectory type (leave-type-out): the grey-box prior "
              "alone (features linear_prior) and with the KNODE net (features linear, the study's "
              "training); learnest-compile MODEL --target crazyflie (ukf, float32, the system's tuning)",
        run="the 17 NanoBench flights, each from the log's start (on the ground) to the end of its "
            "airborne part, replayed on the model fitted on the other type; QEMU: "
            + ", ".join(TIMED),
        firmware=str(rp.firmware_tarball().name) + " (unpacked as a git repository committed on the "
                 "firmware's date; the apps' Makefiles map the file names compiled in, so the figures do "
                 "not depend on the checkout path)",
        toolchain=subprocess.run(
            ["arm-none-eabi-gcc", "--version"], capture_output=True, text=True).stdout.splitlines()[0])
    firmware = rp.unpack_firmware(OUT)
    before = rp.build_firmware(firmware)
    cases = flight_cases(root)
    out: dict = {"budget": {"mhz": MHZ, "cycles_per_instruction": CYCLES_PER_INSTRUCTION,
                            "share_target": SHARE_TARGET, "ram_reserve_bytes": RAM_RESERVE},
                 "firmware": {"before": before.sizes.to_json()}, "apps": {}, "timing": {}, "flights": []}
    for fold, (trained_on, replayed_type) in FOLDS.items():
        train = [c for c in cases if c.name.startswith(trained_on)]
        for model, features in MODELS.items():
            work = OUT / fold / model
            trained = trained_model(train, features, OUT / "study", StudySettings(), work / "model",
                                    progress=False)
            estimator_dir, app = _app(work / "model", work / "gen")
            host = rp.build_replay(app, firmware, work / "host")
            estimator = load_estimator(estimator_dir)
            for path in sorted(folder.glob(f"{replayed_type}*.csv")):
                out["flights"].append(_flight(rp, path, host, estimator, model, fold,
                                              bool(trained.meta.get("net_kept", False))))
            if fold != "circles":
                continue
            build = rp.build_firmware(firmware, app)
            out["firmware"][model] = {**build.sizes.to_json(), "warnings": len(build.warnings),
                                      "app_objects": rp.app_memory(build, app),
                                      "paths_in_binary": rp.path_occurrences(build, firmware, app)}
            if model == "greybox":
                other = _elsewhere(rp, firmware, app, OUT / "elsewhere")
                out["firmware"]["another_path"] = {
                    **other.sizes.to_json(), "same_sizes": other.sizes == build.sizes,
                    "same_binary": other.binary.read_bytes() == build.binary.read_bytes()}
            out["apps"][model] = {"prefix": estimator_dir.name, "estimator": estimator.manifest["estimator"],
                                  "net_kept": bool(trained.meta.get("net_kept", False)),
                                  "prior_params": trained.meta.get("prior_params"),
                                  "workspace_bytes": crazyflie.workspace_bytes(
                                      estimator_dir / f"{estimator_dir.name}.h", estimator_dir.name),
                                  "stack_bytes": 4 * crazyflie.STACK_WORDS}
            rate = crazyflie.sample_rate_hz(estimator.manifest["dt"])
            out["timing"][model] = _timing(rp, app, firmware, host, folder, work / "qemu", rate)
    out["mhe"] = _mhe_workspaces(OUT / "mhe")
    out["firmware"]["free_ram_limit"] = {"bytes": crazyflie.FREE_RAM_BYTES,
                                         "as_measured": crazyflie.FREE_RAM_BYTES == before.sizes.to_json()
                                         ["ram"]["free"]}
    grey = [r for r in out["flights"] if r["model"] == "greybox"]
    knode = [r for r in out["flights"] if r["model"] == "knode_net"]
    out["summary"] = {"flights": len(grey),
                      "greybox_beats_onboard_velocity": sum(r["v_rms"] < r["onboard_v_rms"] for r in grey),
                      "knode_beats_onboard_velocity": sum(r["v_rms"] < r["onboard_v_rms"] for r in knode),
                      "equal_to_bindings": sum(r["equal_to_bindings"] for r in out["flights"]),
                      "replays": len(out["flights"])}
    return out, cond


# -- views -------------------------------------------------------------------------------------------


def render_memory(data: dict) -> str:
    f = data["figures"]["firmware"]
    lines = ["| region | firmware as it comes | with the grey-box app | with the KNODE-net app |",
             "|---|---|---|---|"]
    for region, label in (("flash", "flash"), ("ram", "RAM"), ("ccm", "CCM")):
        cells = [f"{f[k][region]['used']:,} of {f[k][region]['total']:,} B ({f[k][region]['free']:,} free)"
                 for k in ("before", "greybox", "knode_net")]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    a, g, n = data["figures"]["apps"]["greybox"], f["greybox"], f["knode_net"]
    ga, na = g["app_objects"], n["app_objects"]
    lines.append(
        f"\nThe app's own objects take {ga['flash']:,} B of flash and {ga['ram']:,} B of RAM with the "
        f"grey-box model ({na['flash']:,} and {na['ram']:,} B with the KNODE net), the estimator's "
        f"workspace {a['workspace_bytes']:,} B of it (a static buffer, no heap); the app task's stack "
        f"({a['stack_bytes']:,} B of RAM) belongs to the firmware's app layer. Compiler warnings "
        f"in the app's files: {g['warnings']} and {n['warnings']} (the build has -Werror).")
    e = f["another_path"]
    lines.append(
        f"The app's Makefile names the compiled-in file names (the firmware's assertions keep them) "
        f"relative to the firmware's and the app's folders: their absolute paths occur "
        f"{g['paths_in_binary'] + n['paths_in_binary']} times in the two `cf2.bin`, and the grey-box "
        f"build copied to another, longer path has "
        f"{'the same sizes' if e['same_sizes'] else 'other sizes'} "
        f"({'the same bytes' if e['same_binary'] else 'other bytes'}).")
    m = data["figures"]["mhe"]
    n = m["default_horizon"]
    short = min(m["workspace_bytes"], key=int)
    lines.append(f"The embedded MHE (`{m['estimator']}`) needs {m['workspace_bytes'][str(n)]:,} B of "
                 f"workspace at its default horizon N = {n} ({m['bytes_per_stage']:,.0f} B a stage; "
                 f"{m['workspace_bytes'][short]:,} B at N = {short}): with the app task's stack, more "
                 f"than the {f['before']['ram']['free']:,} B of RAM the firmware leaves free. "
                 f"`--target crazyflie` refuses it (exit code {m['target_exit_code']}):\n\n"
                 f"    {m['target_message']}")
    return "\n".join(lines)


def render_timing(data: dict) -> str:
    t = data["figures"]["timing"]
    lines = ["| model | instructions in the estimator's tick (mean / max) | in each other tick (mean) | "
             "instructions a second | share of the M4F | longest step | stack peak |",
             "|---|---|---|---|---|---|---|"]
    for model in ("greybox", "knode_net"):
        r = t[model]
        lines.append(f"| {LABELS[model]} | {r['sample_tick']['mean']:,.0f} / {r['sample_tick']['max']:,} | "
                     f"{r['other_ticks']['mean']:,.0f} | {r['instructions_per_second'] / 1e6:.2f} M | "
                     f"{100 * r['share']:.1f} % | {r['worst_sample_tick_us']:,.0f} us | "
                     f"{r['stack_peak_bytes']:,} B |")
    c = data["conditions"]
    lines.append(f"\nOver {t['greybox']['samples']:,} samples ({', '.join(t['greybox']['flights'])}) for "
                 f"each model; QEMU's estimates equal the host replay's: "
                 f"{'yes' if all(t[m]['equal_to_host'] for m in t) else 'no'}. {c['toolchain']}; "
                 f"{c['date']}, revision {c['commit']}.")
    return "\n".join(lines)


def render_flights(data: dict) -> str:
    rows = {}
    for r in data["figures"]["flights"]:
        rows.setdefault(r["flight"], {})[r["model"]] = r
    lines = ["| flight | replayed on a model fitted on | velocity RMS, grey-box | KNODE net | onboard EKF | "
             "equal to the bindings |", "|---|---|---|---|---|---|"]
    kept = {}
    for flight, r in rows.items():
        g, n = r["greybox"], r["knode_net"]
        fitted = "circles" if g["replayed"] == "figure-eights" else "figure-eights"
        kept[fitted] = n["net_kept"]
        lines.append(f"| {flight} | {fitted} | {g['v_rms']:.4f} | {n['v_rms']:.4f} | "
                     f"{g['onboard_v_rms']:.4f} | "
                     f"{'yes' if g['equal_to_bindings'] and n['equal_to_bindings'] else 'no'} |")
    beats = sum(r["greybox"]["v_rms"] < r["greybox"]["onboard_v_rms"] for r in rows.values())
    net_beats = sum(r["knode_net"]["v_rms"] < r["knode_net"]["onboard_v_rms"] for r in rows.values())
    dropped = ("dropped (it did not beat the prior on its validation data), so that column repeats the "
               "grey-box")
    lines.append(f"\nThe velocity error is below the onboard EKF's on {beats} of {len(rows)} flights with "
                 f"the grey-box estimator, on {net_beats} of {len(rows)} with the KNODE net. " + " ".join(
                     f"The KNODE net fitted on the {t} was {'kept' if k else dropped}."
                     for t, k in kept.items()))
    return "\n".join(lines)


def render_states(data: dict) -> str:
    flights = data["figures"]["flights"]
    lines = ["| state | grey-box: mean RMS (worst flight) | KNODE net | onboard EKF | flights the grey-box "
             "beats the EKF on |", "|---|---|---|---|---|"]
    for s in STATES:
        cells = []
        for model in ("greybox", "knode_net"):
            values = [r["rms"][s] for r in flights if r["model"] == model]
            cells.append(f"{np.mean(values):.4f} ({np.max(values):.4f})")
        g = [r for r in flights if r["model"] == "greybox"]
        if s in g[0]["onboard_rms"]:
            ekf = [r["onboard_rms"][s] for r in g]
            cells.append(f"{np.mean(ekf):.4f} ({np.max(ekf):.4f})")
            cells.append(f"{sum(r['rms'][s] < r['onboard_rms'][s] for r in g)}/{len(g)}")
        else:
            cells += ["-", "-"]
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
