"""The run data format: one CSV per run, read and written in one place.

Columns: ``t`` [s], ``u_<input>``, ``y_<output>`` and, when truth is known, ``x_<state>``,
named after the system's signals. Loading validates the columns against the system, checks that
time increases strictly and that every value is finite, and says exactly what is wrong.

Missing measurements. An empty (or ``nan``) cell in a ``y_`` column means "no sample of this
output at this time" -- a sensor slower than the run's rate, a dropout -- and is read as NaN,
the estimators' convention for a missing output (``estimators/contract.py``). Time, input and
truth cells must be numbers: an input is what was applied, and the estimators hold it between
samples themselves. :func:`write_run` writes a missing output as an empty cell.

Every model and compiled estimator steps at its system's ``dt``; a run sampled at another rate
would be estimated (or trained on) silently wrong, so :func:`check_sampling` compares the two and
:func:`resample` puts a run on the right grid when the user asks for it.
"""

from __future__ import annotations

import csv
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
    y : (T, ny) measurement at ``t[k]``; NaN: no sample of that output at ``t[k]``.
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

    @property
    def missing(self) -> np.ndarray:
        """(T, ny) bool: the outputs without a sample (NaN in ``y``)."""
        return np.isnan(self.y)


def columns(system: System, with_truth: bool) -> list[str]:
    """The CSV header of a run of ``system``."""
    cols = ["t"] + [f"u_{n}" for n in system.input_names] + [f"y_{n}" for n in system.output_names]
    return cols + ([f"x_{n}" for n in system.state_names] if with_truth else [])


def write_run(run: Run, system: System, path: str | Path) -> Path:
    """Write ``run`` as CSV (full double precision), atomically (whole file or none); a missing
    output (NaN) is an empty cell."""
    path = Path(path)
    blocks = [run.t[:, None], run.u, run.y] + ([run.x] if run.x is not None else [])
    table = np.hstack(blocks)
    cells = np.char.mod("%.17g", table)
    cells[np.isnan(table)] = ""
    with atomic_file(path) as tmp, tmp.open("w", newline="") as fh:
        fh.write(",".join(columns(system, run.x is not None)) + "\n")
        fh.writelines(",".join(row) + "\n" for row in cells)
    return path


def read_run(path: str | Path, system: System) -> Run:
    """Read and validate a run CSV of ``system``; raise :class:`DataError` on any problem.

    Empty or ``nan`` cells of ``y_`` columns are missing outputs (NaN in ``Run.y``); anything
    else that is not a finite real number is an error naming the file, the column and the row.
    A UTF-8 byte-order mark is accepted. The file is read as a stream: the memory it takes is
    the numbers of the columns used (8 bytes a cell) plus one block of rows as text.
    """
    path = Path(path)
    header, data = _read_table(path, columns(system, False), system.state_names)
    used = list(data)
    for name in used:
        bad = ~np.isfinite(data[name])
        if name.startswith("y_"):
            bad &= ~np.isnan(data[name])  # NaN: a missing output
        if bad.any():
            r = int(np.argmax(bad))
            if np.isnan(data[name][r]):
                why = "an empty or NaN value", "only measurement (y_) cells may be left empty (missing)"
            else:
                why = "an infinite value", "leave a measurement cell empty for a missing sample"
            raise DataError(f"{path}: {why[0]} in column {name!r} at data row {r + 1} "
                            f"({int(bad.sum())} in that column); {why[1]}")
    t = data["t"]
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        raise DataError(f"{path}: time must increase strictly; t[{k + 1}]={t[k + 1]} after t[{k}]={t[k]}")
    pick = lambda prefix, names: np.column_stack([data[f"{prefix}_{n}"] for n in names])  # noqa: E731
    x = pick("x", system.state_names) if "x_" + system.state_names[0] in data else None
    return Run(t, pick("u", system.input_names), pick("y", system.output_names), x, system.name)


#: Rows parsed at a time by :func:`_read_table` (their text is all it holds besides the numbers).
BLOCK_ROWS = 65536


def _read_table(path: Path, required: list[str],
                states: tuple[str, ...]) -> tuple[list[str], dict[str, np.ndarray]]:
    """The header and the used columns (``required``, plus every ``x_<state>`` when all are
    there) of a run CSV as float arrays, read block by block, with one-line errors for what is
    not one."""
    if not path.exists():
        raise FileNotFoundError(f"run file {path} not found")
    if not path.is_file():
        raise DataError(f"{path}: not a regular file (a folder or a device); expected a run CSV")
    with path.open(encoding="utf-8-sig", newline="") as fh:  # a byte-order mark is not a name
        try:
            return _parse(path, fh, required, states)
        except UnicodeDecodeError:
            pass
    raise _not_utf8(path)


def _parse(path: Path, fh, required: list[str],
           states: tuple[str, ...]) -> tuple[list[str], dict[str, np.ndarray]]:
    lines = _text_lines(path, fh)
    rows = (row for row in csv.reader(lines) if row and (len(row) > 1 or row[0].strip()))  # blank lines
    first = next(rows, None)
    if first is None:
        raise DataError(f"{path}: empty file, expected a header with columns {required}")
    header = [h.strip() for h in first]
    repeated = sorted({h for h in header if header.count(h) > 1})
    if repeated:
        raise DataError(f"{path}: column(s) {repeated} appear more than once in the header")
    missing = [c for c in required if c not in header]
    if missing:
        raise DataError(f"{path}: missing columns {missing} (has {header})")
    where = {name: i for i, name in enumerate(header)}
    truth = [f"x_{n}" for n in states]
    used = required + (truth if all(c in where for c in truth) else [])
    blocks: dict[str, list[np.ndarray]] = {name: [] for name in used}
    count = 0
    block: list[list[str]] = []
    for row in rows:
        if len(row) != len(header):
            ragged = 1 + sum(len(r) != len(header) for r in rows)
            raise DataError(f"{path}: data row {count + len(block) + 1} has {len(row)} values, "
                            f"the header {len(header)} ({ragged} such rows)")
        block.append(row)
        if len(block) == BLOCK_ROWS:
            _convert(path, block, where, blocks, count)
            count += len(block)
            block = []
    if block:
        _convert(path, block, where, blocks, count)
        count += len(block)
    if count < 2:
        raise DataError(f"{path}: need at least 2 samples, got {count}")
    return header, {name: np.concatenate(parts) for name, parts in blocks.items()}


def _text_lines(path: Path, fh):
    """The file's lines; a NUL byte is an error (a binary file, not a run CSV)."""
    for line in fh:
        if "\x00" in line:
            raise DataError(f"{path}: holds NUL bytes; expected a run CSV (text)")
        yield line


def _convert(path: Path, block: list[list[str]], where: dict[str, int],
             out: dict[str, list[np.ndarray]], start: int) -> None:
    """Append the used columns of ``block`` (rows ``start`` + 1 ... of the file) as floats."""
    for name, parts in out.items():
        parts.append(_column(path, name, [r[where[name]] for r in block], start))


def _not_utf8(path: Path) -> DataError:
    """The error for a file that is not UTF-8 text, naming its first bad byte and line."""
    import codecs

    decoder = codecs.getincrementaldecoder("utf-8")()
    offset, lines = 0, 1
    with path.open("rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            try:
                decoder.decode(chunk)
            except UnicodeDecodeError as exc:
                bad = offset + exc.start
                lines += chunk[:exc.start].count(b"\n")
                return DataError(f"{path}: not UTF-8 text (byte {bad}, line {lines}: "
                                 f"{chunk[exc.start:exc.start + 1]!r}); save the run CSV as UTF-8")
            offset += len(chunk)
            lines += chunk.count(b"\n")
    return DataError(f"{path}: not UTF-8 text; save the run CSV as UTF-8")


def _column(path: Path, name: str, cells: list[str], start: int = 0) -> np.ndarray:
    """The cells of one column (data rows ``start`` + 1 ...) as floats; an empty cell is NaN,
    text is an error."""
    cells = [c.strip() or "nan" for c in cells]
    try:
        return np.asarray(cells, dtype=float)
    except ValueError:
        for r, c in enumerate(cells):
            try:
                float(c)
            except ValueError:
                hint = " (a complex number: give its real part)" if _is_complex(c) else ""
                raise DataError(f"{path}: non-numeric value {c!r} in column {name!r} at data row "
                                f"{start + r + 1}{hint}") from None
        raise


def _is_complex(cell: str) -> bool:
    try:
        complex(cell.replace(" ", ""))
    except ValueError:
        return False
    return True


def unmeasured_outputs(run: Run, system: System, where: str) -> list[str]:
    """The outputs of ``run`` without a single sample (their ``y_`` column is empty throughout);
    :class:`DataError` when that is every output: the run holds no measurement to estimate or
    learn from."""
    empty = [name for name, col in zip(system.output_names, run.missing.T) if col.all()]
    if len(empty) == system.ny:
        raise DataError(f"{where}: the run holds no measurement: every y_ cell of "
                        f"{', '.join('y_' + n for n in empty)} is empty ({len(run)} samples); "
                        "fill in the measured outputs (an empty cell means a missing sample)")
    return empty


def longest_gap(run: Run) -> tuple[int, int]:
    """``(first sample, length)`` of the longest stretch of samples without any output
    (``(0, 0)`` when every sample has one)."""
    none = run.missing.all(axis=1).astype(np.int8)
    edges = np.diff(np.concatenate([[0], none, [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    if not len(starts):
        return 0, 0
    k = int(np.argmax(ends - starts))
    return int(starts[k]), int(ends[k] - starts[k])


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
    convention of :class:`Run`: ``u[k]`` applies from ``t[k]`` to ``t[k+1]``). A resampled
    output is missing where either raw sample it lies between is (an interpolation would
    invent a sample the sensor never took).
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
