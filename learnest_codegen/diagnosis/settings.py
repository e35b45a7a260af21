"""Settings of a diagnosis."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from ..errors import UnknownNameError
from .fit import FitSettings

SOURCES = ("auto", "truth", "observer")


@dataclass(frozen=True)
class DiagnosisSettings:
    """Settings of :func:`diagnose`.

    Attributes
    ----------
    source : ``"auto"`` (truth when every run has it), ``"truth"`` or ``"observer"``.
    observer : pre-training observer (default: the system's).
    holdout : share of a single run held out at its end for the shrink step (two runs or more
        are always pooled: fitted together, each held out in turn with the correction fitted on
        the others).
    estimator_runs : with two runs or more, the estimators run on this many held-out runs (the
        last ones), each with the correction fitted without it.
    explained_gap : "explained" needs the corrected prior's held-out residual within the floor:
        its mean square above the floor at most this (noise units^2; 0.25: RMS within 12 %).
    explained_estimator : ... and every estimator's corrected held-out MSE at most this fraction
        above the level the data support (see :mod:`~learnest_codegen.diagnosis.shrink`).
    worse_tolerance : an estimator whose held-out MSE rises by more than this fraction with the
        correction rejects it (and one that falls by more counts as improved).
    relative_floor : floor of a state's noise level, relative to the RMS of its prior derivative.
    calibrate : measure the noise floor on a simulated run of the exact prior.
    snr_gap : a residual state with ``snr`` above this carries a gap.
    estimators, backend : nominal estimators run in the shrink step (``()`` skips them).
    kinds : restrict the library to these effect kinds (default: all).
    fit : the selection settings.
    seed : seeds the calibration's synthetic measurement noise.
    """

    source: str = "auto"
    observer: str | None = None
    holdout: float = 0.3
    estimator_runs: int = 2
    explained_gap: float = 0.25
    explained_estimator: float = 0.2
    worse_tolerance: float = 0.01
    relative_floor: float = 1e-3
    calibrate: bool = True
    snr_gap: float = 1.5
    estimators: tuple[str, ...] = ("mhe", "ukf")
    backend: str = "c"
    kinds: tuple[str, ...] | None = None
    fit: FitSettings = field(default_factory=FitSettings)
    regime_bins: int = 5
    time_bins: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise UnknownNameError(f"unknown source {self.source!r}; choose from {list(SOURCES)}")
        if self.backend not in ("c", "python"):
            raise UnknownNameError(f"unknown backend {self.backend!r}; choose from ['c', 'python']")
        if not 0.05 <= self.holdout <= 0.8 or not self.relative_floor > 0 or self.regime_bins < 2 \
                or self.estimator_runs < 1 or not self.explained_gap > 0 or not self.worse_tolerance >= 0 \
                or not self.explained_estimator >= 0:
            raise ValueError(f"DiagnosisSettings: need 0.05 <= holdout <= 0.8, relative_floor > 0, "
                             f"regime_bins >= 2, estimator_runs >= 1, explained_gap > 0, "
                             f"worse_tolerance >= 0, explained_estimator >= 0; got {self}")
        object.__setattr__(self, "estimators", tuple(self.estimators))

    def to_json(self) -> dict:
        return asdict(self)
