"""State observations of each run, and how runs are split into fitted and held-out data.

Missing samples (empty or NaN cells of a run) are tolerated: an input cell holds the last
command (what a held command is), a measurement cell is interpolated linearly in time for the
observer and the estimators (neither takes a gap), and a pair with a missing truth state is left
out of every fit. :func:`missing` counts them for the report.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..data import Run
from ..errors import DataError
from ..systems import System
from .blur import run_blur
from .fit import Pairs
from .settings import DiagnosisSettings


@dataclass
class Segment:
    """A stretch of one run with its state observations ``z`` and observer variances ``var``.

    ``reference`` is what estimators are scored against (the truth, a recording's own reference
    such as the quadrotor study's, or ``z``); ``start`` where they start (default its first row).
    """

    run: Run
    z: np.ndarray
    var: np.ndarray | None
    reference: np.ndarray
    start: np.ndarray | None = None
    blur: tuple = ()  # the chains the observer smoothed (see blur.py)

    @property
    def x0(self) -> np.ndarray:
        return self.reference[0] if self.start is None else self.start


def missing(runs: Sequence[Run]) -> dict:
    """Non-finite cells of the runs' inputs, measurements and truth (counts)."""
    out = {"inputs": 0, "measurements": 0, "truth": 0}
    for r in runs:
        out["inputs"] += int(np.sum(~np.isfinite(r.u)))
        out["measurements"] += int(np.sum(~np.isfinite(r.y)))
        out["truth"] += 0 if r.x is None else int(np.sum(~np.isfinite(r.x)))
    return out


def complete(run: Run, where: str = "run") -> Run:
    """``run`` with missing inputs held and missing measurements interpolated (see the module
    docstring); the truth is kept as it is. ``run`` itself when nothing is missing."""
    if np.isfinite(run.u).all() and np.isfinite(run.y).all():
        return run
    u = _hold(run.u, where, "input")
    y = np.array(run.y, dtype=float, copy=True)
    for j in range(y.shape[1]):
        ok = np.isfinite(y[:, j])
        if not ok.any():
            raise DataError(f"{where}: measurement column {j} has no finite value")
        if not ok.all():
            y[:, j] = np.interp(run.t, run.t[ok], y[ok, j])
    return Run(run.t, u, y, run.x, run.system)


def _hold(u: np.ndarray, where: str, what: str) -> np.ndarray:
    u = np.array(u, dtype=float, copy=True)
    for j in range(u.shape[1]):
        ok = np.isfinite(u[:, j])
        if not ok.any():
            raise DataError(f"{where}: {what} column {j} has no finite value")
        if ok.all():
            continue
        idx = np.where(ok, np.arange(len(ok)), 0)
        np.maximum.accumulate(idx, out=idx)
        idx[:int(np.argmax(ok))] = int(np.argmax(ok))
        u[:, j] = u[idx, j]
    return u


def observations(system: System, runs: Sequence[Run], settings: DiagnosisSettings,
                 references: Sequence[np.ndarray] | None = None,
                 starts: Sequence[np.ndarray] | None = None) -> tuple[str, list[Segment]]:
    """The source used (``"truth"`` or ``"observer"``) and one :class:`Segment` per run.

    ``references`` / ``starts``: per run, what the estimators are scored against and where they
    start (a recording's own, e.g. the quadrotor study's); default the truth or ``z``.
    """
    source = settings.source
    if source == "auto":
        source = "truth" if all(r.x is not None for r in runs) else "observer"
    if source == "truth" and any(r.x is None for r in runs):
        raise DataError("source 'truth' needs x_ columns in every run")
    from ..observers import observe

    segments = []
    for i, raw in enumerate(runs):
        run = complete(raw, f"run {i}")
        blur = ()
        if source == "truth":
            z, var = run.x, None
        else:
            obs = observe(run, system, settings.observer)
            z, var = obs.zeta, obs.variance
            blur = run_blur(system, len(run), float(np.median(np.diff(run.t))), obs.method, obs.info)
        ref = references[i] if references is not None else run.x if run.x is not None else z
        segments.append(Segment(run, z, var, np.asarray(ref, float),
                                None if starts is None else np.asarray(starts[i], float), blur))
    return source, segments


def cut_segment(seg: Segment, lo: int, hi: int) -> Segment:
    r = seg.run
    run = Run(r.t[lo:hi], r.u[lo:hi], r.y[lo:hi], None if r.x is None else r.x[lo:hi], r.system)
    start = seg.start if lo == 0 else None
    blur = tuple(_cut_blur(c, lo, hi) for c in seg.blur)
    return Segment(run, seg.z[lo:hi], None if seg.var is None else seg.var[lo:hi], seg.reference[lo:hi],
                   start, blur)


def _cut_blur(chain, lo: int, hi: int):
    """A chain's smoother over samples ``lo:hi`` only, with the gains the whole run's smoother has
    there. The data were smoothed as one run: within about the smoother's width of the cut the map
    misses the increments beyond it, a small residual at the stretch's two ends."""
    import dataclasses

    return dataclasses.replace(chain, gain=chain.gain[lo:hi],
                               back=None if chain.back is None else chain.back[lo:hi - 1])


def split(segments: list[Segment], holdout: float) -> tuple[list[Segment], list[Segment]]:
    """Fit and held-out segments: the last run held out, or the end of a single run."""
    if len(segments) >= 2:
        return segments[:-1], segments[-1:]
    seg = segments[0]
    at = int(round((1 - holdout) * len(seg.run)))
    if at < 20 or len(seg.run) - at < 20:
        raise DataError(f"run of {len(seg.run)} samples is too short to hold out {holdout:.0%}")
    return [cut_segment(seg, 0, at)], [cut_segment(seg, at, len(seg.run))]


def pairs_of(segments: Sequence[Segment]) -> Pairs:
    """Consecutive state pairs of the segments (pairs never cross runs)."""
    return Pairs.from_states([(s.run.t, s.z, s.run.u, s.blur) for s in segments])
