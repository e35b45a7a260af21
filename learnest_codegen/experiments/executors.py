"""Where the jobs of a sweep run: a local process pool, a Ray cluster or a Dask cluster.

Each executor offers ``submit(fn, *args) -> Future`` and ``shutdown(cancel)``; the optional
ones (``pip install learnest_codegen[ray]`` / ``[dask]``) fail with a one-line error naming the
extra to install.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import Future, ProcessPoolExecutor
from typing import Callable, Sequence

from ..errors import LearnestError, UnknownNameError

EXECUTORS = ("local", "ray", "dask")



class MissingDependencyError(LearnestError, ImportError):
    """An optional dependency (an executor's package) is not installed."""


def _init_worker() -> None:
    """Process-pool initialiser: one thread per worker, so N workers use N cores."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[var] = "1"
    import torch

    torch.set_num_threads(1)


class LocalExecutor:
    """``jobs`` worker processes on this machine.

    Workers are forked from a fork server that has imported ``preload`` (torch and the job's
    module) but run nothing: safe, unlike forking a parent whose torch may have started threads, and cheap,
    unlike spawning, which re-imports torch in every worker.
    """

    name = "local"

    def __init__(self, jobs: int, preload: Sequence[str] = ("torch",)):
        import multiprocessing

        self.workers = jobs
        context = multiprocessing.get_context("forkserver")
        context.set_forkserver_preload(list(preload))
        self._pool = ProcessPoolExecutor(jobs, mp_context=context, initializer=_init_worker)

    def submit(self, fn: Callable, *args) -> Future:
        return self._pool.submit(fn, *args)

    def shutdown(self, cancel: bool = False) -> None:
        self._pool.shutdown(wait=not cancel, cancel_futures=cancel)


class RayExecutor:
    """Ray tasks of one CPU each; joins a running cluster (``RAY_ADDRESS``) or starts a local one."""

    name = "ray"

    def __init__(self, jobs: int):
        ray = _optional("ray", "ray")
        if not ray.is_initialized():
            ray.init(**({} if os.environ.get("RAY_ADDRESS") else {"num_cpus": jobs}))
        self.workers = jobs
        self._ray = ray
        self._remote = ray.remote(num_cpus=1)(_remote_entry)

    def submit(self, fn: Callable, *args) -> Future:
        return self._remote.remote(fn, *args).future()

    def shutdown(self, cancel: bool = False) -> None:
        pass  # a cluster we joined is not ours to stop; a local one ends with the process


def _remote_entry(fn, *args):
    _init_worker()
    return fn(*args)


class DaskExecutor:
    """A dask.distributed client: ``DASK_SCHEDULER_ADDRESS`` or a local cluster of ``jobs`` workers."""

    name = "dask"

    def __init__(self, jobs: int):
        distributed = _optional("dask.distributed", "dask")
        address = os.environ.get("DASK_SCHEDULER_ADDRESS")
        self._cluster = None if address else distributed.LocalCluster(
            n_workers=jobs, threads_per_worker=1, processes=True)
        self._client = distributed.Client(address or self._cluster)
        self.workers = jobs

    def submit(self, fn: Callable, *args) -> Future:
        future: Future = Future()
        dask_future = self._client.submit(_remote_entry, fn, *args, pure=False)

        def done(f):
            try:
                future.set_result(f.result())
            except BaseException as exc:  # noqa: BLE001 - handed to the caller's future
                future.set_exception(exc)

        dask_future.add_done_callback(done)
        return future

    def shutdown(self, cancel: bool = False) -> None:
        self._client.close()
        if self._cluster is not None:
            self._cluster.close()


EXECUTOR_CLASSES = {"local": LocalExecutor, "ray": RayExecutor, "dask": DaskExecutor}
EXECUTOR_MODULES = {"ray": "ray", "dask": "dask.distributed"}  # what the optional ones import


def _optional(module: str, extra: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise MissingDependencyError(f"the {extra} executor needs {module.split('.')[0]}, which is not "
                                     f"installed: pip install learnest_codegen[{extra}]") from exc


def check_executor(name: str) -> None:
    """Raise a one-line error now (before any work) if executor ``name`` is unknown or not installed."""
    if name not in EXECUTOR_CLASSES:
        raise UnknownNameError(f"unknown executor {name!r}; choose from {list(EXECUTORS)}")
    if name in EXECUTOR_MODULES:
        _optional(EXECUTOR_MODULES[name], name)


def make_executor(name: str, jobs: int, preload: Sequence[str] = ("torch",)):
    """An executor (``submit(fn, *args) -> Future``, ``shutdown(cancel)``) by name; ``preload``
    names the modules a local worker imports before it is forked."""
    check_executor(name)
    return LocalExecutor(jobs, preload) if name == "local" else EXECUTOR_CLASSES[name](jobs)


def cpu_seconds() -> float:
    """User and system CPU seconds of this process and of its finished children (the compilers a
    job runs), so far."""
    import resource

    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


class StageClock:
    """Wall and CPU seconds (:func:`cpu_seconds`) of a job's stages, ``wall`` and ``cpu`` (stage ->
    seconds, summed over the stage's calls), and of the whole job since the clock was made."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self._start, self._start_cpu = time.perf_counter(), cpu_seconds()

    def timed(self, stage: str, fn: Callable, *args, **kwargs):
        """``fn(*args, **kwargs)``, its seconds added to ``stage``."""
        wall, cpu = time.perf_counter(), cpu_seconds()
        value = fn(*args, **kwargs)
        self.wall[stage] = self.wall.get(stage, 0.0) + time.perf_counter() - wall
        self.cpu[stage] = self.cpu.get(stage, 0.0) + cpu_seconds() - cpu
        return value

    def wall_seconds(self) -> float:
        return time.perf_counter() - self._start

    def cpu_seconds(self) -> float:
        return cpu_seconds() - self._start_cpu
