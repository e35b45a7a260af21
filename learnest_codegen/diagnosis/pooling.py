"""Several runs at once: leave-one-run-out held-out corrections and consistency across runs.

A folder of short real recordings is fitted as one pool (cross-validation folds by run, see
:func:`~learnest_codegen.diagnosis.fit.fold_labels`). Two questions remain that a pooled fit
does not answer by itself:

* **Does the correction carry over to a run it has not seen?** Each run is held out in turn and
  the selected effects are refitted on the others (:func:`leave_one_out`); the shrink step scores
  every run with the correction that did not see it.
* **Is each effect the same on every run?** Each run is fitted on its own
  (:func:`consistency`): per parameter its value on every run, the median, the robust spread
  (1.4826 MAD) and the share of runs agreeing in sign with the pooled value. An effect is
  *consistent* when every run agrees in sign and the spread is below half the median's size;
  an inconsistent one (a steering map that differs between recordings) is flagged in the report.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..systems import System
from .effects import Effect
from .fit import FitSettings
from .segments import Segment, pairs_of
from .selection import refit
from .shrink import HeldOut


def leave_one_out(system: System, chosen: Sequence[Effect], theta: np.ndarray, segments: Sequence[Segment],
                  rows, sigma, settings: FitSettings, iterations: int = 8) -> tuple[list[HeldOut], list[str]]:
    """Every segment with the chosen effects refitted (from the pooled ``theta``) on the others.

    Returns the held-out segments and the refinement status of each fold.
    """
    held, status = [], []
    for k, seg in enumerate(segments):
        if not chosen:
            held.append(HeldOut(seg, np.zeros(0)))
            status.append("nothing to fit")
            continue
        others = pairs_of([s for i, s in enumerate(segments) if i != k])
        res = refit(system, chosen, theta, others, rows, sigma, settings, iterations)
        held.append(HeldOut(seg, res.theta))
        status.append(res.status)
    return held, status


def consistency(system: System, chosen: Sequence[Effect], theta: np.ndarray, segments: Sequence[Segment],
                rows, sigma, settings: FitSettings, iterations: int = 8) -> list[dict]:
    """Per parameter of the chosen effects: its value fitted on each run alone, and a summary."""
    if not chosen or len(segments) < 2:
        return []
    values = np.full((len(segments), len(chosen)), np.nan)
    for k, seg in enumerate(segments):
        res = refit(system, chosen, theta, pairs_of([seg]), rows, sigma, settings, iterations)
        if res.ok:
            values[k] = res.theta
    out = []
    for i, e in enumerate(chosen):
        v = values[:, i]
        ok = v[np.isfinite(v)]
        median = float(np.median(ok)) if len(ok) else float("nan")
        spread = float(1.4826 * np.median(np.abs(ok - median))) if len(ok) else float("nan")
        agree = float(np.mean(np.sign(ok) == np.sign(theta[i]))) if len(ok) else 0.0
        out.append({"effect": e.name, "param": e.param, "pooled": float(theta[i]),
                    "per_run": [None if not np.isfinite(x) else float(x) for x in v],
                    "median": median, "spread": spread, "sign_agreement": agree,
                    "consistent": bool(len(ok) == len(v) and agree == 1.0 and spread < 0.5 * abs(median))})
    return out
