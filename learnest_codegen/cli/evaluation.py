"""``learnest evaluate``: estimators of a model scored on many runs, per state group, against
the same estimators of another model."""

from __future__ import annotations

import click
import numpy as np

from .common import ESTIMATOR_HELP, FORCE, RESAMPLE, SYSTEM_HELP, EstimatorChoice, friendly, resolve_system


def _references(references: tuple[str, ...], names: list[str], runs, system) -> list:
    """Per run, its reference states ``(T, nx)``: the ``--reference`` files (one per run, in
    order, or a folder holding ``<run name>.csv``), else the run's truth columns."""
    from pathlib import Path

    from ..recordings.runs import read_reference

    if not references:
        missing = [n for n, r in zip(names, runs) if r.x is None]
        if missing:
            raise click.UsageError(f"runs {missing} hold no truth (x_ columns); give --reference (a CSV of "
                                   "t and x_<state> columns per run, or a folder of them named as the runs)")
        return [r.x for r in runs]
    if len(references) == 1 and Path(references[0]).is_dir():
        files = [Path(references[0]) / f"{Path(n).name}.csv" for n in names]
    elif len(references) == len(runs):
        files = [Path(r) for r in references]
    else:
        raise click.UsageError(f"{len(references)} --reference for {len(runs)} runs: give one per run "
                               "(in the order of --data) or one folder")
    return [read_reference(f, system, r.t) for f, r in zip(files, runs)]


def _paired_summary(per_run: dict, groups: list[str]) -> dict:
    """Per group (and ``overall``): the mean change over the runs, the runs better, the worst."""
    summary = {}
    for g in groups:
        changes = {}
        for name, r in per_run.items():
            if g == "overall":
                changes[name] = r["overall_change"]
            elif g in r["model"] and r["against"].get(g, 0) > 0:
                changes[name] = 100 * (r["against"][g] - r["model"][g]) / r["against"][g]
        if changes:
            worst = min(changes, key=changes.get)
            summary[g] = {"mean": float(np.mean(list(changes.values()))), "runs": len(changes),
                          "better": int(sum(v > 0 for v in changes.values())), "worst": changes[worst],
                          "worst_run": worst}
    return summary


@click.command()
@click.option("--system", "system_name", default=None,
              help=SYSTEM_HELP + " (default: the one --model records; cartpole otherwise)")
@click.option("--data", multiple=True, required=True,
              help="run CSV; give --data several times, a folder or a glob to evaluate many runs")
@click.option("--reference", "references", multiple=True,
              help="reference states of a run: a CSV of t and any x_<state> columns (empty cells: "
                   "no reference there), one per --data in order, or a folder of <run>.csv "
                   "(default: the runs' x_ columns)")
@click.option("--estimator", "estimators", multiple=True, type=EstimatorChoice(),
              default=("ukf",), show_default=True, help=ESTIMATOR_HELP)
@click.option("--model", default="nominal", show_default=True, help="nominal, true, or a model directory")
@click.option("--against", default="nominal", show_default=True,
              help="the estimator model each run's change is measured against (nominal, true or a "
                   "model directory)")
@click.option("--build", type=click.Path(file_okay=False), default=".learnest_compiled", show_default=True,
              help="folder for the compiled estimators (reused while a model is unchanged)")
@click.option("--out", type=click.Path(dir_okay=False), default=None,
              help="write every figure as JSON here")
@RESAMPLE
@FORCE
@friendly
def evaluate(system_name, data, references, estimators, model, against, build, out, resample, force) -> None:
    """Score estimators of a model on many runs, per state group, against the same estimators
    of another model (default: the nominal prior).

    States are grouped by unit (position, velocity, ...); per run and group the MSE against
    the reference and the change 100 (MSE against - MSE model) / MSE against (positive: the
    model is better), and a normalised overall change in which every group weighs the same
    (each group's MSE over the --against estimator's). Over the runs: the mean change, the runs
    better and the worst run, per group. A run that repeats another's data is counted once."""
    from ..evaluation import format_table, group_mse, normalised_change, run_estimator, state_groups
    from ..outputs import atomic_file, claim_output
    from ..pipeline import make_estimator, resolve
    from ..recordings.runs import read_runs, run_paths

    paths = run_paths(data)
    if out is not None:
        claim_output(out, inputs=tuple(str(p) for p in paths), force=force)
    system = resolve_system(system_name, model if model not in ("nominal", "true") else
                            (against if against not in ("nominal", "true") else None))
    names, runs, findings = read_runs(paths, system, resample_runs=resample)
    refs = _references(references, names, runs, system)
    groups = state_groups(system)
    models = {"model": resolve(model, system), "against": resolve(against, system)}
    rows, report = [], {"runs": names, "groups": {g: [system.state_names[i] for i in idx]
                                                   for g, idx in groups.items()},
                        "findings": [f.to_json() for f in findings], "estimators": {}}
    for est in estimators:
        built = {k: make_estimator(m, est, system=system, out=build) for k, m in models.items()}
        per_run = {}
        for name, run, ref in zip(names, runs, refs):
            x0 = np.asarray(system.x0, float)
            mses = {k: group_mse(run_estimator(e, run, x0, f"{est}:{k}").x_hat, ref, groups)
                    for k, e in built.items()}
            per_run[name] = {**mses, "overall_change": normalised_change(mses["model"], mses["against"])}
        summary = _paired_summary(per_run, [*groups, "overall"])
        for g, v in summary.items():
            label = g if g == "overall" else f"{g} ({', '.join(report['groups'][g])})"
            rows.append({"estimator": est, "group": label, "mean": v["mean"],
                         "better": f"{v['better']}/{v['runs']}",
                         "worst": f"{v['worst']:+.1f} % ({v['worst_run']})"})
        report["estimators"][est] = {"per_run": per_run, "summary": summary}
    click.echo(f"{model} against {against} on {len(runs)} run(s); change = 100 (MSE {against} - MSE "
               f"{model}) / MSE {against}, positive is better; overall: every state group weighs the same")
    click.echo(format_table(rows, [("estimator", "estimator", ""), ("group", "state group", ""),
                                   ("mean", "mean change [%]", "+.1f"), ("better", "runs better", ""),
                                   ("worst", "worst run", "")]))
    if out is not None:
        import json

        with atomic_file(out) as tmp:
            tmp.write_text(json.dumps(report, indent=1, allow_nan=True))
        click.echo(f"wrote {out}")
