"""``learnest demo`` and ``learnest reproduce table1|quadrotor``: the end-to-end demo and the paper's
experiments.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import click

from ..config import DEFAULT_TRAINING, TABLE1_CARTPOLE_TRAINING
from .common import SYSTEM_HELP, friendly, parse_covariance, parse_vector, system_named


@click.command()
@click.option("--system", "system_name", default="cartpole", show_default=True, help=SYSTEM_HELP)
@click.option("--out", default="out/demo", show_default=True, type=click.Path(file_okay=False))
@click.option("--epochs", default=DEFAULT_TRAINING.epochs, show_default=True)
@click.option("--observer", default=None,
              help="pre-training observer (default: chosen for the system, and said)")
@click.option("--duration", type=float, default=None, help="length of each run [s] (default: the system's)")
@click.option("--refine", default=DEFAULT_TRAINING.refine, show_default=True,
              help=f"model-based smoothing rounds (0 = paper; Table I uses "
                   f"{TABLE1_CARTPOLE_TRAINING.refine})")
@click.option("--restarts", type=click.IntRange(min=1), default=DEFAULT_TRAINING.restarts, show_default=True,
              help="initialisations per training round (the one whose model best explains the "
                   "measurements is kept; 1 = paper)")
@click.option("--weight-decay", type=click.FloatRange(min=0.0), default=DEFAULT_TRAINING.weight_decay,
              show_default=True, help="decoupled weight decay (AdamW; 0 = the paper's Adam)")
@click.option("--weight-average", type=click.FloatRange(min=0.0, max=1.0, max_open=True),
              default=DEFAULT_TRAINING.weight_average, show_default=True,
              help="keep the moving average of the weights (decay per step; 0 = the weights "
                   "themselves, as the paper)")
@click.option("--no-python-mhe", is_flag=True, help="skip the (slow) Python reference MHE")
@click.option("--x0", "x0_text", default=None,
              help="initial state guess of every estimator, one comma-separated value per state "
                   "(default: the system's x0)")
@click.option("--P0", "P0_text", default=None,
              help="its covariance: 'initial', nx variances or nx*nx entries (default: each "
                   "estimator's own)")
@friendly
def demo(system_name, out, epochs, observer, duration, refine, restarts, weight_decay, weight_average,
         no_python_mhe, x0_text, P0_text) -> None:
    """Simulate, train, compile and compare nominal and KNODE estimators on a test run.

    The training defaults are ``DEFAULT_TRAINING`` (learnest_codegen.config), as ``learnest
    train``'s."""
    from ..experiments.demo import run_demo

    training = replace(DEFAULT_TRAINING, epochs=epochs, refine=refine, restarts=restarts,
                       weight_decay=weight_decay, weight_average=weight_average)
    system = system_named(system_name)
    report = run_demo(system, out, training=training, observer=observer,
                      python_mhe=not no_python_mhe, duration=duration,
                      x0=parse_vector(x0_text, system.nx, "--x0"),
                      P0=parse_covariance(P0_text, system))
    click.echo("\n" + report.table())
    click.echo(f"\nfigures: {', '.join(report.figures)}\nreport: {Path(out) / 'report.json'}")


@click.group()
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
@friendly
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

    from .. import experiments as rep

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


#: ``reproduce quadrotor``'s configurations: the paper's (the defaults) and the best measured.
PAPER = {"features": "state,thrust", "estimators": "mhe,ukf"}
RECOMMENDED = {"features": "bias_lag_prior", "estimators": "ukf,mhe_rti", "tune_noise": False}


@reproduce.command("quadrotor")
@click.option("--data", type=click.Path(file_okay=False), default=None,
              help="data root or nanobench folder (default: ../shared/data or $LEARNEST_DATA)")
@click.option("--simulated", type=click.IntRange(min=2), default=None,
              help="use this many simulated quadrotor runs (seeds 0..N-1) instead of flights")
@click.option("--protocol", type=click.Choice(["single", "leave-type-out", "leave-one-out"]),
              default="single", show_default=True,
              help="single: train one model on each --train flight, test it on every other (the "
                   "paper's); leave-type-out: test each trajectory type on a model trained on the "
                   "other types; leave-one-out: test each flight on a model trained on all others. "
                   "--train SET --test SET trains one model on a set and tests it on another")
@click.option("--train", "train_names", default=None,
              help="single protocol: comma-separated training flights, one model each (default: "
                   "B2_circle_medium_rep1, or sim_seed0); with --test: the training set, flight CSVs "
                   "as folders, globs or files (comma-separated), one model trained on all of them")
@click.option("--test", "test_set", default=None,
              help="the test set (folders, globs or files, comma-separated): one model trained on "
                   "--train, tested on every flight here (a flight that repeats a training flight's "
                   "data is left out)")
@click.option("--all-train", is_flag=True,
              help="single protocol: repeat with every flight as the training flight")
@click.option("--recommended", is_flag=True,
              help=f"the configuration measured best on held-out trajectory types: features "
                   f"{RECOMMENDED['features']} (accelerometer offset and lag states, fitted prior), "
                   f"estimators {RECOMMENDED['estimators']}, the system's noise (add --tune-noise to "
                   f"choose it on the training flights; docs/reports/flights_study.md); use it with "
                   f"--protocol leave-type-out or --train/--test")
@click.option("--features", default=None,
              help="comma-separated (default: state,thrust, the paper's and its thrust variant; "
                   f"--recommended: {RECOMMENDED['features']}): state (residual on v, a: system "
                   "quadrotor_state), "
                   "thrust (v, a, thrust, vbat: system quadrotor), linear (prior A x with "
                   "acceleration rows fitted to the training flights, residual on v, a: system "
                   "quadrotor_linear), linear_prior (that fitted prior alone, no net), "
                   "thrust_prior, thrust_prior_axes, thrust_prior_z (fitted priors with the thrust "
                   "command: system quadrotor_thrust_linear), thrust_linear (thrust_prior and a "
                   "residual on v, a); bias (the triple integrator with accelerometer offset states), "
                   "bias_prior, bias_linear, bias_thrust_prior, bias_thrust_prior_axes (linear_prior, "
                   "linear, thrust_prior, thrust_prior_axes with the offsets); bias_lag, bias_lag_prior "
                   "(bias, bias_prior with the accelerometer read through a lag, chosen with "
                   "--tune-noise); see docs/reports/flights_study.md")
@click.option("--matrix", default="", show_default=True,
              help="single protocol: more training flights, tested with the UKF only (comma-separated, "
                   "or 'default' for a slow and a fast circle and figure-eight)")
@click.option("--estimators", default=None,
              help="comma-separated: mhe, ukf, mhe_gn, mhe_rti (default: mhe,ukf; --recommended: "
                   "ukf,mhe_rti)")
@click.option("--epochs", default=150, show_default=True, type=click.IntRange(min=1))
@click.option("--weight-decay", type=click.FloatRange(min=0.0), default=0.0, show_default=True,
              help="decoupled weight decay of the net (AdamW; 0 = the paper's Adam)")
@click.option("--observer", default="linear_rts", show_default=True,
              help="pre-training observer (rts: position only, per axis)")
@click.option("--clamp-inputs/--no-clamp-inputs", "clamp_inputs", default=None,
              help="keep the net's inputs inside their training range in the compiled estimators "
                   "(default: learnest_codegen.compilation.CLAMP_INPUTS)")
@click.option("--always-keep-net", is_flag=True,
              help="keep the trained net even when the prior alone has the lower validation loss "
                   "(default: such a net is zeroed and the model is its prior)")
@click.option("--tune-noise", is_flag=True,
              help="choose each KNODE estimator's noise scales on the training flights by how well "
                   "it predicts their raw position measurements, and the nominal estimators' the "
                   "same way as a control (docs/reports/flights_study.md)")
@click.option("--savgol-window", default=151, show_default=True, type=click.IntRange(min=3),
              help="Savitzky-Golay window of the paper's reference [samples] (the per-state tables "
                   "use 0.5, 1, 1.5 and 3 s and central differences)")
@click.option("--out", default="results/quadrotor", show_default=True, type=click.Path(file_okay=False))
@click.option("--force", is_flag=True, help="redo studies whose results already exist")
@friendly
def quadrotor(data, simulated, protocol, train_names, test_set, all_train, recommended, features, matrix,
              estimators, epochs, weight_decay, observer, clamp_inputs, always_keep_net, tune_noise,
              savgol_window, out, force) -> None:
    """The paper's quadrotor experiment (Fig. 3) on NanoBench Crazyflie flights, and protocols
    that test flights of a kind the model was not trained on.

    Trains KNODE, compiles the KNODE estimators, and compares each with its nominal estimator
    (and the onboard EKF's velocity) on the test flights. Reports per state group (position,
    velocity, acceleration) and a normalised overall, against references of several windows
    (central-difference velocity; Savitzky-Golay 0.5, 1, 1.5, 3 s), per flight and over the
    flights (mean, flights improved, worst flight); the tunings chosen; what the recording
    checks found (duplicates counted once, faulty spans cut, flights left out). Progress goes
    to stderr one line per step. Writes OUT/quadrotor.{md,json,png}.

    The defaults reproduce the paper (one training flight, features state and thrust); the
    best measured configuration is --recommended with --protocol leave-type-out, or
    --recommended --train DIR1 --test DIR2 for your own flights.
    """

    from ..experiments import quadrotor as fs
    from ..experiments.quadrotor_report import headline
    from ..experiments.quadrotor_states import state_tables
    from ..recordings import data_root

    split = lambda text: [p.strip() for p in text.split(",") if p.strip()]  # noqa: E731
    skipped, findings = None, []
    if test_set is not None and not train_names:
        raise click.UsageError("--test needs --train: the training set (flight folders, globs or files) "
                               "of the one model tested on --test")
    if test_set is not None and (simulated or protocol != "single" or all_train or matrix):
        raise click.UsageError("--train SET --test SET trains one model and tests it; it takes no "
                               "--protocol, --all-train, --matrix or --simulated")
    if simulated:
        cases, default = fs.simulated_cases(range(simulated)), "sim_seed0"
    elif test_set is not None:
        skipped = {}
        train_stems = {p.stem for spec in split(train_names) for p in fs.flight_paths(spec)}
        # training flights first: a test flight repeating one's data is the copy left out
        cases = fs.flight_cases([*split(train_names), *split(test_set)], skipped=skipped, findings=findings,
                                savgol_window=savgol_window)
        protocol, train, default = "train-test", [c.name for c in cases if c.name in train_stems], None
    else:
        root = data_root(data)
        if root is None:
            raise click.ClickException("no data folder found: pass --data DIR or set $LEARNEST_DATA")
        skipped = {}
        cases = fs.flight_cases(root, skipped=skipped, findings=findings, savgol_window=savgol_window)
        default = fs.DEFAULT_TRAIN
    if test_set is None:
        if protocol != "single" and (train_names or all_train or matrix):
            raise click.UsageError(f"--train, --all-train and --matrix belong to --protocol single, "
                                   f"not {protocol}")
        train = [c.name for c in cases] if all_train else split(train_names or default)
    chosen = RECOMMENDED if recommended else PAPER
    base = fs.StudySettings()
    settings = fs.StudySettings(training=replace(base.training, epochs=epochs, weight_decay=weight_decay),
                                observer=observer,
                                estimators=tuple(split(estimators or chosen["estimators"])),
                                clamp_inputs=clamp_inputs, net_must_beat_prior=not always_keep_net,
                                tune_noise=tune_noise or (recommended and RECOMMENDED["tune_noise"]))
    matrix = list(fs.DEFAULT_MATRIX) if matrix.strip() == "default" else split(matrix)
    summaries = fs.run_study(cases, out, train=train if protocol in ("single", "train-test") else (),
                             features=split(features or chosen["features"]), settings=settings,
                             protocol=protocol, matrix=matrix, force=force, skipped=skipped,
                             findings=findings)
    click.echo("\nPer state group and reference, change of KNODE against its nominal estimator over "
               "the test flights (mean; flights better; worst):")
    for s in summaries:
        click.echo("\n".join(state_tables(s)))
    click.echo("Paired change of the overall MSE against the paper's reference (positive is better):")
    click.echo(headline(summaries))
    click.echo(f"wrote {Path(out) / 'quadrotor.md'}, quadrotor.json, quadrotor.png")
