"""``learnest compile`` / ``learnest-compile`` and ``learnest estimate``: C estimators of a model,
and estimates of a run.
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from ..compilation import (
    DEFAULT_ESTIMATORS,
    PRECISION_NAMES,
    check_crazyflie,
    check_horizon,
    compile_estimators,
    crazyflie_default,
    estimator_dir,
    estimator_kind,
    precision_problem,
)
from ..errors import LearnestError, SolverError
from ..evaluation import mse, run_estimator
from ..outputs import atomic_file, claim_output
from ..pipeline import expected_manifest, load_estimator, make_estimator, resolve
from .common import (
    CLAMP_INPUTS,
    ESTIMATOR_HELP,
    FORCE,
    HORIZON,
    PRECISION_HELP,
    RESAMPLE,
    SYSTEM_HELP,
    EstimatorChoice,
    friendly,
    gate_settings,
    missing_note,
    parse_covariance,
    parse_vector,
    read_run,
    resolve_system,
    system_named,
    with_gate_options,
)


def _compile(model_dir: str | None, out: str, system_name: str | None, nominal: bool,
             estimators: tuple[str, ...], precision: str | None = None, gate=None,
             force: bool = False, horizon: int | None = None,
             clamp_inputs: bool | None = None, target: str = "host") -> dict:
    from ..codegen import crazyflie

    if target == "crazyflie":
        estimators, precision = estimators or (crazyflie_default(),), precision or crazyflie.PRECISION
        if len(estimators) != 1:
            raise click.UsageError(f"--target crazyflie builds one estimator into the app, got "
                                   f"{list(estimators)}")
        check_crazyflie(estimators[0])
        crazyflie.check_target(precision, None)
    estimators, precision = estimators or tuple(DEFAULT_ESTIMATORS), precision or "float64"
    if precision_problem(estimators, precision):
        raise click.UsageError(precision_problem(estimators, precision))
    try:
        check_horizon(estimators, horizon)
    except ValueError as exc:
        raise click.UsageError(f"--horizon: {exc}") from exc
    if nominal:
        model, system = "nominal", system_named(system_name or "cartpole")
    else:
        if model_dir is None:
            raise click.UsageError("give MODEL_DIR, or --nominal for the prior-only estimators")
        model, system = model_dir, resolve_system(system_name, model_dir)
    if target == "crazyflie":
        crazyflie.check_target(precision, system)
    resolved = resolve(model, system, clamp_inputs=None if nominal else clamp_inputs)
    inputs = (model_dir,) if model_dir else ()
    # a refused app leaves nothing new: the --out folders this command creates, or new estimator folders
    created = [p for p in (Path(out).resolve(), *Path(out).resolve().parents) if not p.exists()]
    fresh = created[-1:]
    for name in dict.fromkeys(estimators):  # each folder: not over an input, not unasked
        folder = estimator_dir(Path(out), resolved.model, name, precision)
        claim_output(folder, inputs=inputs, force=force, kind="dir")
        if target == "crazyflie":
            claim_output(Path(out) / crazyflie.app_name(folder.name), inputs=inputs, force=force, kind="dir")
            fresh += [] if folder.exists() or created else [folder]
    results = compile_estimators(resolved.model, out, model_hash=resolved.hash, estimators=estimators,
                                 precision=precision, gate=gate, horizon=horizon)
    if target == "crazyflie":  # refused before anything is reported, and nothing new left
        crazyflie.check_fits(next(iter(results.values())), undo=fresh)
    for name, res in results.items():
        click.echo(f"{name}: {res.directory}  ({res.code_bytes / 1024:.0f} KiB of C, "
                   + (f"reused, built in {res.build_seconds:.2f} s)" if res.reused
                      else f"built in {res.build_seconds:.2f} s)"))
    if target == "crazyflie":
        (name, res), = results.items()
        app = crazyflie.write_app(res, system, out)
        click.echo(f"crazyflie app: {app.directory}  ({name} every {1000 // app.sample_rate_hz} ms, "
                   f"workspace {app.workspace_bytes} B); build it with "
                   f"make -C {app.directory} CRAZYFLIE_BASE=path/to/crazyflie-firmware")
    return results


COMPILE_OPTIONS = [
    click.argument("model_dir", required=False, type=click.Path(file_okay=False)),
    click.option("--out", default="generated", show_default=True, type=click.Path(file_okay=False),
                 help="output directory (one subdirectory per estimator)"),
    click.option("--system", "system_name", default=None,
                 help=SYSTEM_HELP + " (default: the one the model records; cartpole with --nominal)"),
    click.option("--nominal", is_flag=True, help="compile the prior-only (nominal) estimators"),
    click.option("--estimator", "estimators", multiple=True, type=EstimatorChoice(),
                 help=ESTIMATOR_HELP + f" (default: {' and '.join(DEFAULT_ESTIMATORS)}; "
                      f"{crazyflie_default()} with --target crazyflie)"),
    click.option("--precision", type=click.Choice(PRECISION_NAMES), default=None,
                 help=PRECISION_HELP + " (default: float64; float32 with --target crazyflie)"),
    click.option("--target", type=click.Choice(["host", "crazyflie"]), default="host", show_default=True,
                 help="host: the estimator folders; crazyflie: also <prefix>_crazyflie/, an "
                      "out-of-tree estimator app for the Crazyflie 2.x firmware (docs/guide/crazyflie.md)"),
    click.option("--force", is_flag=True,
                 help="replace existing estimator folders (an unchanged library is reused)"),
    HORIZON,
    CLAMP_INPUTS,
]


def _with_compile_options(command):
    for option in reversed(COMPILE_OPTIONS):
        command = option(command)
    return command


@click.command("compile", context_settings={"help_option_names": ["-h", "--help"]})
@_with_compile_options
@with_gate_options
@friendly
def compile_cmd(model_dir, out, system_name, nominal, estimators, precision, target, force, horizon,
                clamp_inputs, gate_threshold, gate_recover_after, gate_inflation) -> None:
    """Generate C for the estimators of a model (default: MHE with Ipopt, UKF) and build them.

    Each estimator gets its own folder under --out, written whole or not at all; an existing
    folder is replaced only with --force."""
    _compile(model_dir, out, system_name, nominal, tuple(estimators), precision,
             gate_settings(gate_threshold, gate_recover_after, gate_inflation), force, horizon,
             clamp_inputs, target)


#: Where ``estimate`` compiles an estimator it is not given (``--compiled``): beside the output.
ON_DEMAND = ".learnest_compiled"


@click.command()
@click.option("--system", "system_name", default=None,
              help=SYSTEM_HELP + " (default: the one --model or --compiled records; cartpole otherwise)")
@click.option("--data", multiple=True, required=True,
              help="run CSV (empty y_ cells: missing measurements); give --data several times, a "
                   "folder or a glob to estimate many runs (then --out is a folder)")
@click.option("--estimator", type=EstimatorChoice(), required=True, help=ESTIMATOR_HELP)
@click.option("--model", default="nominal", show_default=True, help="nominal, true, or a model directory")
@click.option("--backend", type=click.Choice(["python", "c"]), default="c", show_default=True)
@click.option("--compiled", type=click.Path(file_okay=False), default=None,
              help="compiled estimator directory (C backend; default: compile on demand into "
                   f"{ON_DEMAND}/ beside --out, said on stderr)")
@click.option("--precision", type=click.Choice(PRECISION_NAMES), default="float64",
              show_default=True, help=PRECISION_HELP + "; C backend, when compiling on demand")
@HORIZON
@click.option("--x0", "x0_text", default=None,
              help="initial state guess, one comma-separated value per state (default: the "
                   "system's x0)")
@click.option("--P0", "P0_text", default=None,
              help="covariance of the initial guess: 'initial' (the system's initial_std**2), "
                   "one variance per state (the diagonal) or nx*nx entries row by row (default: "
                   "the estimator's own: UKF initial_std**2, MHE the steady-state arrival)")
@click.option("--out", type=click.Path(), required=True,
              help="estimates CSV to write; with many runs a folder, one <run>.csv each")
@CLAMP_INPUTS
@with_gate_options
@RESAMPLE
@FORCE
@friendly
def estimate(system_name, data, estimator, model, backend, compiled, precision, horizon, x0_text,
             P0_text, out, clamp_inputs, gate_threshold, gate_recover_after, gate_inflation, resample,
             force) -> None:
    """Run an estimator over a run (or many); write t and one xhat_<state> column per state.

    With a model directory (--model) or a compiled folder (--compiled) the system is the one it
    records. When the run holds the truth, the summary gives the MSE over all states and the RMS
    error of each state in its unit. Samples whose outputs the innovation gate rejected are
    counted in the summary line; they are not errors. Empty y_ cells of the run are missing
    measurements (both backends take them). With a trained model, the summary also gives the
    share of samples whose estimates and inputs lie outside the range the net was trained on.
    Without --compiled the C backend compiles the estimator into .learnest_compiled/ beside
    --out (one line on stderr says where; an unchanged build is reused)."""
    from ..recordings.runs import run_paths

    paths = run_paths(data)
    if len(paths) == 1 and not Path(out).is_dir():
        _estimate_run(system_name, str(paths[0]), estimator, model, backend, compiled, precision, horizon,
                      x0_text, P0_text, out, clamp_inputs, gate_threshold, gate_recover_after,
                      gate_inflation, resample, force)
        return
    if Path(out).exists() and not Path(out).is_dir():
        raise click.UsageError(f"--out {out}: with {len(paths)} runs, --out is a folder (one <run>.csv each)")
    Path(out).mkdir(parents=True, exist_ok=True)
    stems = [p.stem for p in paths]
    for path in paths:
        name = path.stem if stems.count(path.stem) == 1 else f"{path.parent.name}_{path.stem}"
        _estimate_run(system_name, str(path), estimator, model, backend, compiled, precision, horizon,
                      x0_text, P0_text, str(Path(out) / f"{name}.csv"), clamp_inputs, gate_threshold,
                      gate_recover_after, gate_inflation, resample, force)


def _estimate_run(system_name, data, estimator, model, backend, compiled, precision, horizon, x0_text,
                  P0_text, out, clamp_inputs, gate_threshold, gate_recover_after, gate_inflation,
                  resample, force) -> None:
    """One run of :func:`estimate`."""
    if backend == "c" and compiled is None and precision_problem((estimator,), precision):
        raise click.UsageError(precision_problem((estimator,), precision))
    if backend == "python" and estimator_kind(estimator).python is None:
        raise click.UsageError(f"{estimator} has no Python reference (its C defines it); use --backend c")
    try:
        check_horizon((estimator,), horizon)
    except ValueError as exc:
        raise click.UsageError(f"--horizon: {exc}") from exc

    claim_output(out, inputs=(data, compiled, None if model in ("nominal", "true") else model),
                 force=force)
    system = resolve_system(system_name, model, compiled if backend == "c" else None)
    x0 = parse_vector(x0_text, system.nx, "--x0")
    # a guess of one's own is as uncertain as the system's initial state, not as the steady state
    P0 = parse_covariance("initial" if P0_text is None and x0 is not None else P0_text, system)
    run = read_run(data, system, resample)
    trained = None
    if model not in ("nominal", "true"):
        from ..learning.model import load_model

        trained = load_model(model, system)
    resolved = resolve(trained or model, system, clamp_inputs=clamp_inputs)
    gate = gate_settings(gate_threshold, gate_recover_after, gate_inflation)
    if backend == "c" and compiled is not None:
        expect = {"estimator": estimator, **expected_manifest(resolved)}
        est = load_estimator(compiled, expect={**expect, **({} if horizon is None else {"horizon": horizon})},
                             gate=gate)
    else:  # compiled on demand next to the output (reused while the model is unchanged)
        where = Path(out).resolve().parent / ON_DEMAND
        if backend == "c":
            click.echo(f"compiling {estimator} into {where} (reused while the model is unchanged; "
                       "--compiled DIR runs a folder of learnest-compile)", err=True)
        est = make_estimator(resolved, estimator, backend=backend, system=system, precision=precision,
                             out=where, gate=gate, horizon=horizon)
    try:
        result = run_estimator(est, run, np.asarray(system.x0, float) if x0 is None else x0,
                               f"{estimator}:{model}:{backend}", P0)
    except (SolverError, LearnestError) as exc:
        if x0_text is None and P0_text is None:
            raise
        raise type(exc)(f"{exc}; the initial guess may be the cause (--x0 {x0_text}, --P0 "
                        f"{P0_text or 'initial'}): give a state near the run's first one and a "
                        "covariance of its error") from exc
    header = "t," + ",".join(f"xhat_{n}" for n in system.state_names)
    with atomic_file(out) as tmp:
        np.savetxt(tmp, np.column_stack([run.t, result.x_hat]), delimiter=",", header=header,
                   comments="", fmt="%.17g")
    line = f"wrote {out}: {len(run)} estimates, {result.seconds_per_step * 1e6:.1f} us/step"
    if run.x is not None:
        line += f", MSE vs truth {mse(result.x_hat, run.x):.4e} (all states)"
    line += f", {result.rejections} output(s) rejected by the innovation gate"
    line += missing_note(run, est.settings.gate, system.dt)
    input_rejections = int(getattr(est, "input_rejections", 0))
    if input_rejections:
        line += f", {input_rejections} implausible input(s) replaced"
    if trained is not None:
        from ..learning.ranges import extrapolation

        outside = extrapolation(trained, result.x_hat, run.u)
        line += ("; the model records no training range" if outside is None
                 else f"; {outside.describe()}")
    click.echo(line)
    if run.x is not None:  # one figure per state, in its own unit
        rms = np.sqrt(np.mean((result.x_hat - run.x) ** 2, axis=0))
        click.echo("RMS error per state: " + ", ".join(
            f"{s.name} {e:.3g} {s.unit}".rstrip() for s, e in zip(system.states, rms)))
