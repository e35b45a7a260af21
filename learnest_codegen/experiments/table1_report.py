"""Table I from the results of a sweep: mean and std per method, gap closures, the paper's
numbers beside ours, as Markdown, CSV, a figure and ``summary.json``."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .store import write_json
from .table1 import METHOD_LABELS, METHODS, PAPER_TABLE1, TASK_TITLES


def gap_closure(prior: float, knode: float, true: float) -> float:
    """``(prior - knode) / (prior - true)``: 1 closes the gap to true dynamics, 0 is no better
    than the prior (nan when prior and true are equal)."""
    gap = prior - true
    return float((prior - knode) / gap) if gap != 0 else math.nan


def relative_difference(value: float, reference: float) -> float:
    """``(value - reference) / reference`` (nan for a zero reference)."""
    return float((value - reference) / reference) if reference != 0 else math.nan


# KNODE rows and their baselines (prior, true dynamics) for the gap closure.
CLOSURE_ROWS = {
    "KNODE-MHE": ("MHE", "MHE (true dynamics)"),
    "KNODE-MHE (full state)": ("MHE", "MHE (true dynamics)"),
    "KNODE-UKF": ("UKF", "UKF (true dynamics)"),
    "KNODE-UKF (full state)": ("UKF", "UKF (true dynamics)"),
}
FULL_STATE_ROWS = {"KNODE-MHE (full state)": "MHE (true dynamics)",
                   "KNODE-UKF (full state)": "UKF (true dynamics)"}


def paper_closures(task: str) -> dict[str, float]:
    """The gap closures implied by the paper's Table I means (fractions)."""
    paper = PAPER_TABLE1.get(task)
    if not paper:
        return {}
    return {row: gap_closure(paper[p][0], paper[row][0], paper[t][0]) for row, (p, t) in CLOSURE_ROWS.items()}


@dataclass
class Table1:
    """The combined table: ``tasks[task]`` holds per method the MSEs over seeds and statistics."""

    tasks: dict[str, dict] = field(default_factory=dict)
    sweep: dict = field(default_factory=dict)
    markdown: str = ""
    files: list[str] = field(default_factory=list)


def load_results(out: str | Path) -> dict[str, list[dict]]:
    """All results files under ``OUT/runs``: task -> results, ordered by seed."""
    found: dict[str, list[dict]] = {}
    for path in sorted((Path(out) / "runs").glob("*/seed_*.json")):
        if path.name.endswith(".error.json"):
            continue
        try:
            results = json.loads(path.read_text())
        except json.JSONDecodeError:
            continue
        found.setdefault(path.parent.name, []).append(results)
    return {t: sorted(r, key=lambda x: x["seed"]) for t, r in sorted(found.items(), key=_task_order)}


def _task_order(item) -> tuple[int, str]:
    order = list(PAPER_TABLE1)
    return (order.index(item[0]) if item[0] in order else len(order), item[0])


def summarise(results: Sequence[dict], task: str) -> dict:
    """Statistics of one task's results files (see :class:`Table1`)."""
    seeds = [r["seed"] for r in results]
    mse = {m: np.array([r["methods"][m]["mse"] for r in results], dtype=float) for m in METHOD_LABELS}
    paper = PAPER_TABLE1.get(task, {})
    methods = {}
    for label in METHOD_LABELS:
        values = mse[label]
        methods[label] = {
            "mse": values.tolist(), "mean": float(values.mean()), "std": float(values.std()),
            "mean_1e3": float(values.mean() * 1e3), "std_1e3": float(values.std() * 1e3),
            "paper_mean_1e3": paper.get(label, (None, None))[0],
            "paper_std_1e3": paper.get(label, (None, None))[1],
            "us_per_step": float(np.mean([r["methods"][label]["us_per_step"] for r in results])),
        }
    papers = paper_closures(task)
    closure = {}
    for row, (prior, true) in CLOSURE_ROWS.items():
        per_seed = np.array([gap_closure(p, k, t) for p, k, t in zip(mse[prior], mse[row], mse[true])])
        finite = per_seed[np.isfinite(per_seed)]
        closure[row] = {
            "of_means": gap_closure(mse[prior].mean(), mse[row].mean(), mse[true].mean()),
            "per_seed": per_seed.tolist(),
            "median": float(np.median(finite)) if finite.size else math.nan,
            "min": float(finite.min()) if finite.size else math.nan,
            "paper": papers.get(row),
        }
    full = {}
    for row, true in FULL_STATE_ROWS.items():
        full[row] = {"rel_diff": relative_difference(mse[row].mean(), mse[true].mean()),
                     "paper": relative_difference(paper[row][0], paper[true][0]) if paper else None}
    training = {key: {stat: float(np.mean([r["training"][key][stat] for r in results]))
                      for stat in ("train_seconds", "best_epoch")} for key in ("knode", "knode_full")}
    timings = sorted({k for r in results for k in r.get("timings", {})})
    return {
        "ipopt_reference": _reference_summary(results),
        "n_seeds": len(results), "seeds": seeds, "methods": methods, "closure": closure,
        "full_state_vs_true": full, "training_mean": training,
        "timings_mean": {k: float(np.mean([r["timings"].get(k, 0.0) for r in results])) for k in timings},
        "job_wall_seconds_mean": float(np.mean([r["wall_seconds"] for r in results])),
        **_cpu_summary(results),
        "configurations": sorted({r.get("task_hash", "?") for r in results}),
        "backends": sorted({r.get("backend", "?") for r in results}),
        "code": sorted({r.get("code", "?") for r in results}),
    }


def _cpu_summary(results: Sequence[dict]) -> dict:
    """The jobs' CPU seconds (``cpu_seconds_total``, the mean per job and per stage), when every
    job recorded them (results files written before they were recorded have none)."""
    if not results or not all("cpu_seconds" in r for r in results):
        return {}
    stages = sorted({k for r in results for k in r["cpu_timings"]})
    return {"job_cpu_seconds_total": float(sum(r["cpu_seconds"] for r in results)),
            "job_cpu_seconds_mean": float(np.mean([r["cpu_seconds"] for r in results])),
            "cpu_timings_mean": {k: float(np.mean([r["cpu_timings"].get(k, 0.0) for r in results]))
                                 for k in stages}}


def _reference_summary(results: Sequence[dict]) -> dict:
    """The MHE rows' agreement with the Ipopt MHE where a job ran both (the reference seed)."""
    rows = [(r["seed"], label, v["reference"]) for r in results for label, v in r["methods"].items()
            if "reference" in v]
    if not rows:
        return {}
    return {"seeds": sorted({seed for seed, _, _ in rows}), "rows": len(rows),
            "max_abs_difference": max(ref["max_abs_difference"] for _, _, ref in rows),
            "max_mse_relative_difference": max(ref["mse_relative_difference"] for _, _, ref in rows),
            "per_row": {f"seed {seed}: {label}": ref for seed, label, ref in rows}}


def combine(out: str | Path, *, sweep: dict | None = None, figure: bool = True) -> Table1:
    """Combine every results file under ``out`` into table1.md/.csv/.png and summary.json.

    ``sweep`` (the sweep's wall time, jobs, cores) goes into summary.json; without it, the
    ``sweep`` entry of an existing summary.json is kept.
    """
    out = Path(out)
    summary_path = out / "summary.json"
    if sweep is None and summary_path.is_file():
        try:
            sweep = json.loads(summary_path.read_text()).get("sweep")
        except json.JSONDecodeError:
            sweep = None
    table = Table1(sweep=sweep or {})
    for task, results in load_results(out).items():
        table.tasks[task] = summarise(results, task)
    out.mkdir(parents=True, exist_ok=True)
    table.markdown = format_markdown(table)
    (out / "table1.md").write_text(table.markdown)
    write_csv(table, out / "table1.csv")
    table.files = [str(out / "table1.md"), str(out / "table1.csv")]
    if figure and table.tasks:
        table.files.append(str(plot_table1(table, out / "table1.png")))
    write_json(summary_path, {"table": table.tasks, "sweep": table.sweep,
                               "paper": {"table1_1e3": PAPER_TABLE1,
                                         "closure": {t: paper_closures(t) for t in PAPER_TABLE1}},
                               "files": table.files})
    table.files.append(str(summary_path))
    return table


def _f(value, fmt: str = ".4g", scale: float = 1.0) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    return format(value * scale, fmt)


def format_markdown(table: Table1) -> str:
    """Table I in the paper's layout plus gap closures and full state against true dynamics."""
    if not table.tasks:
        return "# Table I\n\nNo results yet.\n"
    tasks = list(table.tasks)
    lines = ["# Table I: MSE statistics (units of 1e-3; μ mean, σ std over seeds)", ""]
    head = ["Method"]
    for t in tasks:
        title = TASK_TITLES.get(t, t)
        head += [f"{title} μ", "σ", "paper μ", "paper σ"]
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, label in enumerate(METHOD_LABELS):
        if i == 4:
            lines.append("| " + " | ".join([""] * len(head)) + " |")
        cells = [label]
        for t in tasks:
            m = table.tasks[t]["methods"][label]
            cells += [_f(m["mean_1e3"]), _f(m["std_1e3"]), _f(m["paper_mean_1e3"]), _f(m["paper_std_1e3"])]
        lines.append("| " + " | ".join(cells) + " |")
    cells = ["seeds"]
    for t in tasks:
        cells += [str(table.tasks[t]["n_seeds"]), "", "15" if t in PAPER_TABLE1 else "", ""]
    lines.append("| " + " | ".join(cells) + " |")

    lines += ["", "## Gap closure: (MSE_prior − MSE_KNODE) / (MSE_prior − MSE_true)", "",
              "| Task | Row | of the means | median over seeds | min over seeds | paper |",
              "|---|---|---|---|---|---|"]
    for t in tasks:
        for row, c in table.tasks[t]["closure"].items():
            pct = [_f(c[k], ".1f", 100) for k in ("of_means", "median", "min", "paper")]
            lines.append(f"| {t} | {row} | " + " | ".join(f"{p} %" for p in pct) + " |")
    lines += ["", "## Full-state KNODE against true dynamics: (μ_full − μ_true) / μ_true", "",
              "| Task | Row | relative difference | paper |", "|---|---|---|---|"]
    for t in tasks:
        for row, c in table.tasks[t]["full_state_vs_true"].items():
            rel, paper = _f(c["rel_diff"], "+.1f", 100), _f(c["paper"], "+.1f", 100)
            lines.append(f"| {t} | {row} | {rel} % | {paper} % |")
    lines += ["", "## Cost per estimator step [µs] (mean over seeds)", "",
              "| Method | " + " | ".join(tasks) + " |", "|---|" + "---|" * len(tasks)]
    for m in METHOD_LABELS:
        lines.append(f"| {m} | " + " | ".join(_f(table.tasks[t]["methods"][m]["us_per_step"], ".1f")
                                              for t in tasks) + " |")
    lines.append("")
    for t in tasks:
        s = table.tasks[t]
        tm = s["timings_mean"]
        cpu = ""
        if "cpu_timings_mean" in s:  # the CPU seconds, where the jobs recorded them
            cpu = (f"; CPU {s['job_cpu_seconds_mean']:.1f} s ("
                   + ", ".join(f"{k} {v:.1f} s" for k, v in s["cpu_timings_mean"].items()) + ")")
        lines.append(f"- {t}: job wall time {s['job_wall_seconds_mean']:.1f} s on average ("
                     + ", ".join(f"{k} {v:.1f} s" for k, v in tm.items()) + f"){cpu}; best epochs "
                     f"{s['training_mean']['knode']['best_epoch']:.0f} (partial), "
                     f"{s['training_mean']['knode_full']['best_epoch']:.0f} (full state); "
                     f"backend {', '.join(s['backends'])}; code {', '.join(s.get('code', ['?']))}")
        ref = s.get("ipopt_reference") or {}
        if ref:
            lines.append(f"- {t}: the MHE rows ran on the embedded Gauss-Newton MHE (`mhe_gn`); on seed(s) "
                         f"{', '.join(map(str, ref['seeds']))} the Ipopt MHE ran beside it on the same "
                         f"{ref['rows']} rows: largest difference of an estimate "
                         f"{ref['max_abs_difference']:.2g}, of a row's MSE "
                         f"{ref['max_mse_relative_difference']:.2g} (relative)")
        if len(s["configurations"]) > 1:
            lines.append(f"- **warning**: the {t} results mix {len(s['configurations'])} configurations "
                         "(rerun with the same options, or --force)")
    sweep = table.sweep
    if sweep.get("wall_seconds") is not None:
        lines.append(f"- sweep: {sweep['wall_seconds']:.1f} s wall, {sweep.get('jobs_run', 0)} jobs run, "
                     f"{sweep.get('jobs_skipped', 0)} skipped, {sweep.get('jobs_failed', 0)} failed, "
                     f"{sweep.get('workers')} {sweep.get('executor')} workers on "
                     f"{sweep.get('cpu_count')} cores")
    return "\n".join(lines) + "\n"


def write_csv(table: Table1, path: Path) -> Path:
    """Rows = the 8 methods; per task: n, μ, σ (1e-3), the paper's μ, σ, and gap closures [%]."""
    header = ["method"]
    for t in table.tasks:
        header += [f"{t}_{c}" for c in ("n", "mu_1e-3", "sigma_1e-3", "paper_mu_1e-3", "paper_sigma_1e-3",
                                        "closure_of_means_pct", "closure_median_pct", "closure_min_pct",
                                        "paper_closure_pct", "rel_diff_to_true_pct", "us_per_step")]
    with open(path, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(header)
        for label in METHOD_LABELS:
            row: list[Any] = [label]
            for s in table.tasks.values():
                m, c = s["methods"][label], s["closure"].get(label)
                full = s["full_state_vs_true"].get(label)
                pct = lambda v: "" if v is None or not math.isfinite(v) else f"{100 * v:.3f}"  # noqa: E731
                row += [s["n_seeds"], f"{m['mean_1e3']:.6g}", f"{m['std_1e3']:.6g}",
                        "" if m["paper_mean_1e3"] is None else m["paper_mean_1e3"],
                        "" if m["paper_std_1e3"] is None else m["paper_std_1e3"],
                        pct(c["of_means"]) if c else "", pct(c["median"]) if c else "",
                        pct(c["min"]) if c else "", pct(c["paper"]) if c else "",
                        pct(full["rel_diff"]) if full else "", f"{m['us_per_step']:.2f}"]
            writer.writerow(row)
    return path


MODEL_COLOURS = {"nominal": "0.55", "knode": "tab:blue", "knode_full": "tab:green", "true": "black"}


def plot_table1(table: Table1, path: Path) -> Path:
    """Per task: each method's MSE over seeds (box and points) on a log scale, MHE and UKF grouped."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = list(table.tasks)
    fig, axes = plt.subplots(1, len(tasks), figsize=(6.5 * len(tasks), 4.8), squeeze=False)
    positions = [i + (1 if i >= 4 else 0) for i in range(len(METHODS))]  # a gap between MHE and UKF
    rng = np.random.default_rng(0)
    for ax, task in zip(axes[0], tasks):
        s = table.tasks[task]
        data = [np.array(s["methods"][m.label]["mse"]) for m in METHODS]
        box = ax.boxplot(data, positions=positions, widths=0.6, showfliers=False, patch_artist=True,
                         medianprops={"color": "0.2"})
        for patch, m in zip(box["boxes"], METHODS):
            patch.set_facecolor(MODEL_COLOURS[m.model])
            patch.set_alpha(0.25)
        for pos, values, m in zip(positions, data, METHODS):
            ax.scatter(pos + rng.uniform(-0.15, 0.15, values.size), values, s=12, zorder=3,
                       color=MODEL_COLOURS[m.model])
            paper = s["methods"][m.label]["paper_mean_1e3"]
            if paper is not None:
                ax.plot([pos - 0.3, pos + 0.3], [paper * 1e-3] * 2, color="tab:red", lw=1.5, zorder=4)
        ax.axvline(4, color="0.8", lw=1)
        ax.set_yscale("log")
        ax.set_xticks(positions)
        ax.set_xticklabels([m.label for m in METHODS], rotation=40, ha="right", fontsize=8)
        ax.set_ylabel("MSE over the test run")
        ax.set_title(f"{TASK_TITLES.get(task, task)} ({s['n_seeds']} seeds)")
        for x, name in ((1.5, "MHE"), (6.5, "UKF")):
            ax.text(x, 0.98, name, transform=ax.get_xaxis_transform(), ha="center", va="top",
                    fontweight="bold")
        ax.grid(True, axis="y", which="both", alpha=0.3)
    handles = [plt.Line2D([], [], marker="o", ls="", color=c, label=k) for k, c in MODEL_COLOURS.items()]
    handles.append(plt.Line2D([], [], color="tab:red", label="paper μ"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)
