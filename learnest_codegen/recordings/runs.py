"""Many recordings of any system at once: which files, each counted once, and their references.

``learnest train --data a.csv --data logs/`` trains one model on many runs and ``learnest
evaluate`` scores estimators on many; both name their runs through :func:`run_paths` (files,
folders, glob patterns) and read them with :func:`read_runs`, which counts a recording that
repeats another's data (the same run saved under two names) once and says so. A run's
reference states (for ``evaluate``) are its truth columns (``x_<state>``) or a separate
reference CSV (:func:`read_reference`), which may cover only some states.
"""

from __future__ import annotations

import csv
from glob import glob
from pathlib import Path
from typing import Sequence

import numpy as np

from ..data import Run, check_sampling, read_run, resample
from ..errors import DataError
from .checks import Finding, announce, content_key, duplicate_findings


def run_paths(specs: Sequence[str | Path]) -> list[Path]:
    """The run CSVs ``specs`` name, in order, each once: a file, a folder (its ``*.csv``,
    sorted) or a glob pattern (``logs/day2_*.csv``, sorted)."""
    out: list[Path] = []
    for spec in specs:
        text = str(spec)
        path = Path(text)
        if path.is_dir():
            found = sorted(p for p in path.glob("*.csv") if p.is_file())
        elif path.exists() and not any(ch in text for ch in "*?["):
            found = [path]  # a file, or a device or pipe that reading refuses by name
        elif any(ch in text for ch in "*?["):
            found = sorted(Path(p) for p in glob(text) if Path(p).is_file())
        else:
            raise FileNotFoundError(f"{text}: no such run file, folder or matching files")
        if not found:
            raise FileNotFoundError(f"{text}: no run CSV in it (expected *.csv files)")
        out += [p for p in found if p not in out]
    return out


def read_runs(specs: Sequence[str | Path], system, *, resample_runs: bool = False,
              echo: bool = True) -> tuple[list[str], list[Run], list[Finding]]:
    """``(names, runs, findings)``: every run ``specs`` name (:func:`run_paths`), read and
    checked against ``system`` (its columns and its sampling period, or resampled onto it),
    each recording once: a run with the same data as an earlier one is left out, with a
    ``duplicate`` finding (printed on stderr with ``echo``). Names are the files' stems (made
    unique with their folder when two files share one)."""
    paths = run_paths(specs)
    stems = [p.stem for p in paths]
    names = [p.stem if stems.count(p.stem) == 1 else f"{p.parent.name}/{p.stem}" for p in paths]
    runs, keys = {}, {}
    for name, path in zip(names, paths):
        run = read_run(path, system)
        if resample_runs:
            run = resample(run, system.dt)
        check_sampling(run, system.dt, str(path))
        runs[name] = run
        keys[name] = content_key([run.t - run.t[0], run.u, run.y])
    findings = duplicate_findings(keys)
    limits = getattr(system, "input_limits", None)
    if limits is not None:
        lo, hi = np.array([a for a, _ in limits]), np.array([b for _, b in limits])
        for name, run in runs.items():
            out = np.any((run.u < lo) | (run.u > hi), axis=1)
            if out.any():
                first, last = np.flatnonzero(out)[[0, -1]]
                findings.append(Finding(name, "inputs", float(run.t[first] - run.t[0]),
                                        float(run.t[last] - run.t[0]),
                                        f"{int(out.sum())} sample(s) with an input outside the system's "
                                        f"input_limits", "kept", "the estimators replace them by the last "
                                        "plausible input; training sees them as logged"))
    if echo:
        announce(findings)
    left_out = {f.recording for f in findings}
    kept = [n for n in names if n not in left_out]
    return kept, [runs[n] for n in kept], findings


def read_reference(path: str | Path, system, t: np.ndarray) -> np.ndarray:
    """Reference states for a run with times ``t`` from a CSV of ``t`` and any of the
    ``x_<state>`` columns, ``(T, nx)``: NaN for a state without a column, or an empty cell
    (no reference there). Its times must be the run's (to 1e-6 s)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"reference file {path} not found")
    with path.open(newline="", encoding="utf-8-sig") as fh:
        rows = [row for row in csv.reader(fh) if row]
    if not rows or "t" not in [h.strip() for h in rows[0]]:
        raise DataError(f"{path}: a reference CSV needs a header with 't' and x_<state> columns "
                        f"({', '.join('x_' + n for n in system.state_names)})")
    header = [h.strip() for h in rows[0]]
    known = {f"x_{n}": i for i, n in enumerate(system.state_names)}
    unknown = [h for h in header if h != "t" and h not in known]
    if unknown or len(header) < 2:
        raise DataError(f"{path}: columns {unknown or header} are not t or x_<state> of system "
                        f"{system.name!r} ({', '.join(known)})")

    def number(text: str, r: int, column: str) -> float:
        if not text.strip():
            return np.nan
        try:
            return float(text)
        except ValueError:
            raise DataError(f"{path}: {text!r} in column {column!r} at data row {r} is not a number") \
                from None

    body = rows[1:]
    if any(len(row) != len(header) for row in body):
        raise DataError(f"{path}: every row needs {len(header)} cells")
    table = np.array([[number(c, r + 1, header[j]) for j, c in enumerate(row)] for r, row in enumerate(body)])
    times = table[:, header.index("t")]
    if times.shape != t.shape or not np.allclose(times, t, rtol=0, atol=1e-6):
        raise DataError(f"{path}: its {len(times)} times are not the run's {len(t)} (a reference "
                        "has one row per run sample, at the same t)")
    out = np.full((len(t), system.nx), np.nan)
    for j, column in enumerate(header):
        if column != "t":
            out[:, known[column]] = table[:, j]
    return out
