"""The innovation gate every estimator applies to its measurements, and its recovery rule.

Gate. For output ``j`` of a sample, the normalised innovation is
``d_j^2 = (y_j - yhat_j)^2 / S_jj``, with ``yhat`` the output predicted before the sample and
``S_jj`` its predicted variance. For a consistent filter ``d_j^2`` is chi-square with one
degree of freedom, so ``d_j^2 > threshold`` rejects a valid sample with probability
``1 - chi2.cdf(threshold, 1)``: the default 50.8 rejects 1e-12 of clean outputs
(:data:`DEFAULT_THRESHOLD` says why not the textbook 15.1). A rejected
output is left out of that sample's update (the estimate keeps the prediction for it); the
step is not an error and reports ``LEARNEST_MEASUREMENT_REJECTED`` (status 1).

- UKF: ``yhat`` and ``S = P_zz + R`` are the unscented transform of the predicted sigma points
  (the ``S`` of the update itself).
- MHE (Ipopt and embedded): ``yhat = h(xpred, u)`` at the prediction ``xpred = F(xhat, u)`` of
  the previous estimate (the last stage of the warm start), and
  ``S = C P_arr C^T + R^-1`` with ``C = dh/dx`` at ``xpred`` and ``P_arr`` the inverse of the
  arrival weight in use. The default arrival weight is the inverse of the steady-state Kalman
  *prior* covariance (:func:`~.mhe_problem.steady_state_arrival`), so ``S`` is then the
  steady-state Kalman innovation covariance; with a weight ``inv(P0)`` given at reset it is the
  first sample's innovation covariance.

Recovery. A lost track (a real jump of the system, a wrong ``x0``, a sensor offset that
persists) would otherwise be rejected forever. From the ``recover_after``-th (K) consecutive
step with at least one rejected output on, every such step multiplies the estimator's
uncertainty by ``inflation`` (gamma): the UKF's variances (the diagonal of ``P``, after the
step; the covariances stay, so stale correlations fade), the MHEs' arrival covariance in the
gate (and a restart of the window once the measurements pass, see :mod:`.mhe`). The
inflation compounds, so a persistent offset of any size is accepted after about
``K + log_gamma(d^2 / threshold)`` steps, while a burst shorter than K only costs the
prediction. A step without rejection resets the streak and divides ``rho`` by gamma (down to
1; the UKF's ``P`` shrinks by its own updates). ``rho`` is
capped at :func:`max_inflation` (1e12; a float32 MHE 1e6) so a covariance cannot overflow.

``threshold = inf`` (or 0, which means the same) disables the gate and the recovery.

Missing outputs (NaN in ``y``, :mod:`.contract`) are not tested: a missing output is neither
accepted nor rejected. The streak is kept per output and counts that output's own samples, so
a missing sample neither lengthens nor ends it, and the accepted samples of a fast output do
not end the streak of a slow one that keeps being rejected (counted per step, a quarter-rate
output of the cartpole was rejected 589 times out of 1,250 and never recovered: the UKF's MSE
was 4.6 times the clean run's; ``docs/reports/reliability.md``). A step whose outputs are all missing
(a pure prediction) carries no evidence either way and leaves the streaks and ``rho`` as they
were.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..errors import SettingsError
from ..runtime.limits import check_option
from .inputs import INPUT_REJECTED, MEASUREMENT_REJECTED, InputCheck

#: chi2.isf(1e-12, df=1) (7.1 sigma). A consistent filter rejects 1e-12 of clean outputs; a
#: model with model error (the nominal prior) has innovations larger than its ``S``, and at
#: the textbook 15.14 (1e-4) the nominal cartpole UKF rejected 4 % of a clean test run's
#: outputs and its MSE moved by 11 %; at 50.8 it rejects none (docs/reports/reliability.md), while
#: garbage of 10 units on a 0.01-std output scores d^2 ~ 1e6.
DEFAULT_THRESHOLD = 50.844127911818155
#: Largest factor one recovery episode multiplies the uncertainty by, per precision (the
#: MHEs' arrival weight in float32: 1e6; see :func:`max_inflation`).
MAX_INFLATION = {"float64": 1e12, "float32": 1e6}


def max_inflation(estimator: str, precision: str) -> float:
    """The inflation cap of ``estimator`` in ``precision``: 1e12, but 1e6 for a float32 MHE,
    whose arrival weight (the inverse covariance) enters float32 normal equations. A float32
    UKF's variances times 1e12 stay far inside float32's range, and at 1e6 it never
    re-acquired a 45 rad jump of the cartpole's angle (docs/reports/reliability.md, float32 soak)."""
    return MAX_INFLATION["float64"] if estimator == "ukf" else MAX_INFLATION[precision]


@dataclass(frozen=True, kw_only=True)
class GateSettings:
    """Innovation gate and lost-track recovery (see the module docstring).

    Attributes
    ----------
    threshold : reject output ``j`` when ``d_j^2`` exceeds it (a chi-square(1) quantile;
        default 50.8, false rejections 1e-12, see :data:`DEFAULT_THRESHOLD`), 1 to 1e12.
        ``0`` or ``inf``: no gate, no recovery.
    recover_after : K, consecutive steps with rejections before the uncertainty is inflated,
        1 to 1e6.
    inflation : factor (1 < inflation <= 100) applied to the uncertainty at each further
        rejecting step.

    The ranges are :mod:`~learnest_codegen.runtime.limits`' (the C's ``set_gate`` checks the
    same); outside them :class:`~learnest_codegen.errors.SettingsError`.
    """

    threshold: float = DEFAULT_THRESHOLD
    recover_after: int = 10
    inflation: float = 2.0

    def __post_init__(self) -> None:
        t = check_option("gate_threshold", self.threshold, "GateSettings.threshold")
        object.__setattr__(self, "threshold", math.inf if t == 0 else t)
        object.__setattr__(self, "recover_after", check_option(
            "gate_recover_after", self.recover_after, "GateSettings.recover_after"))
        object.__setattr__(self, "inflation", check_option(
            "gate_inflation", self.inflation, "GateSettings.inflation"))

    @property
    def enabled(self) -> bool:
        return math.isfinite(self.threshold)

    @classmethod
    def from_false_rejection(cls, probability: float, **overrides) -> "GateSettings":
        """The gate whose threshold rejects ``probability`` of clean outputs (chi-square(1))."""
        from scipy.stats import chi2

        if not 0 < probability < 1:
            raise SettingsError(f"false-rejection probability must be in (0, 1), got {probability}")
        return cls(threshold=float(chi2.isf(probability, 1)), **overrides)

    def c_threshold(self) -> float:
        """The threshold as the C code takes it: 0 disables the gate."""
        return self.threshold if self.enabled else 0.0

    def to_json(self) -> dict:
        data = dataclasses.asdict(self)
        data["threshold"] = data["threshold"] if self.enabled else 0.0  # JSON has no inf
        return data

    @classmethod
    def coerce(cls, value) -> "GateSettings":
        """``value`` as GateSettings: itself, or a dict of its fields (from JSON)."""
        if isinstance(value, cls):
            return value
        if isinstance(value, dict):
            return cls(**value)
        raise TypeError(f"gate settings must be GateSettings or a dict, got {type(value).__name__}")


class GateState:
    """The gate's bookkeeping for one estimator run (the C kit's ``learnest_gate.h``, rule for
    rule; ``tests/test_ckit.py`` compares them).

    Attributes
    ----------
    rejected : (ny,) bool, the outputs rejected by the last step.
    streaks : (ny,) int, per output the consecutive samples *of that output* that were rejected
        (a missing sample neither lengthens nor breaks it).
    streak : the longest of them.
    inflation : rho, the factor in force (1 outside an episode; see the module docstring).
    """

    def __init__(self, settings: GateSettings, ny: int, precision: str = "float64"):
        self.settings, self.ny = settings, ny
        self.cap = MAX_INFLATION[precision]
        self.reset()

    def reset(self) -> None:
        self.rejected = np.zeros(self.ny, dtype=bool)
        self.streaks = np.zeros(self.ny, dtype=int)
        self.inflation = 1.0

    @property
    def streak(self) -> int:
        return int(self.streaks.max(initial=0))

    def test(self, d2: np.ndarray, observed: np.ndarray | None = None) -> np.ndarray:
        """The rejected mask of normalised innovations ``d2 (ny,)`` (not stored); an output
        that is not ``observed`` (missing) is never rejected."""
        observed = np.ones(self.ny, dtype=bool) if observed is None else np.asarray(observed, bool)
        if not self.settings.enabled:
            return np.zeros(self.ny, dtype=bool)
        with np.errstate(invalid="ignore"):
            return ~(np.asarray(d2) <= self.settings.threshold) & observed  # NaN d2 is rejected

    def ends_episode(self, rejected: np.ndarray, observed: np.ndarray) -> bool:
        """Whether this step ends a recovery episode: it rejects nothing and accepts a sample of
        an output whose streak had reached ``recover_after`` (the MHEs restart their window)."""
        in_episode = self.streaks >= self.settings.recover_after
        return bool(not np.any(rejected) and np.any(in_episode & np.asarray(observed, bool)))

    def record(self, rejected: np.ndarray, observed: np.ndarray | None = None) -> float:
        """Store the step's mask, update the streaks; return the factor to inflate by now (>= 1).

        Per observed output the streak grows by a rejection and ends with an acceptance. A step
        with a rejection of an output whose streak has reached ``recover_after`` multiplies
        ``rho`` by ``inflation`` (capped); a step that observes an output and rejects none
        divides it (down to 1); a step with no ``observed`` output (a pure prediction) changes
        nothing. With every output sampled every step this is the single-rate rule of the
        module docstring; with outputs at different rates a slow output's rejections still add
        up while a fast one is accepted in between.
        """
        self.rejected = np.asarray(rejected, dtype=bool).copy()
        observed = np.ones(self.ny, dtype=bool) if observed is None else np.asarray(observed, bool)
        if not observed.any():
            return 1.0
        self.streaks = np.where(observed, np.where(self.rejected, self.streaks + 1, 0), self.streaks)
        if not self.rejected.any():
            self.inflation = max(1.0, self.inflation / self.settings.inflation)
            return 1.0
        due = self.streaks[self.rejected].max() >= self.settings.recover_after
        if not due or self.inflation * self.settings.inflation > self.cap:
            return 1.0
        self.inflation *= self.settings.inflation
        return self.settings.inflation

    @property
    def status(self) -> int:
        """1 (MEASUREMENT_REJECTED) when the last step rejected an output, else 0 (OK)."""
        return int(self.rejected.any())


class GateReport:
    """What a Python estimator holding a :class:`GateState` as ``_gate`` and an
    :class:`~.inputs.InputCheck` as ``_inputs`` reports of them."""

    _gate: GateState
    _inputs: InputCheck
    _missing: np.ndarray

    @property
    def rejected(self) -> np.ndarray:
        """(ny,) bool, the outputs the gate left out of the last step."""
        return self._gate.rejected.copy()

    @property
    def missing(self) -> np.ndarray:
        """(ny,) bool, the outputs the last step had no sample of (NaN in ``y``)."""
        return self._missing.copy()

    @property
    def input_rejected(self) -> np.ndarray:
        """(nu,) bool, the input components the last step replaced by their held value."""
        return self._inputs.rejected.copy()

    @property
    def input_rejections(self) -> int:
        """Input components replaced since the last reset."""
        return self._inputs.rejections

    @property
    def last_status(self) -> int:
        """The last step's status bits: 0 OK, +1 an output was rejected, +2 an input
        component was replaced (:mod:`.inputs`); none of them is an error."""
        return (MEASUREMENT_REJECTED * self._gate.status
                | INPUT_REJECTED * int(self._inputs.rejected.any()))
