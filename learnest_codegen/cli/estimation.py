"""``learnest compile`` / ``learnest-compile`` and ``learnest estimate``: C estimators of a model,
and estimates of a run.
"""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from .common import (
    CLAMP_INPUTS,
    ESTIMATOR_CHOICES,
    ESTIMATOR_HELP,
    FORCE,
    PRECISION_HELP,
    RESAMPLE,
    SYSTEM_HELP,
    friendly,
    gate_settings,
    read_run,
    system_named,
    with_gate_options,
)


def _compile(model_dir: str | None, out: str, system_name: str | None, nominal: bool,
             estimators: tuple[str, ...], precision: str = "float64", gate=None,
             clamp_inputs: bool | None = None) -> dict:
    from ..compilation import compile_estimators, precision_problem, resolve_model

    if precision_problem(estimators, precision):
        raise click.UsageError(precision_problem(estimators, precision))
    if nominal:
        system = system_named(system_name or "cartpole")
        model, model_hash = resolve_model(system, "nominal")
    else:
        if model_dir is None:
            raise click.UsageError("give MODEL_DIR, or --nominal for the prior-only estimators")
        meta_path = Path(model_dir) / "model.json"
        if system_name is None and meta_path.is_file():
            system_name = json.loads(meta_path.read_text()).get("system")
        model, model_hash = resolve_model(system_named(system_name or "cartpole"), model_dir, clamp_inputs)
    results = compile_estimators(model, out, model_hash=model_hash, estimators=estimators,
                                 precision=precision, gate=gate)
    for name, res in results.items():
        click.echo(f"{name}: {res.directory}  ({res.code_bytes / 1024:.0f} KiB of C, "
                   f"built in {res.build_seconds:.2f} s{', reused' if res.build_seconds == 0 else ''})")
    return results


COMPILE_OPTIONS = [
    click.argument("model_dir", required=False, type=click.Path(file_okay=False)),
    click.option("--out", default="generated", show_default=True, type=click.Path(file_okay=False),
                 help="output directory (one subdirectory per estimator)"),
    click.option("--system", "system_name", default=None, help=SYSTEM_HELP + " (default: the model's)"),
    click.option("--nominal", is_flag=True, help="compile the prior-only (nominal) estimators"),
    click.option("--estimator", "estimators", multiple=True, type=click.Choice(ESTIMATOR_CHOICES),
                 default=("mhe", "ukf"), show_default=True, help=ESTIMATOR_HELP),
    click.option("--precision", type=click.Choice(["float64", "float32"]), default="float64",
                 show_default=True, help=PRECISION_HELP),
    CLAMP_INPUTS,
]


def _with_compile_options(fn):
    for option in reversed(COMPILE_OPTIONS):
        fn = option(fn)
    return with_gate_options(fn)


@click.command("compile")
@_with_compile_options
@friendly
def compile_cmd(model_dir, out, system_name, nominal, estimators, precision, clamp_inputs, gate_threshold,
                gate_recover_after, gate_inflation) -> None:
    """Generate C for the estimators of a model (default: MHE with Ipopt, UKF) and build them."""
    _compile(model_dir, out, system_name, nominal, tuple(estimators), precision,
             gate_settings(gate_threshold, gate_recover_after, gate_inflation), clamp_inputs)


@click.command("learnest-compile", context_settings={"help_option_names": ["-h", "--help"]})
@_with_compile_options
@friendly
def compile_standalone(model_dir, out, system_name, nominal, estimators, precision, clamp_inputs,
                       gate_threshold, gate_recover_after, gate_inflation) -> None:
    """Generate C for the estimators of a model (default: MHE with Ipopt, UKF) and build them."""
    _compile(model_dir, out, system_name, nominal, tuple(estimators), precision,
             gate_settings(gate_threshold, gate_recover_after, gate_inflation), clamp_inputs)


@click.command()
@click.option("--system", "system_name", default="cartpole", show_default=True, help=SYSTEM_HELP)
@click.option("--data", type=click.Path(exists=True, dir_okay=False), required=True, help="run CSV")
@click.option("--estimator", type=click.Choice(ESTIMATOR_CHOICES), required=True, help=ESTIMATOR_HELP)
@click.option("--model", default="nominal", show_default=True, help="nominal, true, or a model directory")
@click.option("--backend", type=click.Choice(["python", "c"]), default="c", show_default=True)
@click.option("--compiled", type=click.Path(file_okay=False), default=None,
              help="compiled estimator directory (C backend; default: compile on demand)")
@click.option("--precision", type=click.Choice(["float64", "float32"]), default="float64",
              show_default=True, help=PRECISION_HELP + "; C backend, when compiling on demand")
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="estimates CSV to write")
@CLAMP_INPUTS
@with_gate_options
@RESAMPLE
@FORCE
@friendly
def estimate(system_name, data, estimator, model, backend, compiled, precision, out, clamp_inputs,
             gate_threshold, gate_recover_after, gate_inflation, resample, force) -> None:
    """Run an estimator over a run; write t and one xhat_<state> column per state.

    Samples whose outputs the innovation gate rejected are counted in the summary line; they
    are not errors. With a trained model, the summary also gives the share of samples whose
    estimates and inputs lie outside the range the net was trained on."""
    from ..compilation import estimator_kind, precision_problem

    if backend == "c" and compiled is None and precision_problem((estimator,), precision):
        raise click.UsageError(precision_problem((estimator,), precision))
    if backend == "python" and estimator_kind(estimator).python is None:
        raise click.UsageError(f"{estimator} has no Python reference (its C defines it); use --backend c")
    from ..evaluation import mse, run_estimator
    from ..outputs import atomic_file, claim_output
    from ..pipeline import expected_manifest, load_estimator, make_estimator, resolve

    claim_output(out, inputs=(data, compiled, None if model in ("nominal", "true") else model),
                 force=force)
    system = system_named(system_name)
    run = read_run(data, system, resample)
    trained = None
    if model not in ("nominal", "true"):
        from ..learning.model import load_model

        trained = load_model(model, system)
    resolved = resolve(trained or model, system, clamp_inputs=clamp_inputs)
    gate = gate_settings(gate_threshold, gate_recover_after, gate_inflation)
    if backend == "c" and compiled is not None:
        est = load_estimator(compiled, expect={"estimator": estimator, **expected_manifest(resolved)},
                             gate=gate)
    else:  # compiled on demand next to the output (reused while the model is unchanged)
        est = make_estimator(resolved, estimator, backend=backend, system=system, precision=precision,
                             out=Path(out).resolve().parent / ".learnest_compiled", gate=gate)
    result = run_estimator(est, run, np.asarray(system.x0, float), f"{estimator}:{model}:{backend}")
    header = "t," + ",".join(f"xhat_{n}" for n in system.state_names)
    with atomic_file(out) as tmp:
        np.savetxt(tmp, np.column_stack([run.t, result.x_hat]), delimiter=",", header=header,
                   comments="", fmt="%.17g")
    line = f"wrote {out}: {len(run)} estimates, {result.seconds_per_step * 1e6:.1f} us/step"
    if run.x is not None:
        line += f", MSE vs truth {mse(result.x_hat, run.x):.4e}"
    line += f", {result.rejections} output(s) rejected by the innovation gate"
    if trained is not None:
        from ..learning.ranges import extrapolation

        outside = extrapolation(trained, result.x_hat, run.u)
        line += ("; the model records no training range" if outside is None
                 else f"; {outside.describe()}")
    click.echo(line)
