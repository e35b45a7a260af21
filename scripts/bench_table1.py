"""Table I of the paper as ``learnest reproduce table1 --jobs 2`` produces it, with its wall time.

Runs the whole sweep in a fresh process (2 tasks x 15 seeds, every option at its default but
``--jobs``) into ``build/bench/table1`` and keeps its ``summary.json``: per task the MSE of the
eight rows over the seeds, the gap closure of each KNODE row, the full-state rows against the
true dynamics, the job times, and the sweep's raw wall time beside the machine's load, sampled
every 30 s while it ran. ``--from DIR`` reads an already finished sweep folder instead of
running one (for development); the figure's conditions then say so.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import figures

MINUTES = 40
ORDER = 60
OUT = figures.ROOT / "build" / "bench" / "table1"


def add_arguments(parser) -> None:
    parser.add_argument("--jobs", type=int, default=2, help="parallel jobs of the sweep (default 2)")
    parser.add_argument("--from", dest="from_dir", default=None, metavar="DIR",
                        help="read the finished sweep in DIR instead of running one (development)")


class LoadSampler(threading.Thread):
    """The 1-minute load average every ``period`` seconds until :meth:`stop`."""

    def __init__(self, period: float = 30.0):
        super().__init__(daemon=True)
        self.period, self.samples, self._halt = period, [], threading.Event()

    def run(self) -> None:
        while not self._halt.is_set():
            self.samples.append(os.getloadavg()[0])
            self._halt.wait(self.period)

    def stop(self) -> dict:
        self._halt.set()
        self.join()
        s = self.samples or [os.getloadavg()[0]]
        return {"mean": round(sum(s) / len(s), 2), "min": round(min(s), 2), "max": round(max(s), 2),
                "samples": len(s), "every_s": self.period}


def measure(args) -> tuple[dict, dict]:
    jobs = getattr(args, "jobs", 2)
    from_dir = getattr(args, "from_dir", None)
    command = ["learnest", "reproduce", "table1", "--jobs", str(jobs)]
    if from_dir:
        folder = Path(from_dir).resolve()
        shown = folder.relative_to(figures.ROOT) if folder.is_relative_to(figures.ROOT) else folder
        how = f"read from the finished sweep in {shown} (not run by this command)"
        load = None
    else:
        folder = OUT
        shutil.rmtree(folder, ignore_errors=True)
        how = f"run by this command: {' '.join(command)} --out {folder.relative_to(figures.ROOT)}"
        sampler = LoadSampler()
        sampler.start()
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "learnest_codegen.cli", *command[1:], "--out", str(folder),
                        "--no-progress"], check=True)
        wall = time.perf_counter() - start
        load = {**sampler.stop(), "process_wall_seconds": round(wall, 1)}
    summary = json.loads((folder / "summary.json").read_text())
    cond = figures.conditions(
        model="per job, the KNODE models the sweep trains (learnest_codegen.experiments.table1's task "
              "configurations: the partial-measurement net through the pre-training observer and the "
              "full-state net), the nominal and the true-dynamics models",
        run="per task (cartpole, ground_robot) and seed s = 0..14: training run seed 2s, test run "
            "seed 2s+1, the whole run", sweep=how, jobs=jobs, load_during_sweep=load)
    return {"tasks": summary["table"], "sweep": summary.get("sweep", {}),
            "paper_closure": summary.get("paper", {}).get("closure", {})}, cond


# -- views -------------------------------------------------------------------------------------

def _f(value, fmt: str = ".4g", scale: float = 1.0) -> str:
    return "–" if value is None else format(value * scale, fmt)


def _tasks(data: dict) -> dict:
    return data["figures"]["tasks"]


def render_table(data: dict) -> str:
    """The paper's layout: mean and std of the MSE over the seeds, the paper's beside them."""
    from learnest_codegen.experiments.table1 import METHOD_LABELS, TASK_TITLES

    tasks = _tasks(data)
    head = ["Method"]
    for t in tasks:
        head += [f"{TASK_TITLES.get(t, t)} μ", "σ", "paper μ", "paper σ"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, label in enumerate(METHOD_LABELS):
        if i == 4:
            lines.append("| " + " | ".join([""] * len(head)) + " |")
        cells = [label]
        for s in tasks.values():
            m = s["methods"][label]
            cells += [_f(m["mean_1e3"]), _f(m["std_1e3"]), _f(m["paper_mean_1e3"]), _f(m["paper_std_1e3"])]
        lines.append("| " + " | ".join(cells) + " |")
    cells = ["seeds"]
    for s in tasks.values():
        cells += [str(s["n_seeds"]), "", "15", ""]
    lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n\nMSE in units of 1e-3. " + render_conditions(data)


def render_closure(data: dict) -> str:
    """The gap closure of each KNODE row: of the means, the median and the worst seed."""
    lines = ["| Task | Row | of the means | median over seeds | min over seeds | paper |",
             "|---|---|---|---|---|---|"]
    for t, s in _tasks(data).items():
        for row, c in s["closure"].items():
            pct = [_f(c[k], ".2f", 100) for k in ("of_means", "median", "min", "paper")]
            lines.append(f"| {t} | {row} | " + " | ".join(f"{p} %" for p in pct) + " |")
    return "\n".join(lines)


def render_full_state(data: dict) -> str:
    """The full-state KNODE rows against the true dynamics: (μ_full − μ_true) / μ_true."""
    lines = ["| Task | Row | relative difference | paper |", "|---|---|---|---|"]
    for t, s in _tasks(data).items():
        for row, c in s["full_state_vs_true"].items():
            rel, paper = _f(c["rel_diff"], "+.1f", 100), _f(c["paper"], "+.1f", 100)
            lines.append(f"| {t} | {row} | {rel} % | {paper} % |")
    return "\n".join(lines)


def render_jobs(data: dict) -> str:
    """What a job costs, per task, and the sweep's wall time."""
    lines = ["| Task | job wall time (mean) | stages (mean) | MHE rows against the Ipopt MHE |",
             "|---|---:|---|---|"]
    for t, s in _tasks(data).items():
        stages = ", ".join(f"{k} {v:.1f} s" for k, v in s["timings_mean"].items())
        ref = s.get("ipopt_reference") or {}
        agree = (f"seed {', '.join(map(str, ref['seeds']))}: largest difference of an estimate "
                 f"{ref['max_abs_difference']:.1e}, of a row's MSE {ref['max_mse_relative_difference']:.1e} "
                 "(relative)") if ref else "–"
        lines.append(f"| {t} | {s['job_wall_seconds_mean']:.1f} s | {stages} | {agree} |")
    return "\n".join(lines) + "\n\n" + render_conditions(data)


def render_conditions(data: dict) -> str:
    c, sweep = data["conditions"], data["figures"]["sweep"]
    m, load = c["machine"], c.get("load_during_sweep")
    text = (f"Measured by `{data['command']}` on {c['date']}; the sweep {c['sweep']}: "
            f"{sweep.get('wall_seconds', float('nan')):.0f} s wall "
            f"({sweep.get('wall_seconds', 0) / 60:.1f} min), "
            f"{sweep.get('jobs_run', 0)} jobs run, {sweep.get('jobs_failed', 0)} failed, "
            f"{sweep.get('workers')} workers on {m['cpu']} ({m['cores']} cores)")
    if load:
        text += (f", at a 1-minute load of {load['mean']} on average ({load['min']}-{load['max']}, sampled "
                 f"every {load['every_s']:.0f} s)")
    return text + "."


if __name__ == "__main__":
    import bench

    sys.exit(bench.main(["table1", *sys.argv[1:]]))
