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
inflation compounds up to :data:`MAX_INFLATION` (1e4), so an offset up to about 100 prior
standard deviations is accepted after about ``K + log_gamma(d^2 / threshold)`` steps, while a
burst shorter than K only costs the prediction. A step without rejection resets the streak
and divides ``rho`` by gamma (down to 1; the UKF's ``P`` shrinks by its own updates).

Ceiling. No covariance an estimator carries grows beyond :data:`MAX_INFLATION` times its
reference: the UKF's ``P`` beyond the settings' initial variances (a long run of predictions
grew the cartpole UKF's ``P`` from 16 to 1e44 within 1,000 steps and its state to 6e12), an
MHE's restart prior or carried arrival covariance beyond the running arrival covariance (a
larger one made the float32 Gauss-Newton normal equations fail at every step after a
restart). :func:`cap_variances` scales the rows and columns, so the correlations stay.

Lost track and re-seed. ``age`` counts the steps since one last accepted an output (a step
whose outputs are all missing or all rejected lengthens it); ``lost_after`` is
``recover_after`` plus the widenings ``rho`` needs to reach the cap (23 by default). An estimate
is *lost* when an output's streak has reached ``lost_after`` (a track the widest gate cannot
re-acquire) or ``age`` has (a run of that many predictions): each step then reports
:data:`UNRELIABLE` (status bit 4), and the next step whose gate rejects a valid output re-seeds
instead (:meth:`GateState.reseeds`): it takes every valid output, from the prediction with the
ceiling as its covariance (the UKF's update; the MHEs' window restart, :mod:`.mhe`), which ends
the streaks and the age. A sensor that stays off by more than the widest gate is thus taken
after ``lost_after`` samples, as the inflation would take any persistent offset. A 45 rad jump
of the cartpole's angle needs ``rho`` ~ 1.6e7 to pass the gate, and a cap that large leaves the
float32 normal equations of a restarted MHE unsolvable; the re-seed re-acquires it after
``lost_after`` steps in both precisions (``docs/reports/reliability.md``).

``threshold = inf`` (or 0, which means the same) disables the gate and the recovery.

Missing outputs (NaN in ``y``, :mod:`.contract`) are not tested: a missing output is neither
accepted nor rejected. The streak is kept per output and counts that output's own samples, so
a missing sample neither lengthens nor ends it, and the accepted samples of a fast output do
not end the streak of a slow one that keeps being rejected (counted per step, a quarter-rate
output of the cartpole was rejected 589 times out of 1,250 and never recovered: the UKF's MSE
was 4.6 times the clean run's). A step whose outputs are all missing (a pure prediction)
leaves the streaks and ``rho`` as they were and lengthens ``age``.
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
#: The widest the recovery opens the gate (``rho``'s cap), and the ceiling of every covariance an
#: estimator carries relative to its reference (see the module docstring), in every estimator and
#: precision: at 1e5 the float32 Gauss-Newton MHE failed every step after a restart.
MAX_INFLATION = 1e4
#: Status bit: no output has been accepted for ``lost_after`` steps (see the module docstring).
UNRELIABLE = 4


def max_inflation(estimator: str, precision: str) -> float:
    """The inflation cap and covariance ceiling factor of ``estimator`` in ``precision``:
    :data:`MAX_INFLATION` for every one (the C's ``LEARNEST_MAX_INFLATION``)."""
    return MAX_INFLATION


def cap_variances(P: np.ndarray, ceiling: np.ndarray) -> np.ndarray:
    """``P (n, n)`` with row and column ``i`` scaled by ``sqrt(ceiling_i / P_ii)`` where
    ``P_ii`` exceeds ``ceiling_i`` (the C kit's ``learnest_cap_variances``): variances at most
    the ceiling, correlations kept."""
    P = np.array(P, dtype=float)
    d = np.diag(P).copy()
    over = d > ceiling
    if not over.any():
        return P
    s = np.where(over, np.sqrt(np.divide(ceiling, d, where=over, out=np.ones_like(d))), 1.0)
    return P * s[:, None] * s[None, :]


def lost_after(settings: "GateSettings", cap: float = MAX_INFLATION) -> int:
    """``recover_after`` plus the number of widenings by ``inflation`` that keep ``rho`` within
    ``cap``: the steps without an accepted output after which an estimate is lost."""
    r, n = 1.0, 0
    while r * settings.inflation <= cap and n < 1000:
        r *= settings.inflation
        n += 1
    return settings.recover_after + n


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
    age : steps since one accepted an output.
    lost : whether an output's streak or ``age`` has reached ``lost_after`` (the estimate is
        unreliable; see the module docstring).
    """

    def __init__(self, settings: GateSettings, ny: int, precision: str = "float64"):
        self.settings, self.ny = settings, ny
        self.cap = MAX_INFLATION
        self.lost_after = lost_after(settings, self.cap)
        self.reset()

    def reset(self) -> None:
        self.rejected = np.zeros(self.ny, dtype=bool)
        self.streaks = np.zeros(self.ny, dtype=int)
        self.inflation = 1.0
        self.age = 0

    @property
    def streak(self) -> int:
        return int(self.streaks.max(initial=0))

    @property
    def lost(self) -> bool:
        return self.age >= self.lost_after or self.streak >= self.lost_after

    def test(self, d2: np.ndarray, observed: np.ndarray | None = None) -> np.ndarray:
        """The rejected mask of normalised innovations ``d2 (ny,)`` (not stored); an output
        that is not ``observed`` (missing) is never rejected."""
        observed = np.ones(self.ny, dtype=bool) if observed is None else np.asarray(observed, bool)
        if not self.settings.enabled:
            return np.zeros(self.ny, dtype=bool)
        with np.errstate(invalid="ignore"):
            return ~(np.asarray(d2) <= self.settings.threshold) & observed  # NaN d2 is rejected

    def reseeds(self, rejected: np.ndarray) -> bool:
        """Whether a step whose gate rejected ``rejected`` re-seeds instead: the estimate is
        lost and an output was rejected (the caller then takes every valid output)."""
        return bool(np.any(rejected)) and self.lost

    def ends_episode(self, rejected: np.ndarray, observed: np.ndarray) -> bool:
        """Whether this step ends a recovery episode: it rejects nothing and accepts a sample of
        an output whose streak had reached ``recover_after`` (the MHEs restart their window)."""
        in_episode = self.streaks >= self.settings.recover_after
        return bool(not np.any(rejected) and np.any(in_episode & np.asarray(observed, bool)))

    def record(self, rejected: np.ndarray, observed: np.ndarray | None = None) -> float:
        """Store the step's mask, update the streaks and the age; return the factor to inflate
        by now (>= 1).

        Per observed output the streak grows by a rejection and ends with an acceptance. A step
        with a rejection of an output whose streak has reached ``recover_after`` multiplies
        ``rho`` by ``inflation`` (capped); a step that observes an output and rejects none
        divides it (down to 1); a step with no ``observed`` output (a pure prediction) changes
        neither. ``age`` restarts at 0 on a step that accepts an output and grows otherwise.
        With every output sampled every step this is the single-rate rule of the module
        docstring; with outputs at different rates a slow output's rejections still add up
        while a fast one is accepted in between.
        """
        self.rejected = np.asarray(rejected, dtype=bool).copy()
        observed = np.ones(self.ny, dtype=bool) if observed is None else np.asarray(observed, bool)
        self.age = 0 if np.any(observed & ~self.rejected) else self.age + 1
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
        component was replaced (:mod:`.inputs`), +4 the estimate is unreliable (lost, see the
        module docstring); none of them is an error."""
        return (MEASUREMENT_REJECTED * self._gate.status
                | INPUT_REJECTED * int(self._inputs.rejected.any())
                | UNRELIABLE * int(self._gate.lost))
