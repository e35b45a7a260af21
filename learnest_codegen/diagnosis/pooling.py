"""Several runs at once: leave-one-run-out held-out corrections and consistency across runs.

A folder of short real recordings is fitted as one pool (cross-validation folds by run, see
:func:`~learnest_codegen.diagnosis.fit.fold_labels`). Two questions remain that a pooled fit
does not answer by itself:

* **Does the correction carry over to a run it has not seen?** Each run is held out in turn and
  the selected effects are refitted on the others (:func:`leave_one_out`); the shrink step scores
  every run with the correction that did not see it.
* **Is each effect the same on every run?** Each run is fitted on its own
  (:func:`consistency`): per parameter its value on every run with its standard error, the
  median, the robust spread (1.4826 MAD) and the share of runs agreeing in sign with the pooled
  value. An effect is *consistent* when the runs' intervals share a value of the pooled sign
  (:func:`~learnest_codegen.diagnosis.search.consistent`: a run that hardly excites it has a wide
  interval); an inconsistent one (a steering map that differs between recordings) is flagged in
  the report.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..systems import System
from .cv import weighted
from .effects import Effect
from .fit import FitSettings, one_step
from .refine import bounds
from .search import consistent, per_run_values
from .segments import Segment, pairs_of
from .selection import refit
from .shrink import HeldOut


def leave_one_out(system: System, chosen: Sequence[Effect], theta: np.ndarray, segments: Sequence[Segment],
                  rows, sigma, settings: FitSettings, iterations: int = 8) -> tuple[list[HeldOut], list[str]]:
    """Every segment with the chosen effects refitted (from the pooled ``theta``) on the others, by
    ordinary least squares: whitened by an autoregression of a residual far above the noise floor
    (unmodelled dynamics, as on the DART recordings), the refit predicts the held-out run worse.

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
    se = np.full((len(segments), len(chosen)), np.nan)
    lo, hi = bounds(system, chosen, settings.bound)
    for k, seg in enumerate(segments):
        pairs = pairs_of([seg])
        res = refit(system, chosen, theta, pairs, rows, sigma, settings, iterations)
        if not res.ok:
            continue
        r, J = one_step(system, chosen, res.theta, pairs)
        data = weighted(r, J, rows, sigma, lo=lo - res.theta, hi=hi - res.theta,
                        runs=np.zeros(len(pairs), dtype=int))
        values[k], se[k] = (a[0] for a in per_run_values(data, list(range(len(chosen))), res.theta))
    out = []
    for i, e in enumerate(chosen):
        v, ok = values[:, i], np.isfinite(values[:, i])
        check = consistent(v[ok], float(theta[i]), se[ok, i]) if ok.any() else {"consistent": False}
        out.append({"effect": e.name, "param": e.param, "pooled": float(theta[i]),
                    **{k: check.get(k) for k in ("median", "spread", "sign_agreement", "common")},
                    "per_run": [None if not np.isfinite(x) else float(x) for x in v],
                    "se": [None if not np.isfinite(x) else float(x) for x in se[:, i]],
                    "consistent": bool(ok.all() and check["consistent"])})
    return out
