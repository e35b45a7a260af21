"""What every pre-training observer returns, and the intensity grid they search."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

JERK_GRID = np.logspace(-2, 8, 21)  # white-jerk spectral densities tried [unit^2 / s^5]


@dataclass(frozen=True)
class Observations:
    """State observations for training.

    Attributes
    ----------
    zeta : (T, nx) state observations.
    variance : (T, nx) their marginal variances, as the observer believes them.
    method : which observer produced them.
    info : per-observer details (e.g. the chosen jerk intensities).
    """

    zeta: np.ndarray
    variance: np.ndarray
    method: str
    info: dict
