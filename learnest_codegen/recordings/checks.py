"""Checks a recording passes before it is used: what was found, where, and what was done.

A real log can hold the same recording twice under two names, spans in which a sensor
disagrees with the others (an accelerometer that drifts away while the motion capture shows
normal flight), inputs outside their range, or dropouts. Each check reports a
:class:`Finding` (the recording, the check, the span in seconds, what was found and what was
done about it: ``cut``, ``left out``, ``counted once``), printed on stderr by :func:`announce`
and listed in the reports, so nothing is dropped or shortened silently.

The helpers are format-neutral: :func:`content_key` and :func:`duplicates` find identical
recordings (any system), :func:`runs_of` and :func:`longest_run` turn a per-sample mask into
spans, and :func:`drift_onset` dates the start of a drift by a hinge fit.
"""

from __future__ import annotations

import hashlib
import sys
from dataclasses import asdict, dataclass
from typing import Iterable, Mapping, Sequence

import numpy as np

#: What a check did about what it found.
ACTIONS = ("cut", "left out", "counted once", "marked missing", "kept")


@dataclass(frozen=True)
class Finding:
    """One thing a check found in one recording.

    Attributes
    ----------
    recording : the recording's name (its file's stem).
    check : ``"duplicate"``, ``"accelerometer"``, ``"inputs"``, ``"dropout"``, ...
    start_s, end_s : the span it concerns, in seconds from the start of the log (``None``
        for the whole recording).
    detail : what was found, with its size.
    action : what was done (one of :data:`ACTIONS`), and ``note`` how (``"kept 0.0-27.1 s"``).
    """

    recording: str
    check: str
    start_s: float | None
    end_s: float | None
    detail: str
    action: str
    note: str = ""

    def line(self) -> str:
        """``"B2_x: accelerometer, 28.10-34.70 s: ...; cut (kept 3.4-27.1 s)"``."""
        where = "" if self.start_s is None else f", {self.start_s:.2f}-{self.end_s:.2f} s"
        return (f"{self.recording}: {self.check}{where}: {self.detail}; {self.action}"
                + (f" ({self.note})" if self.note else ""))

    def to_json(self) -> dict:
        return asdict(self)


def announce(findings: Iterable[Finding], stream=None) -> None:
    """One ``warning:`` line per finding on stderr (or ``stream``)."""
    stream = sys.stderr if stream is None else stream
    for finding in findings:
        print(f"warning: {finding.line()}", file=stream, flush=True)


def content_key(arrays: Sequence[np.ndarray]) -> str:
    """A hash of the numbers of a recording (shapes and float64 values): two recordings with
    the same key hold the same data, whatever their names or text formatting."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
        h.update(str(a.shape).encode() + b"\0" + a.tobytes())
    return h.hexdigest()[:20]


def duplicates(keys: Mapping[str, str]) -> dict[str, str]:
    """``name -> original`` for every recording whose key an earlier one (in the mapping's
    order) already has: each recording is counted once, under its first name."""
    first: dict[str, str] = {}
    out = {}
    for name, key in keys.items():
        if key in first:
            out[name] = first[key]
        else:
            first[key] = name
    return out


def duplicate_findings(keys: Mapping[str, str]) -> list[Finding]:
    """A ``duplicate`` finding (``counted once``) for every copy in ``keys`` (see :func:`duplicates`)."""
    return [Finding(name, "duplicate", None, None, f"the same data as {original}", "counted once",
                    f"{name} left out")
            for name, original in duplicates(keys).items()]


def runs_of(mask: np.ndarray) -> list[tuple[int, int]]:
    """``(first, last)`` index of every run of ``True`` in a 1-D bool array, in order."""
    padded = np.concatenate([[0], np.asarray(mask, bool).astype(np.int8), [0]])
    starts, ends = np.flatnonzero(np.diff(padded) == 1), np.flatnonzero(np.diff(padded) == -1)
    return [(int(s), int(e) - 1) for s, e in zip(starts, ends)]


def longest_run(mask: np.ndarray) -> tuple[int, int] | None:
    """The longest run of ``True`` (the first of equal ones), or ``None`` when there is none."""
    runs = runs_of(mask)
    return max(runs, key=lambda r: r[1] - r[0]) if runs else None


def grow(mask: np.ndarray, before: int, after: int) -> np.ndarray:
    """``mask`` with every run of ``True`` extended by ``before`` samples before it and
    ``after`` after it (clipped to the array)."""
    out = np.asarray(mask, bool).copy()
    for first, last in runs_of(mask):
        out[max(0, first - before):last + after + 1] = True
    return out


def drift_onset(deviation: np.ndarray, end: int, lookback: int) -> int:
    """Where a drift that ends (or is first noticed) at index ``end`` began: the hinge of the
    least-squares fit of ``deviation[end - lookback: end + 1]`` by a constant followed by a
    straight line (``c`` before the hinge, ``c + s (k - hinge)`` after). A threshold crossing
    comes late on a slow drift; the hinge dates its start."""
    lo = max(0, end - lookback)
    d = np.asarray(deviation[lo:end + 1], float)
    n = d.size
    if n < 4:
        return lo
    k = np.arange(n, dtype=float)
    h = np.arange(n - 2, dtype=float)  # candidate hinges; the ramp is (k - h) for k > h
    m = n - 1 - h  # samples on the ramp, at 1, 2, ..., m
    after_d = np.cumsum(d[::-1])[::-1]  # sum of d[j] for j >= i
    after_kd = np.cumsum((k * d)[::-1])[::-1]
    s_d = after_d[h.astype(int) + 1]
    s_rd = after_kd[h.astype(int) + 1] - h * s_d
    s_r, s_rr = m * (m + 1) / 2, m * (m + 1) * (2 * m + 1) / 6
    # normal equations of [1, ramp] per hinge, solved in closed form
    det = n * s_rr - s_r ** 2
    c = (s_rr * d.sum() - s_r * s_rd) / det
    s = (n * s_rd - s_r * d.sum()) / det
    sse = np.sum(d * d) - c * d.sum() - s * s_rd
    return lo + int(np.argmin(sse))
