"""The run data format: one CSV per run, read and written in one place.

Columns: ``t`` [s], ``u_<input>``, ``y_<output>`` and, when truth is known, ``x_<state>``,
named after the system's signals. Loading validates the columns against the system, checks that
time increases strictly and that every value is finite, and says exactly what is wrong.

Every model and compiled estimator steps at its system's ``dt``; a run sampled at another rate
would be estimated (or trained on) silently wrong, so :func:`check_sampling` compares the two and
:func:`resample` puts a run on the right grid when the user asks for it.
"""

from __future__ import annotations

import csv
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import DataError, SettingsError, ShapeError
from .outputs import atomic_file
from .systems import System

#: How far the median sampling period may differ from the expected ``dt`` (relative).
SAMPLING_RTOL = 0.01
#: How far a single step may differ from ``dt`` (relative): timestamp jitter, not a gap.
JITTER_RTOL = 0.5


@dataclass(frozen=True)
class Run:
    """One recorded or simulated run of a system.

    Attributes
    ----------
    t : (T,) sample times [s], strictly increasing.
    u : (T, nu) input applied from ``t[k]`` to ``t[k+1]``.
    y : (T, ny) measurement at ``t[k]``.
    x : (T, nx) true state at ``t[k]``, or ``None`` for real recordings.
    system : name of the system the columns belong to.
    """

    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    x: np.ndarray | None
    system: str

    def __post_init__(self) -> None:
        T = self.t.shape[0]
        for name, arr in (("u", self.u), ("y", self.y), ("x", self.x)):
            if arr is not None and (arr.ndim != 2 or arr.shape[0] != T):
                raise ShapeError(f"run.{name}: expected ({T}, n) to match t, got {arr.shape}")

    @property
    def dt(self) -> float:
        """Mean sampling period [s]."""
        return float(np.mean(np.diff(self.t)))

    @property
    def median_dt(self) -> float:
        """Median sampling period [s] (robust to a few late timestamps)."""
        return float(np.median(np.diff(self.t)))

    def __len__(self) -> int:
        return self.t.shape[0]


def columns(system: System, with_truth: bool) -> list[str]:
    """The CSV header of a run of ``system``."""
    cols = ["t"] + [f"u_{n}" for n in system.input_names] + [f"y_{n}" for n in system.output_names]
    return cols + ([f"x_{n}" for n in system.state_names] if with_truth else [])


def write_run(run: Run, system: System, path: str | Path) -> Path:
    """Write ``run`` as CSV (full double precision), atomically (whole file or none)."""
    path = Path(path)
    blocks = [run.t[:, None], run.u, run.y] + ([run.x] if run.x is not None else [])
    table = np.hstack(blocks)
    with atomic_file(path) as tmp, tmp.open("w", newline="") as fh:
        fh.write(",".join(columns(system, run.x is not None)) + "\n")
        np.savetxt(fh, table, delimiter=",", fmt="%.17g")
    return path


def read_run(path: str | Path, system: System) -> Run:
    """Read and validate a run CSV of ``system``; raise :class:`DataError` on any problem."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"run file {path} not found")
    with path.open(newline="") as fh:
        header = next(csv.reader(fh), None)
    if not header:
        raise DataError(f"{path}: empty file, expected a header with columns {columns(system, False)}")
    header = [h.strip() for h in header]
    missing = [c for c in columns(system, False) if c not in header]
    if missing:
        raise DataError(f"{path}: missing columns {missing} for system {system.name!r} (has {header})")
    try:
        with warnings.catch_warnings():  # an empty table is reported below as a DataError
            warnings.simplefilter("ignore", UserWarning)
            table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise DataError(f"{path}: non-numeric content: {exc}") from exc
    if table.shape[0] < 2:
        raise DataError(f"{path}: need at least 2 samples, got {table.shape[0]}")
    col = {name: i for i, name in enumerate(header)}
    bad = np.argwhere(~np.isfinite(table))
    if bad.size:
        r, c = bad[0]
        raise DataError(f"{path}: non-finite value in column {header[c]!r} at data row {r + 1} "
                        f"({len(bad)} non-finite values in all)")
    t = table[:, col["t"]]
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        raise DataError(f"{path}: time must increase strictly; t[{k + 1}]={t[k + 1]} after t[{k}]={t[k]}")
    pick = lambda prefix, names: table[:, [col[f"{prefix}_{n}"] for n in names]]  # noqa: E731
    truth_cols = [f"x_{n}" for n in system.state_names]
    x = pick("x", system.state_names) if all(c in col for c in truth_cols) else None
    return Run(t, pick("u", system.input_names), pick("y", system.output_names), x, system.name)


def check_sampling(run: Run, dt: float, where: str, *, rtol: float = SAMPLING_RTOL,
                   jitter: float = JITTER_RTOL) -> None:
    """Raise :class:`DataError` unless ``run`` is sampled every ``dt`` seconds.

    The median step must equal ``dt`` within ``rtol`` (relative), and every single step within
    ``jitter`` (relative: timestamp jitter passes, a dropped sample does not). The message says
    how to resample (``--resample`` on the command line, :func:`resample` in Python).
    """
    steps = np.diff(run.t)
    median = float(np.median(steps))
    if abs(median - dt) > rtol * dt:
        raise DataError(f"{where}: the run is sampled every {median:.6g} s (median step), but the "
                        f"{run.system} model steps every {dt:g} s; resample it (--resample, or "
                        f"learnest_codegen.data.resample) or use a model of that rate")
    k = int(np.argmax(np.abs(steps - dt)))
    if abs(steps[k] - dt) > jitter * dt:
        raise DataError(f"{where}: step {steps[k]:.6g} s from t={run.t[k]:.6g} s (sample {k}) is not "
                        f"the model's {dt:g} s within {jitter:.0%}: a gap or a time jump; resample "
                        f"the run (--resample) or cut it there")


def resample(run: Run, dt: float) -> Run:
    """``run`` on the uniform grid ``t[0] + k dt`` that fits inside it.

    Measurements and truth are interpolated linearly; the input is held (zero-order hold, the
    convention of :class:`Run`: ``u[k]`` applies from ``t[k]`` to ``t[k+1]``).
    """
    if not dt > 0:
        raise SettingsError(f"resample: need dt > 0, got {dt}")
    t = run.t[0] + dt * np.arange(int(np.floor((run.t[-1] - run.t[0]) / dt + 1e-9)) + 1)
    if len(t) < 2:
        raise DataError(f"resample: a run of {run.t[-1] - run.t[0]:g} s holds fewer than 2 samples "
                        f"at dt={dt:g} s")
    held = np.clip(np.searchsorted(run.t, t, side="right") - 1, 0, len(run) - 1)
    lerp = lambda a: np.column_stack([np.interp(t, run.t, col) for col in a.T])  # noqa: E731
    return Run(t, run.u[held], lerp(run.y), None if run.x is None else lerp(run.x), run.system)
