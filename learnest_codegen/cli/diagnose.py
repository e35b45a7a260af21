"""``learnest diagnose``: the sim-to-real gap of a prior (see :mod:`learnest_codegen.diagnosis`).
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from .common import FORCE, RESAMPLE, SYSTEM_HELP, friendly, system_named


@click.command()
@click.option("--system", "system_name", default=None, help=SYSTEM_HELP)
@click.option("--data", type=click.Path(exists=True), default=None,
              help="a run CSV or a folder of them (project run format, or --format)")
@click.option("--format", "data_format", default="run", show_default=True,
              help="format of --data: run, or a reader in learnest_codegen.recordings (nanobench, dart)")
@click.option("--model", default=None, type=click.Path(file_okay=False),
              help="trained KNODE model directory to compare with (its system is the default of --system)")
@click.option("--out", default=None, type=click.Path(file_okay=False),
              help="folder for diagnosis.json, report.md and figures")
@click.option("--source", type=click.Choice(["auto", "truth", "observer"]), default="auto", show_default=True,
              help="state observations: the truth (x_ columns) when present, else the pre-training observer")
@click.option("--observer", default=None, help="pre-training observer (default: the system's own)")
@click.option("--estimators", default="mhe,ukf", show_default=True,
              help="nominal estimators run with the corrected prior ('' for none)")
@click.option("--backend", type=click.Choice(["c", "python"]), default="c", show_default=True)
@click.option("--kinds", default=None, help="comma-separated effect kinds to consider (default: all)")
@click.option("--estimator-runs", default=2, show_default=True, type=click.IntRange(min=1),
              help="with several runs (fitted together, each held out in turn): held-out runs "
                   "the estimators are scored on")
@click.option("--list-effects", is_flag=True, help="list the effect library of --system and exit")
@click.option("--selftest", is_flag=True, help="diagnose simulated runs with withheld effects; print a table")
@click.option("--case", "cases", multiple=True, help="self-test case key (repeatable; default: all)")
@click.option("--no-progress", is_flag=True)
@RESAMPLE
@FORCE
@friendly
def diagnose(system_name, data, data_format, model, out, source, observer, estimators, backend, kinds,
             estimator_runs, list_effects, selftest, cases, no_progress, resample, force) -> None:
    """Diagnose the sim-to-real gap of a prior: where it lies, which effect, how far it shrinks.

    Writes OUT/diagnosis.json and OUT/report.md with PNG figures. --list-effects prints the
    library; --selftest runs the withheld-effect self-test (estimators only when --estimators
    is given explicitly, as they compile per case).
    """
    import dataclasses

    from .. import diagnosis as dg

    kinds_t = tuple(k.strip() for k in kinds.split(",") if k.strip()) if kinds else None
    settings = dg.DiagnosisSettings(source=source, observer=observer, backend=backend, kinds=kinds_t,
                                    estimators=tuple(e.strip() for e in estimators.split(",") if e.strip()),
                                    estimator_runs=estimator_runs)
    if list_effects:
        from ..diagnosis import describe_library, library

        click.echo(describe_library(library(system_named(system_name or "cartpole"), kinds=kinds_t)))
        return
    if selftest:
        from ..diagnosis import selftest as st

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
    if data is None or out is None or (system_name is None and model is None and data_format == "run"):
        raise click.UsageError("give --system (unless --format or --model names it), --data and --out "
                               "(or --list-effects / --selftest)")
    from ..data import check_sampling
    from ..data import resample as to_grid
    from ..diagnosis.report import write_report
    from ..outputs import claim_output

    claim_output(out, inputs=(data, model), force=force, kind="dir")
    if system_name is None and model is not None and data_format == "run":  # the model's own
        from .common import resolve_system

        system_name = resolve_system(None, model)
    system, found = dg.load_recordings(system_name, data, data_format)
    if resample:
        if found.references is not None:
            raise click.UsageError(f"--resample applies to run CSVs; the {data_format} reader already puts "
                                   f"its recordings on the model's grid")
        found = dataclasses.replace(found, runs=[to_grid(r, system.dt) for r in found.runs])
    for name, r in zip(found.names, found.runs):
        check_sampling(r, system.dt, f"{data} ({name})")
    click.echo(compared_against(system, found.runs, settings, data))
    trained = None
    if model is not None:
        from ..learning.training import load_model

        trained = load_model(model, system)
    result = dg.diagnose(system, found, model=trained, settings=settings, work_dir=Path(out) / "work",
                         progress=not no_progress)
    result.write(out)
    report = write_report(result, out)
    click.echo(dg.summary(result.report))
    click.echo(f"wrote {Path(out) / 'diagnosis.json'} and {report}")


def compared_against(system, runs, settings, data) -> str:
    """One line saying which states the prior is compared against: the runs' true states
    (``x_`` columns; ``--source auto`` takes them when every run has them) or the
    pre-training observer's estimates from the measurements."""
    source = settings.source
    if source == "auto":
        source = "truth" if all(r.x is not None for r in runs) else "observer"
    if source == "truth":
        columns = ", ".join(f"x_{n}" for n in system.state_names)
        return (f"diagnose: comparing against the true states in {data} ({columns}); "
                "--source observer uses the measurements alone")
    observer = settings.observer or system.default_observer
    outputs = ", ".join(f"y_{n}" for n in system.output_names)
    return (f"diagnose: comparing against the states the {observer!r} observer estimates from "
            f"the measurements in {data} ({outputs})")
