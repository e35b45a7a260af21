"""The resumable, parallel sweep of Table I's jobs over tasks and seeds.

Jobs already done with the same configuration are skipped (``force`` redoes them); a failed
job is recorded in ``seed_<s>.error.json`` and the others go on; the nominal and true-dynamics
estimators are compiled once per task before any job starts. The results are combined into
the table at the end (:func:`.table1_report.combine`).
"""

from __future__ import annotations

import json
import os
import time
import traceback
from concurrent.futures import Future
from concurrent.futures import as_completed as _as_completed
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Mapping, Sequence

from ..errors import SettingsError, UnknownNameError
from .executors import check_executor, make_executor
from .store import code_hash, write_json
from .table1 import (
    BACKENDS,
    DEFAULT_OUT,
    DEFAULT_SEEDS,
    Job,
    TaskConfig,
    _resolved,
    compile_shared,
    run_job,
    shared_dir,
)
from .table1_report import Table1, combine


def record_failure(job: Job, exc: BaseException, tb: str | None = None, wall: float | None = None) -> dict:
    """Write ``job.error_path`` (error, traceback, configuration); returns the failure summary."""
    failure = {"status": "error", "task": job.task, "seed": job.seed, "config_hash": job.config_hash(),
               "error": f"{type(exc).__name__}: {exc}",
               "traceback": tb or "".join(traceback.format_exception(exc)),
               "wall_seconds": wall, "identity": job.identity()}
    write_json(job.error_path, failure)
    return failure


def execute_job(job: Job, job_fn: Callable[[Job], dict] | None = None) -> dict:
    """The function the executors run: ``run_job`` with its failure recorded, never raised.

    Returns ``{"status": "ok", "task", "seed", "wall_seconds", "mse": {label: mse}}`` or the
    failure summary of :func:`record_failure`.
    """
    start = time.perf_counter()
    try:
        results = (job_fn or run_job)(job)
    except Exception as exc:  # noqa: BLE001 - any failure of one job is recorded, the sweep goes on
        return record_failure(job, exc, wall=time.perf_counter() - start)
    job.error_path.unlink(missing_ok=True)  # an earlier failure of this job is history now
    return {"status": "ok", "task": job.task, "seed": job.seed, "wall_seconds": results["wall_seconds"],
            "mse": {k: v["mse"] for k, v in results["methods"].items()}}




@dataclass
class SweepReport:
    """What a sweep did: jobs run, skipped and failed, the wall time and the combined table."""

    total: int = 0
    ran: list[tuple[str, int]] = field(default_factory=list)
    skipped: list[tuple[str, int]] = field(default_factory=list)
    redone: list[tuple[str, int]] = field(default_factory=list)  # results of another configuration
    other_code: list[tuple[str, int]] = field(default_factory=list)  # skipped, made by other code
    failed: dict[tuple[str, int], str] = field(default_factory=dict)
    wall_seconds: float = 0.0
    shared_compile_seconds: dict[str, dict[str, float]] = field(default_factory=dict)
    table: "Table1 | None" = None


def plan_jobs(configs: Mapping[str, TaskConfig], seeds: int, *, out: str | Path,
              backend: str = "c") -> list[Job]:
    """Every (task, seed) job of a sweep."""
    out = str(Path(out))
    return [Job(task, s, cfg, backend, out, str(shared_dir(out, task)))
            for task, cfg in configs.items() for s in range(seeds)]


def run_sweep(configs: Mapping[str, TaskConfig], *, seeds: int = DEFAULT_SEEDS,
              out: str | Path = DEFAULT_OUT, jobs: int | None = None, executor: str = "local",
              backend: str = "c", force: bool = False, progress: bool = True,
              echo: Callable[[str], None] = print,
              job_fn: Callable[[Job], dict] | None = None) -> SweepReport:
    """Run the jobs of ``configs`` x ``range(seeds)`` not already done, then :func:`combine`.

    Parameters
    ----------
    configs : task name -> :class:`TaskConfig` (see :func:`task_configs`).
    jobs : parallel workers (default: all cores).
    executor : ``"local"``, ``"ray"`` or ``"dask"``.
    backend : ``"c"`` (compiled libraries) or ``"python"`` (the Python references).
    force : redo jobs whose results exist.
    job_fn : replaces :func:`run_job` (must be picklable; for tests).

    Failures of single jobs are recorded (``seed_<s>.error.json``) and listed in
    ``SweepReport.failed``; they do not stop the sweep.
    """
    if backend not in BACKENDS:
        raise UnknownNameError(f"unknown backend {backend!r}; choose from {list(BACKENDS)}")
    if seeds < 1:
        raise SettingsError(f"run_sweep: seeds must be >= 1, got {seeds}")
    check_executor(executor)
    start = time.perf_counter()
    out = Path(out)
    jobs = jobs or os.cpu_count() or 1
    report = SweepReport()
    prepared, broken = {}, {}
    for task, cfg in configs.items():
        try:
            prepared[task] = _resolved(cfg)
        except Exception as exc:  # noqa: BLE001 - this task's jobs fail, the others go on
            broken[task], prepared[task] = exc, cfg
    planned = plan_jobs(prepared, seeds, out=out, backend=backend)
    report.total = len(planned)

    todo: list[Job] = []
    for job in planned:
        if job.task in broken:
            continue
        status = _existing(job)
        if status == "same" and not force:
            report.skipped.append((job.task, job.seed))
            if _stored_code(job) != code_hash():
                report.other_code.append((job.task, job.seed))
            continue
        if status == "other":
            report.redone.append((job.task, job.seed))
            echo(f"{job.task} seed {job.seed}: results are of another configuration; redoing")
        todo.append(job)
    if report.other_code:
        names = ", ".join(f"{t} seed {sd}" for t, sd in report.other_code)
        echo(f"note: {len(report.other_code)} finished job(s) were made by other code than this "
             f"(the package's sources changed since, or predate this record): {names}. Their "
             f"results are kept; use --force to redo them.")
    for job in planned:  # failed preparation: every job of that task is a recorded failure
        if job.task in broken:
            report.failed[job.task, job.seed] = record_failure(job, broken[job.task])["error"]

    if todo and backend == "c":
        for task in sorted({j.task for j in todo}):
            echo(f"compiling the nominal and true-dynamics estimators of {task} (shared by all seeds)")
            try:
                report.shared_compile_seconds[task] = compile_shared(prepared[task], shared_dir(out, task))
            except Exception as exc:  # noqa: BLE001
                for job in [j for j in todo if j.task == task]:
                    report.failed[job.task, job.seed] = record_failure(job, exc)["error"]
                todo = [j for j in todo if j.task != task]
    for job in todo:  # a redone job must not leave stale results behind if it fails now
        job.result_path.unlink(missing_ok=True)

    if todo:
        workers = min(jobs, len(todo))
        echo(f"running {len(todo)} of {len(planned)} jobs ({len(report.skipped)} already done) on "
             f"{workers} {executor} worker(s), backend {backend}")
        pool = make_executor(executor, workers, preload=("torch", "learnest_codegen.experiments.table1"))
        _dispatch(todo, pool, report, progress, echo, job_fn,
                  already=len(report.skipped) + len(report.failed), total=len(planned))
    elif planned:
        echo(f"all {len(planned)} jobs already done (use --force to redo)")

    report.wall_seconds = time.perf_counter() - start
    sweep = {"wall_seconds": report.wall_seconds, "jobs_total": report.total, "jobs_run": len(report.ran),
             "jobs_skipped": len(report.skipped), "jobs_failed": len(report.failed),
             "workers": min(jobs, len(todo)), "jobs_option": jobs, "cpu_count": os.cpu_count(),
             "executor": executor, "backend": backend, "seeds": seeds,
             "tasks": {t: c.to_json() for t, c in prepared.items()},
             "shared_compile_seconds": report.shared_compile_seconds, "code": code_hash(),
             "made_by_other_code": [f"{t}/seed_{s}" for t, s in report.other_code],
             "failed": {f"{t}/seed_{s}": e for (t, s), e in report.failed.items()}}
    report.table = combine(out, sweep=sweep)
    return report


def _stored_code(job: Job) -> str | None:
    try:
        return json.loads(job.result_path.read_text()).get("code")
    except (json.JSONDecodeError, OSError):
        return None


def _existing(job: Job) -> str:
    """``"none"``, ``"same"`` (results of this configuration) or ``"other"``."""
    if not job.result_path.is_file():
        return "none"
    try:
        return "same" if json.loads(job.result_path.read_text()).get("config_hash") == job.config_hash() \
            else "other"
    except (json.JSONDecodeError, OSError):
        return "other"


def _dispatch(todo: Sequence[Job], pool, report: SweepReport, progress: bool, echo, job_fn,
              *, already: int, total: int) -> None:
    from tqdm.auto import tqdm

    bar = tqdm(total=total, initial=already, desc="table1 jobs", unit="job",  # quiet off a terminal
               disable=None if progress else True, dynamic_ncols=True)
    say = echo if bar.disable else bar.write
    futures: dict[Future, Job] = {}
    try:
        for job in todo:
            futures[pool.submit(execute_job, job, job_fn) if job_fn else pool.submit(execute_job, job)] = job
        for n, future in enumerate(_as_completed(futures), start=already + 1):
            job = futures[future]
            try:
                outcome = future.result()
            except Exception as exc:  # noqa: BLE001 - the worker itself died (or could not pickle)
                outcome = record_failure(job, exc)
            bar.update(1)
            if outcome["status"] == "ok":
                report.ran.append((job.task, job.seed))
                mse = outcome["mse"]
                say(f"[{n}/{total}] {job.task} seed {job.seed}: done in {outcome['wall_seconds']:.1f} s; "
                    f"MSE x1e-3 MHE {mse['MHE'] * 1e3:.4g} -> KNODE {mse['KNODE-MHE'] * 1e3:.4g}, "
                    f"UKF {mse['UKF'] * 1e3:.4g} -> KNODE {mse['KNODE-UKF'] * 1e3:.4g}")
            else:
                report.failed[job.task, job.seed] = outcome["error"]
                say(f"[{n}/{total}] {job.task} seed {job.seed}: FAILED ({outcome['error'].splitlines()[0]}); "
                    f"see {job.error_path}")
    except KeyboardInterrupt:
        pool.shutdown(cancel=True)
        raise
    finally:
        bar.close()
    pool.shutdown()
