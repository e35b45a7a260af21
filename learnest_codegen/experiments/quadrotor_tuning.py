"""The study's estimator noise chosen on the training flights (``--tune-noise``).

A model that predicts better can be trusted more, but how much is a number the system's
hand tuning cannot know; it is chosen on the training flights against their reference, the
same way for the KNODE and the nominal estimators (see docs/reports/flights.md, "Tuned noise").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import SolverError
from .quadrotor_cases import Case, initial_state, scores

#: Factors on every process-noise std (trust in the model) and on every measurement-noise std
#: that the search tries; (1, 1) is the system's own tuning. A Kalman filter's or an MHE's
#: estimate moves with their ratio only, but the innovation gate with both: with the same
#: ratio, a larger measurement factor widens the gate.
PROCESS_SCALES = (1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0, 2.0)
MEASUREMENT_SCALES = (1.0, 2.0, 4.0)


@dataclass(frozen=True)
class Tuning:
    """The system's noise stds scaled: ``process_std * process_scale`` (below 1 the estimator
    trusts the model more) and ``measurement_std * measurement_scale``."""

    process_scale: float = 1.0
    measurement_scale: float = 1.0

    @property
    def label(self) -> str:
        return f"q{self.process_scale:g}_r{self.measurement_scale:g}"

    def settings(self, name: str, model) -> Any:
        """Estimator ``name``'s settings for the discrete ``model`` with these stds, through the
        estimators' own defaults (an MHE's arrival cost is recomputed for them)."""
        from ..compilation import estimator_kind

        noise = model.system.noise
        return estimator_kind(name).default_settings(
            model, process_std=tuple(self.process_scale * s for s in noise.process_std),
            measurement_std=tuple(self.measurement_scale * s for s in noise.measurement_std))


def tune(model, name: str, cases: Sequence[Case], out: Path, *, system,
         clamp_inputs: bool | None = None) -> tuple[Tuning, Any, dict[str, float]]:
    """The :class:`Tuning` of the grid whose estimator ``name`` of ``model`` has the lowest mean
    MSE over ``cases`` (the training flights), that estimator (compiled under
    ``out/<label>``), and every grid point's mean MSE by label."""
    from ..evaluation import run_estimator
    from ..pipeline import make_estimator, resolve

    discrete = resolve(model, system, clamp_inputs=clamp_inputs).model
    best, grid = None, {}
    for tuning in (Tuning(q, r) for q in PROCESS_SCALES for r in MEASUREMENT_SCALES):
        estimator = make_estimator(model, name, system=system, out=out / tuning.label,
                                   clamp_inputs=clamp_inputs, settings=tuning.settings(name, discrete))
        mse = float(np.mean([scores(run_estimator(estimator, c.run, initial_state(c.run), name).x_hat,
                                    c.reference)["mse"] for c in cases]))
        grid[tuning.label] = mse
        if np.isfinite(mse) and (best is None or mse < best[0]):
            best = (mse, tuning, estimator)
    if best is None:
        raise SolverError(f"tuning {name}: no grid point gave a finite MSE on the training flights")
    return best[1], best[2], grid
