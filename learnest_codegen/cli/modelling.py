"""``learnest simulate`` and ``learnest train``: a run from the true system, a model from a run.
"""

from __future__ import annotations

import click

from ..config import ACTIVATIONS
from ..config import DEFAULT_TRAINING as _TRAIN
from .common import FORCE, RESAMPLE, SYSTEM_HELP, friendly, read_run, system_named


@click.command()
@click.option("--system", "system_name", default="cartpole", show_default=True, help=SYSTEM_HELP)
@click.option("--seed", default=0, show_default=True, help="seeds the excitation and the noise")
@click.option("--duration", type=float, default=None, help="run length [s] (default: the system's)")
@click.option("--out", type=click.Path(dir_okay=False), required=True, help="run CSV to write")
@FORCE
@friendly
def simulate(system_name: str, seed: int, duration: float | None, out: str, force: bool) -> None:
    """Simulate the true system and write a run CSV (truth included)."""
    from ..data import write_run
    from ..outputs import claim_output
    from ..simulation import simulate as sim

    claim_output(out, force=force)
    system = system_named(system_name)
    run = sim(system, seed, duration=duration)
    write_run(run, system, out)
    click.echo(f"wrote {out}: {len(run)} samples of {system.name}, dt={run.dt:g} s")


@click.command()
@click.option("--system", "system_name", default="cartpole", show_default=True, help=SYSTEM_HELP)
@click.option("--data", multiple=True, required=True,
              help="training run CSV; give --data several times, a folder or a glob ('logs/*.csv') "
                   "to train one model on many runs (each recording once: a copy of another is "
                   "left out, and said)")
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
              help="pre-training observer turning (y, u) into state observations (default: chosen "
                   "for the system, and said; see `learnest_codegen.observers.OBSERVERS`)")
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
@click.option("--quiet", is_flag=True, help="print only the result line (no recipe, no progress)")
@RESAMPLE
@FORCE
@friendly
def train(system_name, data, out, epochs, learning_rate, batch_size, hidden, layers, activation,
          observer, full_state, refine, validation_fraction, restarts, weight_decay, final_learning_rate,
          weight_average, seed, quiet, resample, force) -> None:
    """Train the KNODE residual network on one run or many and write a model directory.

    The option defaults are the one default training, ``DEFAULT_TRAINING``
    (learnest_codegen.config), the same as the library's ``ln.train``. With many runs one model
    is trained on all of them: each run is observed on its own, and each holds out its own final
    part for early stopping. The model records its system, so later commands need no --system.
    On stderr: the recipe first, the observer chosen, then one line per training (the first, then
    each refinement round) with its best epoch, validation loss and the time so far; --quiet
    leaves only the result line."""
    from dataclasses import replace

    from ..config import NetworkSettings
    from ..learning.training import train_on_run
    from ..outputs import atomic_dir, claim_output
    from ..recordings.runs import read_runs, run_paths

    paths = run_paths(data)
    claim_output(out, inputs=tuple(str(p) for p in paths), force=force, kind="dir")
    system = system_named(system_name)
    if len(paths) > 1 and full_state:
        raise click.UsageError("--full-state trains on one run; give one --data")
    if len(paths) == 1:  # full states need no y
        runs, names = [read_run(str(paths[0]), system, resample, measured=not full_state)], [paths[0].stem]
    else:
        names, runs, _ = read_runs(paths, system, resample_runs=resample)
    settings = replace(_TRAIN, epochs=epochs, learning_rate=learning_rate, batch_size=batch_size, seed=seed,
                       network=NetworkSettings(layers, hidden, activation),
                       validation_fraction=validation_fraction, refine=refine, restarts=restarts,
                       weight_decay=weight_decay, final_learning_rate=final_learning_rate,
                       weight_average=weight_average)
    if not quiet:
        click.echo(recipe_line(settings, system.name, ", ".join(map(str, data)), sum(len(r) for r in runs),
                               observer, full_state),
                   err=True)
    if len(runs) == 1:
        model = train_on_run(runs[0], system, settings, observer=observer, full_state=full_state,
                             progress=not quiet)
    else:
        from ..learning.runs import train_on_runs

        if not quiet:
            click.echo(f"training one model on {len(runs)} runs: {', '.join(names)}", err=True)
        model = train_on_runs(runs, system, settings, names=names, observer=observer, progress=not quiet)
    with atomic_dir(out) as tmp:
        model.save(tmp)
    click.echo(f"wrote {out}: final loss {model.meta['final_loss']:.4e} "
               f"(prior alone {model.meta['prior_loss']:.4e}), observer {model.meta['observer']}, "
               f"{model.meta['train_seconds']:.1f} s")


def recipe_line(settings, system: str, data: str, samples: int, observer: str | None,
                full_state: bool) -> str:
    """What ``learnest train`` is about to do, in one line: the data, the observer, the epochs,
    refinement rounds, initialisations, weight decay and precision."""
    batch = "full batch" if settings.batch_size >= samples else f"batches of {settings.batch_size}"
    source = ("noisy full states, smoothed" if full_state
              else f"observer {observer}" if observer else "observer chosen for the system")
    rounds = 0 if full_state else settings.refine
    return (f"training {system} on {data} ({samples} samples): {source}; {settings.epochs} epochs "
            f"({batch}), {rounds} refinement round{'s' * (rounds != 1)}, {settings.restarts} "
            f"initialisation{'s' * (settings.restarts != 1)} per training"
            + (f" ({settings.refine_restarts} in the refinement rounds)"
               if rounds and settings.refine_restarts not in (None, settings.restarts) else "")
            + f", weight decay {settings.weight_decay:g}, {settings.precision}")
