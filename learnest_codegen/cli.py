"""The ``learnest`` command line (and ``learnest-compile``).

Commands: ``simulate``, ``train``, ``compile``, ``estimate``, ``demo``, ``reproduce table1``,
``reproduce quadrotor``, ``diagnose``.
Every ``--system`` accepts a built-in name or the path of a Python file defining ``SYSTEM``.
Errors a user can cause (the package's :class:`LearnestError`, missing or unwritable files,
values out of range) are printed as one clear line with exit code 1 instead of a traceback;
``LEARNEST_TRACEBACK=1`` shows the traceback. Outputs are never written over an input, nor over
an existing file or folder without ``--force``, and appear whole or not at all.
"""

from __future__ import annotations

import functools
import json
import os
import sys
from dataclasses import replace
from pathlib import Path

import click
import numpy as np

from .config import ACTIVATIONS, QUICK_TRAINING, RECOMMENDED_TRAINING
from .config import TRAIN_COMMAND_TRAINING as _TRAIN
from .errors import LearnestError

SYSTEM_HELP = "built-in system name (cartpole) or path to a .py file defining SYSTEM"


#: Failures a user can cause: the package's own errors, files (missing, unreadable, unwritable),
#: values out of range (settings' ValueError) and numerics that a bad input drives off a cliff.
USER_ERRORS = (LearnestError, OSError, ValueError, ArithmeticError, np.linalg.LinAlgError)


def _friendly(fn):
    """Turn the failures a user can cause into a one-line error (exit 1) instead of a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except USER_ERRORS as exc:
            if os.environ.get("LEARNEST_TRACEBACK"):
                raise
            message = " ".join(str(exc).split()) or type(exc).__name__
            raise click.ClickException(message) from exc

    return wrapper


FORCE = click.option("--force", is_flag=True, help="replace an existing output")
RESAMPLE = click.option("--resample", is_flag=True,
                        help="put a run sampled at another rate on the system's time step "
                             "(default: refuse such a run)")


def _read_run(data: str, system, resample: bool):
    """Read a run CSV and make sure it is sampled at the system's ``dt`` (or resample it)."""
    from .data import check_sampling, read_run
    from .data import resample as to_grid

    run = read_run(data, system)
    if resample:
        run = to_grid(run, system.dt)
    check_sampling(run, system.dt, str(data))
    return run


def _system(name: str):
    from .systems import get_system

    return get_system(name)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="learnest_codegen")
def cli() -> None:
    """Learned (KNODE) dynamics models to compiled C state estimators (MHE, UKF)."""


@cli.command()
@click.option("--system", "system_name", default="cartpole", show_default=True, help=SYSTEM_HELP)
@click.option("--seed", default=0, show_default=True, help="seeds the excitation and the noise")
@click.option("--duration", type=float, default=None, help="run length [s] (default: the system's)")
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="run CSV to write")
@FORCE
@_friendly
def simulate(system_name: str, seed: int, duration: float | None, out: str, force: bool) -> None:
    """Simulate the true system and write a run CSV (truth included)."""
    from .data import write_run
    from .outputs import claim_output
    from .simulation import simulate as sim

    claim_output(out, force=force)
    system = _system(system_name)
    run = sim(system, seed, duration=duration)
    write_run(run, system, out)
    click.echo(f"wrote {out}: {len(run)} samples of {system.name}, dt={run.dt:g} s")


@cli.command()
@click.option("--system", "system_name", default="cartpole", show_default=True, help=SYSTEM_HELP)
@click.option("--data", type=click.Path(exists=True, dir_okay=False), required=True, help="training run CSV")
@click.option("--out", type=click.Path(file_okay=False), required=True, help="model directory to write")
@click.option("--epochs", default=_TRAIN.epochs, show_default=True)
@click.option("--lr", "learning_rate", default=_TRAIN.learning_rate, show_default=True,
              help="Adam learning rate")
@click.option("--batch-size", default=_TRAIN.batch_size, show_default=True,
              help="pairs per step (at least the training pairs: full batch)")
@click.option("--hidden", default=_TRAIN.network.hidden, show_default=True, help="hidden neurons per layer")
@click.option("--layers", default=_TRAIN.network.layers, show_default=True,
              help="linear layers (2 = one hidden layer)")
@click.option("--activation", default=_TRAIN.network.activation, show_default=True,
              type=click.Choice(ACTIVATIONS))
@click.option("--observer", default=None,
              help="pre-training observer turning (y, u) into state observations "
                   "(default: the system's own; see `learnest_codegen.observers.OBSERVERS`)")
@click.option("--full-state", is_flag=True, help="train on noisy full states (needs x_ columns)")
@click.option("--refine", default=_TRAIN.refine, show_default=True,
              help="rounds of model-based (EKF-RTS) smoothing and retraining; 0 = the paper's method")
@click.option("--validation-fraction", default=_TRAIN.validation_fraction, show_default=True,
              help="final share of the run held out for early stopping; 0 disables")
@click.option("--restarts", type=click.IntRange(min=1), default=_TRAIN.restarts, show_default=True,
              help="initialisations trained per round; through an observer the one whose model "
                   "best explains the measurements (EKF likelihood) is kept, on full states the "
                   "lowest validation loss")
@click.option("--weight-decay", type=click.FloatRange(min=0.0), default=_TRAIN.weight_decay,
              show_default=True,
              help="decoupled weight decay (AdamW); 0.1 helps the cartpole's nets generalise")
@click.option("--final-lr", "final_learning_rate", type=click.FloatRange(min=0.0, min_open=True),
              default=_TRAIN.final_learning_rate,
              help="anneal the learning rate to this value (cosine); default: constant")
@click.option("--weight-average", type=click.FloatRange(min=0.0, max=1.0, max_open=True),
              default=_TRAIN.weight_average, show_default=True,
              help="validate and keep the moving average of the weights with this decay per step "
                   "(e.g. 0.99); 0 = the weights themselves")
@click.option("--seed", default=_TRAIN.seed, show_default=True)
@RESAMPLE
@FORCE
@_friendly
def train(system_name, data, out, epochs, learning_rate, batch_size, hidden, layers, activation,
          observer, full_state, refine, validation_fraction, restarts, weight_decay, final_learning_rate,
          weight_average, seed, resample, force) -> None:
    """Train the KNODE residual network on a run and write a model directory."""
    from .config import NetworkSettings, TrainingSettings
    from .learning.training import train_on_run
    from .outputs import atomic_dir, claim_output

    claim_output(out, inputs=(data,), force=force, kind="dir")
    system = _system(system_name)
    run = _read_run(data, system, resample)
    settings = TrainingSettings(epochs, learning_rate, batch_size, seed,
                                NetworkSettings(layers, hidden, activation), validation_fraction, refine,
                                restarts, weight_decay, final_learning_rate, weight_average)
    model = train_on_run(run, system, settings, observer=observer, full_state=full_state)
    with atomic_dir(out) as tmp:
        model.save(tmp)
    click.echo(f"wrote {out}: final loss {model.meta['final_loss']:.4e} "
               f"(prior alone {model.meta['prior_loss']:.4e}), {model.meta['train_seconds']:.1f} s")


def _compile(model_dir: str | None, out: str, system_name: str | None, nominal: bool,
             estimators: tuple[str, ...], precision: str = "float64") -> dict:
    from .compilation import compile_estimators, precision_problem, resolve_model

    if precision_problem(estimators, precision):
        raise click.UsageError(precision_problem(estimators, precision))
    if nominal:
        system = _system(system_name or "cartpole")
        model, model_hash = resolve_model(system, "nominal")
    else:
        if model_dir is None:
            raise click.UsageError("give MODEL_DIR, or --nominal for the prior-only estimators")
        meta_path = Path(model_dir) / "model.json"
        if system_name is None and meta_path.is_file():
            system_name = json.loads(meta_path.read_text()).get("system")
        model, model_hash = resolve_model(_system(system_name or "cartpole"), model_dir)
    results = compile_estimators(model, out, model_hash=model_hash, estimators=estimators,
                                 precision=precision)
    for name, res in results.items():
        click.echo(f"{name}: {res.directory}  ({res.code_bytes / 1024:.0f} KiB of C, "
                   f"built in {res.build_seconds:.2f} s{', reused' if res.build_seconds == 0 else ''})")
    return results


# the names of compilation.ESTIMATOR_NAMES (not imported here: it would load casadi for --help)
ESTIMATOR_CHOICES = ["mhe", "ukf", "mhe_gn", "mhe_rti"]
ESTIMATOR_HELP = ("mhe: the MHE solved by Ipopt (the reference); ukf: the UKF; mhe_gn: the "
                  "embedded MHE (Gauss-Newton, no Ipopt, no malloc) iterated to convergence, the "
                  "same estimates as mhe; mhe_rti: the embedded MHE with one Gauss-Newton "
                  "iteration per sample (real-time iteration, fastest)")
PRECISION_HELP = ("C real type: float32 for single-precision FPUs (ukf, mhe_gn and mhe_rti; the "
                  "float32 UKF uses sigma-point spread alpha = 0.5)")

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
]


def _with_compile_options(fn):
    for option in reversed(COMPILE_OPTIONS):
        fn = option(fn)
    return fn


@cli.command("compile")
@_with_compile_options
@_friendly
def compile_cmd(model_dir, out, system_name, nominal, estimators, precision) -> None:
    """Generate C for the estimators of a model (default: MHE with Ipopt, UKF) and build them."""
    _compile(model_dir, out, system_name, nominal, tuple(estimators), precision)


@click.command("learnest-compile", context_settings={"help_option_names": ["-h", "--help"]})
@_with_compile_options
@_friendly
def compile_standalone(model_dir, out, system_name, nominal, estimators, precision) -> None:
    """Generate C for the estimators of a model (default: MHE with Ipopt, UKF) and build them."""
    _compile(model_dir, out, system_name, nominal, tuple(estimators), precision)


@cli.command()
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
@RESAMPLE
@FORCE
@_friendly
def estimate(system_name, data, estimator, model, backend, compiled, precision, out, resample,
             force) -> None:
    """Run an estimator over a run; write t and one xhat_<state> column per state."""
    from .compilation import estimator_kind, precision_problem

    if backend == "c" and compiled is None and precision_problem((estimator,), precision):
        raise click.UsageError(precision_problem((estimator,), precision))
    if backend == "python" and estimator_kind(estimator).python is None:
        raise click.UsageError(f"{estimator} has no Python reference (its C defines it); use --backend c")
    from .evaluation import mse, run_estimator
    from .outputs import atomic_file, claim_output
    from .pipeline import expected_manifest, load_estimator, make_estimator, resolve

    claim_output(out, inputs=(data, compiled, None if model in ("nominal", "true") else model),
                 force=force)
    system = _system(system_name)
    run = _read_run(data, system, resample)
    resolved = resolve(model, system)
    if backend == "c" and compiled is not None:
        est = load_estimator(compiled, expect={"estimator": estimator, **expected_manifest(resolved)})
    else:  # compiled on demand next to the output (reused while the model is unchanged)
        est = make_estimator(resolved, estimator, backend=backend, system=system, precision=precision,
                             out=Path(out).resolve().parent / ".learnest_compiled")
    result = run_estimator(est, run, np.asarray(system.x0, float), f"{estimator}:{model}:{backend}")
    header = "t," + ",".join(f"xhat_{n}" for n in system.state_names)
    with atomic_file(out) as tmp:
        np.savetxt(tmp, np.column_stack([run.t, result.x_hat]), delimiter=",", header=header,
                   comments="", fmt="%.17g")
    line = f"wrote {out}: {len(run)} estimates, {result.seconds_per_step * 1e6:.1f} us/step"
    if run.x is not None:
        line += f", MSE vs truth {mse(result.x_hat, run.x):.4e}"
    click.echo(line)


@cli.command()
@click.option("--system", "system_name", default="cartpole", show_default=True, help=SYSTEM_HELP)
@click.option("--out", default="out/demo", show_default=True, type=click.Path(file_okay=False))
@click.option("--epochs", default=QUICK_TRAINING.epochs, show_default=True)
@click.option("--observer", default=None, help="pre-training observer (default: the system's own)")
@click.option("--duration", type=float, default=None, help="length of each run [s] (default: the system's)")
@click.option("--refine", default=QUICK_TRAINING.refine, show_default=True,
              help=f"model-based smoothing rounds (0 = paper; Table I uses {RECOMMENDED_TRAINING.refine})")
@click.option("--restarts", type=click.IntRange(min=1), default=QUICK_TRAINING.restarts, show_default=True,
              help="initialisations per training round (the one whose model best explains the "
                   "measurements is kept; 1 = paper)")
@click.option("--weight-decay", type=click.FloatRange(min=0.0), default=QUICK_TRAINING.weight_decay,
              show_default=True, help="decoupled weight decay (AdamW; 0 = the paper's Adam)")
@click.option("--weight-average", type=click.FloatRange(min=0.0, max=1.0, max_open=True),
              default=QUICK_TRAINING.weight_average, show_default=True,
              help="keep the moving average of the weights (decay per step; 0 = the weights "
                   "themselves, as the paper)")
@click.option("--no-python-mhe", is_flag=True, help="skip the (slow) Python reference MHE")
@_friendly
def demo(system_name, out, epochs, observer, duration, refine, restarts, weight_decay, weight_average,
         no_python_mhe) -> None:
    """Simulate, train, compile and compare nominal and KNODE estimators on a test run.

    The training defaults are ``QUICK_TRAINING`` (learnest_codegen.config)."""
    from .experiments.demo import run_demo

    training = replace(QUICK_TRAINING, epochs=epochs, refine=refine, restarts=restarts,
                       weight_decay=weight_decay, weight_average=weight_average)
    report = run_demo(_system(system_name), out, training=training, observer=observer,
                      python_mhe=not no_python_mhe, duration=duration)
    click.echo("\n" + report.table())
    click.echo(f"\nfigures: {', '.join(report.figures)}\nreport: {Path(out) / 'report.json'}")


@cli.group()
def reproduce() -> None:
    """Reproduce the paper's experiments (resumable sweeps over seeds)."""


@reproduce.command("table1")
@click.option("--tasks", default="cartpole,ground_robot", show_default=True,
              help="comma-separated tasks (see learnest_codegen.experiments.DEFAULT_TASKS)")
@click.option("--seeds", default=15, show_default=True, type=click.IntRange(min=1),
              help="jobs per task; job s trains on seed 2s and tests on seed 2s+1")
@click.option("--epochs", type=click.IntRange(min=1), default=None,
              help="training epochs of both KNODE models (default: per task)")
@click.option("--refine", type=click.IntRange(min=0), default=None,
              help="EKF-RTS refinement rounds of the partial-measurement model (default: per task)")
@click.option("--duration", type=float, default=None, help="length of each run [s] (default: the system's)")
@click.option("--jobs", type=click.IntRange(min=1), default=None, help="parallel jobs (default: all cores)")
@click.option("--executor", type=click.Choice(["local", "ray", "dask"]), default="local", show_default=True)
@click.option("--backend", type=click.Choice(["c", "python"]), default="c", show_default=True,
              help="compiled C estimators, or the Python references")
@click.option("--out", default="results/table1", show_default=True, type=click.Path(file_okay=False))
@click.option("--force", is_flag=True, help="redo jobs whose results already exist")
@click.option("--combine-only", is_flag=True, help="only remake the table and figure from existing results")
@click.option("--no-progress", is_flag=True, help="no progress bar (one line per finished job only)")
@_friendly
def table1(tasks, seeds, epochs, refine, duration, jobs, executor, backend, out, force, combine_only,
           no_progress) -> None:
    """Table I of the paper: 8 estimators on every task and seed.

    One job per (task, seed) writes OUT/runs/<task>/seed_<s>.json; finished jobs of the same
    configuration are skipped (resume), --force redoes them. All results present are combined
    into OUT/table1.md, table1.csv, table1.png and summary.json. A failed job is recorded in
    seed_<s>.error.json and the command exits non-zero after the others have run.
    """
    import os
    import time

    from . import experiments as rep

    start = time.perf_counter()
    if combine_only:
        table = rep.combine(out)
        failed = {}
    else:
        configs = rep.task_configs([t.strip() for t in tasks.split(",") if t.strip()], epochs=epochs,
                                   duration=duration, refine=refine)
        click.echo(rep.config_summary(configs))
        report = rep.run_sweep(configs, seeds=seeds, out=out, jobs=jobs or os.cpu_count(), executor=executor,
                               backend=backend, force=force, progress=not no_progress, echo=click.echo)
        table, failed = report.table, report.failed
    click.echo("\n" + table.markdown)
    click.echo(f"wrote {', '.join(table.files)}")
    click.echo(f"wall time {time.perf_counter() - start:.1f} s")
    if failed:
        listing = "; ".join(f"{t} seed {s}: {e.splitlines()[0]}" for (t, s), e in sorted(failed.items()))
        raise click.ClickException(f"{len(failed)} job(s) failed (tracebacks in "
                                   f"{Path(out) / 'runs'}/<task>/seed_<s>.error.json): {listing}")


@reproduce.command("quadrotor")
@click.option("--data", type=click.Path(file_okay=False), default=None,
              help="data root or nanobench folder (default: ../shared/data or $LEARNEST_DATA)")
@click.option("--simulated", type=click.IntRange(min=2), default=None,
              help="use this many simulated quadrotor runs (seeds 0..N-1) instead of flights")
@click.option("--train", "train_names", default=None,
              help="comma-separated training flight(s) (default: B2_circle_medium_rep1, or sim_seed0)")
@click.option("--all-train", is_flag=True, help="repeat with every flight as the training flight")
@click.option("--features", default="state,thrust", show_default=True,
              help="residual inputs: state (v, a: system quadrotor_state, the paper's) and/or "
                   "thrust (v, a, thrust, vbat: system quadrotor)")
@click.option("--matrix", default="", show_default=True,
              help="more training flights, tested with the UKF only (comma-separated, or 'default' "
                   "for a slow and a fast circle and figure-eight)")
@click.option("--estimators", default="mhe,ukf", show_default=True, help="mhe and/or ukf")
@click.option("--epochs", default=150, show_default=True, type=click.IntRange(min=1))
@click.option("--observer", default="linear_rts", show_default=True,
              help="pre-training observer (rts: position only, per axis)")
@click.option("--savgol-window", default=151, show_default=True, type=click.IntRange(min=3),
              help="Savitzky-Golay window of the reference [samples]")
@click.option("--out", default="results/quadrotor", show_default=True, type=click.Path(file_okay=False))
@click.option("--force", is_flag=True, help="redo studies whose results already exist")
@_friendly
def quadrotor(data, simulated, train_names, all_train, features, matrix, estimators, epochs,
              observer, savgol_window, out, force) -> None:
    """The paper's quadrotor experiment (Fig. 3) on NanoBench Crazyflie flights.

    Trains KNODE on one flight, compiles KNODE-MHE and KNODE-UKF, and compares them with the
    nominal MHE and UKF (and the onboard EKF's velocity) on every other flight against
    Savitzky-Golay reference states. Writes OUT/quadrotor.{md,json,png}.
    """

    from .experiments import quadrotor as fs
    from .recordings import data_root

    split = lambda text: [p.strip() for p in text.split(",") if p.strip()]  # noqa: E731
    skipped = None
    if simulated:
        cases, default = fs.simulated_cases(range(simulated)), "sim_seed0"
    else:
        root = data_root(data)
        if root is None:
            raise click.ClickException("no data folder found: pass --data DIR or set $LEARNEST_DATA")
        skipped: dict[str, str] = {}
        cases, default = fs.flight_cases(root, skipped=skipped, savgol_window=savgol_window), fs.DEFAULT_TRAIN
        for name, reason in skipped.items():
            click.echo(f"skipped {name}: {reason}", err=True)
    train = [c.name for c in cases] if all_train else split(train_names or default)
    base = fs.StudySettings()
    settings = fs.StudySettings(training=replace(base.training, epochs=epochs), observer=observer,
                                estimators=tuple(split(estimators)))
    matrix = list(fs.DEFAULT_MATRIX) if matrix.strip() == "default" else split(matrix)
    summaries = fs.run_study(cases, out, train=train, features=split(features), settings=settings,
                             matrix=matrix, force=force, skipped=skipped)
    click.echo("\n" + fs.markdown(summaries).split("### medians")[-1])
    click.echo(f"wrote {Path(out) / 'quadrotor.md'}, quadrotor.json, quadrotor.png")


@cli.command()
@click.option("--system", "system_name", default=None, help=SYSTEM_HELP)
@click.option("--data", type=click.Path(exists=True), default=None,
              help="a run CSV or a folder of them (project run format, or --format)")
@click.option("--format", "data_format", default="run", show_default=True,
              help="format of --data: run, or a reader in learnest_codegen.recordings (nanobench, dart)")
@click.option("--model", default=None, type=click.Path(file_okay=False),
              help="trained KNODE model directory to compare with")
@click.option("--out", default=None, type=click.Path(file_okay=False),
              help="folder for diagnosis.json, report.md and figures")
@click.option("--source", type=click.Choice(["auto", "truth", "observer"]), default="auto", show_default=True,
              help="state observations: the truth (x_ columns) when present, else the pre-training observer")
@click.option("--observer", default=None, help="pre-training observer (default: the system's own)")
@click.option("--estimators", default="mhe,ukf", show_default=True,
              help="nominal estimators run with the corrected prior ('' for none)")
@click.option("--backend", type=click.Choice(["c", "python"]), default="c", show_default=True)
@click.option("--kinds", default=None, help="comma-separated effect kinds to consider (default: all)")
@click.option("--pool/--no-pool", default=None,
              help="fit every run of a folder together, folds by run, each run held out in turn "
                   "[default: pool from 3 runs]")
@click.option("--estimator-runs", default=2, show_default=True, type=click.IntRange(min=1),
              help="with --pool: held-out runs the estimators are scored on")
@click.option("--list-effects", is_flag=True, help="list the effect library of --system and exit")
@click.option("--selftest", is_flag=True, help="diagnose simulated runs with withheld effects; print a table")
@click.option("--case", "cases", multiple=True, help="self-test case key (repeatable; default: all)")
@click.option("--no-progress", is_flag=True)
@RESAMPLE
@FORCE
@_friendly
def diagnose(system_name, data, data_format, model, out, source, observer, estimators, backend, kinds,
             pool, estimator_runs, list_effects, selftest, cases, no_progress, resample, force) -> None:
    """Diagnose the sim-to-real gap of a prior: where it lies, which effect, how far it shrinks.

    Writes OUT/diagnosis.json and OUT/report.md with PNG figures. --list-effects prints the
    library; --selftest runs the withheld-effect self-test (estimators only when --estimators
    is given explicitly, as they compile per case).
    """
    import dataclasses

    from . import diagnosis as dg

    kinds_t = tuple(k.strip() for k in kinds.split(",") if k.strip()) if kinds else None
    settings = dg.DiagnosisSettings(source=source, observer=observer, backend=backend, kinds=kinds_t,
                                    estimators=tuple(e.strip() for e in estimators.split(",") if e.strip()),
                                    pool=pool, estimator_runs=estimator_runs)
    if list_effects:
        from .diagnosis import describe_library, library

        click.echo(describe_library(library(_system(system_name or "cartpole"), kinds=kinds_t)))
        return
    if selftest:
        from .diagnosis import selftest as st

        systems = [system_name] if system_name else None
        explicit = click.get_current_context().get_parameter_source("estimators").name != "DEFAULT"
        if not explicit:
            settings = dataclasses.replace(settings, estimators=())
        rows = st.run_selftest(st.select_cases(list(cases) or None, systems), settings=settings,
                               progress=not no_progress)
        click.echo(st.table(rows))
        if out:
            Path(out).mkdir(parents=True, exist_ok=True)
            (Path(out) / "selftest.json").write_text(json.dumps(rows, indent=2))
            (Path(out) / "selftest.md").write_text(st.table(rows) + "\n")
        failed = [r["case"] for r in rows if not r["pass"]]
        if failed:
            raise click.ClickException(f"{len(failed)} self-test case(s) failed: {'; '.join(failed)}")
        return
    if data is None or out is None or (system_name is None and data_format == "run"):
        raise click.UsageError("give --system (unless --format names it), --data and --out "
                               "(or --list-effects / --selftest)")
    from .data import check_sampling
    from .data import resample as to_grid
    from .diagnosis.report import write_report
    from .outputs import claim_output

    claim_output(out, inputs=(data, model), force=force, kind="dir")
    system, runs = dg.load(system_name, data, data_format)
    if resample:
        runs = [to_grid(r, system.dt) for r in runs]
    for i, r in enumerate(runs):
        check_sampling(r, system.dt, f"{data} (run {i})")
    trained = None
    if model is not None:
        from .learning.training import load_model

        trained = load_model(model, system)
    result = dg.diagnose(system, runs, model=trained, settings=settings, work_dir=Path(out) / "work",
                         progress=not no_progress)
    result.write(out)
    report = write_report(result, out)
    click.echo(dg.summary(result.report))
    click.echo(f"wrote {Path(out) / 'diagnosis.json'} and {report}")


def main() -> None:
    """Entry point of ``learnest``."""
    cli(prog_name="learnest")


def compile_main() -> None:
    """Entry point of ``learnest-compile``."""
    compile_standalone(prog_name="learnest-compile")


if __name__ == "__main__":
    sys.exit(main())
