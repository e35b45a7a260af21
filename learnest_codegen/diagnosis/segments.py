"""State observations of each run, and how runs are split into fitted and held-out data."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..data import Run
from ..errors import DataError
from ..systems import System
from .fit import Pairs
from .settings import DiagnosisSettings


@dataclass
class Segment:
    """A stretch of one run with its state observations ``z`` and observer variances ``var``."""

    run: Run
    z: np.ndarray
    var: np.ndarray | None
    reference: np.ndarray  # what estimators are scored against: truth, or z


def observations(system: System, runs: Sequence[Run],
                 settings: DiagnosisSettings) -> tuple[str, list[Segment]]:
    """The source used (``"truth"`` or ``"observer"``) and one :class:`Segment` per run."""
    source = settings.source
    if source == "auto":
        source = "truth" if all(r.x is not None for r in runs) else "observer"
    if source == "truth" and any(r.x is None for r in runs):
        raise DataError("source 'truth' needs x_ columns in every run")
    from ..observers import observe

    segments = []
    for run in runs:
        if source == "truth":
            segments.append(Segment(run, run.x, None, run.x))
        else:
            obs = observe(run, system, settings.observer)
            segments.append(Segment(run, obs.zeta, obs.variance, run.x if run.x is not None else obs.zeta))
    return source, segments


def cut_segment(seg: Segment, lo: int, hi: int) -> Segment:
    r = seg.run
    run = Run(r.t[lo:hi], r.u[lo:hi], r.y[lo:hi], None if r.x is None else r.x[lo:hi], r.system)
    return Segment(run, seg.z[lo:hi], None if seg.var is None else seg.var[lo:hi], seg.reference[lo:hi])


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
    return Pairs.from_states([(s.run.t, s.z, s.run.u) for s in segments])
