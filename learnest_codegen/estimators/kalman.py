"""What the reference Kalman filters (the UKF, :mod:`.ukf`; the EKF, :mod:`.ekf`) share: their
settings (diagonal noise covariances from stds, the gate, the input limits) and the step around
FilterPy's predict and update (missing outputs, the gate, the lost-track re-seed, the
covariance guard and ceiling, :meth:`set_noise`, :meth:`run`), as the C kit's
``learnest_kalman.h`` shares them between its two filters.

A filter subclass holds a FilterPy filter as ``_kf`` (attributes ``x, P, Q, R``) and defines
its predict, its predicted outputs with their covariance, and its update on a subset of the
outputs; the sample convention is :meth:`KalmanFilter.run`'s: sample 0 is an update only, every
later sample a predict with the input held since the previous sample followed by an update.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from ..errors import DataError, SettingsError, ShapeError, SolverError
from ..export import DiscreteModel
from ..runtime.limits import check_option
from ..systems import System
from . import validation
from .gate import MAX_INFLATION, GateReport, GateSettings, GateState, cap_variances
from .inputs import InputCheck, check_limits, plausible_inputs

STD_FIELDS = ("process_std", "measurement_std", "initial_std")


@dataclass(frozen=True, kw_only=True)
class KalmanSettings:
    """Tuning of a Kalman filter: diagonal noise covariances, the gate and the input limits.

    Attributes
    ----------
    process_std : (nx,) stds of the assumed process noise, ``Q = diag(process_std**2)``.
    measurement_std : (ny,) stds of the measurement noise, ``R = diag(measurement_std**2)``.
    initial_std : (nx,) stds of the initial uncertainty, ``P0 = diag(initial_std**2)``.
        Every std is in ``[1e-100, 1e100]`` (``runtime/limits.py``).
    gate : the innovation gate and lost-track recovery (:mod:`.gate`); a dict is accepted.
    input_limits : ``((lo, hi), ...)`` per input, the plausible range of ``u``
        (:mod:`.inputs`; ``from_system`` takes :func:`~.inputs.plausible_inputs`); ``None``:
        only finiteness is checked.
    """

    process_std: tuple[float, ...]
    measurement_std: tuple[float, ...]
    initial_std: tuple[float, ...]
    gate: GateSettings = GateSettings()
    input_limits: tuple[tuple[float, float], ...] | None = None

    def __post_init__(self) -> None:
        name = type(self).__name__
        object.__setattr__(self, "gate", GateSettings.coerce(self.gate))
        if self.input_limits is not None:
            limits = check_limits(self.input_limits, len(tuple(self.input_limits)), name)
            object.__setattr__(self, "input_limits", limits)
        for field in STD_FIELDS:
            values = tuple(float(v) for v in np.atleast_1d(getattr(self, field)))
            if not values or not all(math.isfinite(v) and v > 0 for v in values):
                raise SettingsError(f"{name}.{field} must be a non-empty sequence of positive "
                                    f"finite stds, got {values}")
            object.__setattr__(self, field, tuple(check_option("std", v, f"{name}.{field}")
                                                  for v in values))

    @classmethod
    def from_system(cls, system: System, **overrides):
        """Settings with the noise stds of ``system.noise`` and the system's plausible inputs
        (:func:`~.inputs.plausible_inputs`), any field overridden by keyword."""
        unknown = set(overrides) - {f.name for f in fields(cls)}
        if unknown:
            raise TypeError(f"{cls.__name__} has no field(s) {sorted(unknown)}")
        noise = {name: getattr(system.noise, name) for name in STD_FIELDS}
        return cls(**{**noise, "input_limits": plausible_inputs(system), **overrides})

    def validate_for(self, model: DiscreteModel) -> None:
        """Raise :class:`ShapeError` unless the std lengths match ``model.nx`` and ``model.ny``."""
        for name, size, n in (("process_std", "nx", model.nx), ("measurement_std", "ny", model.ny),
                              ("initial_std", "nx", model.nx)):
            if len(getattr(self, name)) != n:
                raise ShapeError(f"{type(self).__name__}.{name}: the model has {size} = {n}, "
                                 f"got {len(getattr(self, name))} values")
        check_limits(self.input_limits, model.nu, type(self).__name__)

    def to_json(self) -> dict:
        data = {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}
        data["input_limits"] = None if self.input_limits is None else [list(p) for p in self.input_limits]
        if data["input_limits"] is None:
            del data["input_limits"]  # the manifests of builds without limits stay as they were
        return {**data, "gate": self.gate.to_json()}

    def Q(self) -> np.ndarray:
        """Process-noise covariance ``(nx, nx)``."""
        return np.diag(np.square(self.process_std))

    def R(self) -> np.ndarray:
        """Measurement-noise covariance ``(ny, ny)``."""
        return np.diag(np.square(self.measurement_std))

    def P0(self) -> np.ndarray:
        """Initial covariance ``(nx, nx)``."""
        return np.diag(np.square(self.initial_std))


class KalmanFilter(GateReport):
    """The step every reference Kalman filter shares (see the module docstring).

    Each update is gated (:mod:`.gate`): an output whose normalised innovation
    ``(y_j - zp_j)^2 / S_jj`` exceeds ``settings.gate.threshold`` is left out (FilterPy's update
    on the other outputs; none left: the prediction), and after ``recover_after`` consecutive
    steps with rejections each further one multiplies the variances (the diagonal of ``P``)
    by ``inflation``. A missing output (NaN) is left out the same way but is no rejection.
    No variance of ``P`` exceeds :attr:`ceiling`; a lost estimate re-seeds (:mod:`.gate`): the
    update from the prior covariance ``diag(ceiling)`` with every valid output.

    Attributes
    ----------
    rejected : (ny,) bool, the outputs the gate rejected in the last step.
    missing : (ny,) bool, the outputs the last step had no sample of.
    input_rejected : (nu,) bool, the input components the last step replaced (:mod:`.inputs`).
    last_status : status bits of the last step (0 OK, 1 output rejected, 2 input replaced).
    rejections, input_rejections : outputs / input components rejected since :meth:`reset`.
    """

    SETTINGS: type[KalmanSettings] = KalmanSettings
    #: The FilterPy filter's attributes a failed step restores.
    SAVED: tuple[str, ...] = ("x", "P")

    def __init__(self, model: DiscreteModel, settings: KalmanSettings | None = None):
        self.model = model
        self.settings = settings or self.SETTINGS.from_system(model.system)
        self.settings.validate_for(model)
        self._kf = self._make_filter()
        self._kf.Q, self._kf.R = self.settings.Q(), self.settings.R()
        self._gate = GateState(self.settings.gate, model.ny)
        self._inputs = InputCheck(self.settings.input_limits, model.nu)
        self._missing = np.zeros(model.ny, dtype=bool)
        self.rejections = 0
        self._first: bool | None = None  # None until reset(): no state to filter from

    # -- what a filter defines -------------------------------------------------------------
    def _make_filter(self):
        """The FilterPy filter (attributes ``x, P, Q, R``)."""
        raise NotImplementedError

    def _start(self) -> None:
        """Prepare sample 0's update (no predict before it)."""

    def _predict(self, u: np.ndarray) -> None:
        """FilterPy's predict with the input ``u``."""
        raise NotImplementedError

    def _innovation(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The predicted outputs ``zp (ny,)`` and their covariance ``S (ny, ny)``."""
        raise NotImplementedError

    def _reseeded(self) -> None:
        """Follow a re-seed of ``P`` (the UKF redraws its sigma points)."""

    def _update(self, u: np.ndarray, y: np.ndarray, keep: np.ndarray) -> None:
        """FilterPy's update on the outputs ``keep`` marks (none: no update)."""
        raise NotImplementedError

    # -- the shared step -------------------------------------------------------------------
    @property
    def name(self) -> str:
        return type(self).__name__

    def reset(self, x0, P0=None) -> None:
        """Start from mean ``x0 (nx,)`` and covariance ``P0 (nx, nx)`` (default settings.P0()).

        ``Q`` and ``R`` go back to the settings' (undoing :meth:`set_noise`).
        """
        nx = self.model.nx
        x0 = validation.vector(f"{self.name}.reset x0", x0, nx).copy()
        P0 = validation.covariance(f"{self.name}.reset P0", self.settings.P0() if P0 is None else P0, nx)
        self._kf.x, self._kf.P = x0, P0.copy()
        self._kf.Q, self._kf.R = self.settings.Q(), self.settings.R()
        self._gate = GateState(self.settings.gate, self.model.ny)  # as of this reset
        self._inputs = InputCheck(self.settings.input_limits, self.model.nu)
        self._missing = np.zeros(self.model.ny, dtype=bool)
        self.rejections = 0
        self._first = True

    def step(self, u, y, valid=None) -> np.ndarray:
        """Filter one sample and return the posterior mean ``x (nx,)``.

        Predicts with ``u (nu,)``, the input applied since the previous sample (no predict on
        the first call after :meth:`reset`), then updates with the outputs ``y (ny,)`` holds
        (NaN: missing; or those ``valid (ny,)`` marks): a missing output contributes nothing,
        none leaves the prediction, evaluating ``h`` at the same ``u``. Raises
        :class:`SolverError` (state unchanged) if the covariance stops being positive definite.
        A rejected output or input is not an error (see the class).
        """
        self._require_reset("step")
        u = validation.input_vector(f"{self.name}.step u", u, self.model.nu)
        y, mask = validation.measurements(f"{self.name}.step y", y, valid, self.model.ny)
        if y.shape != (self.model.ny,):
            raise ShapeError(f"{self.name}.step y: expected shape ({self.model.ny},), got {y.shape}")
        observed = np.ones(self.model.ny, dtype=bool) if mask is None else mask
        u, u_rejected = self._inputs.apply(u)
        saved = {k: getattr(self._kf, k).copy() for k in self.SAVED}
        try:
            # an overflow shows as a non-finite state, turned into the one error below
            with np.errstate(over="ignore", invalid="ignore"):
                if self._first:
                    self._start()
                else:
                    self._predict(u)
                rejected = self._gated_update(u, y, observed)
            failure = None
        except np.linalg.LinAlgError as exc:  # Cholesky or inverse of a non-positive-definite matrix
            failure = f"{exc}"
        except ValueError:  # scipy's Cholesky meets an overflowed (inf) sigma point
            failure = "non-finite values in the prediction"
        if failure is None and not (np.all(np.isfinite(self._kf.x)) and np.all(np.isfinite(self._kf.P))):
            failure = "non-finite state or covariance"
        if failure is None:
            try:  # the compiled filter's PSD guard (P - K S K^T can lose definiteness in rounding)
                validation.covariance("updated P", self._kf.P, self.model.nx, precision=None)
            except DataError as exc:
                failure = str(exc)
        if failure is not None:
            for k, v in saved.items():
                setattr(self._kf, k, v)
            raise SolverError(f"{self.name}.step: {failure} (state left as before this step)")
        # recovery: the variances grow, the covariances stay, up to the ceiling (estimators/gate.py)
        self._kf.P[np.diag_indices(self.model.nx)] *= self._gate.record(rejected, observed)
        self._kf.P = cap_variances(self._kf.P, self.ceiling)
        self._inputs.record(u, u_rejected)
        self._missing = ~observed
        self.rejections += int(rejected.sum())
        self._first = False
        return self.x

    def predict(self, u) -> np.ndarray:
        """A sample without any measurement: ``step(u, y)`` with every output missing."""
        return self.step(u, np.full(self.model.ny, np.nan))

    def set_noise(self, Q=None, R=None, P_arrival=None) -> None:
        """Change the process-noise covariance ``Q (nx, nx)`` and/or the measurement-noise
        covariance ``R (ny, ny)`` of the running filter; its state, covariance and gate are
        kept (the next :meth:`reset` returns to the settings' values; the C ``set_noise``).

        ``P_arrival`` is the MHEs' arrival covariance; a Kalman filter has none (its ``P`` is
        set by :meth:`reset`), so giving it raises :class:`TypeError`.
        """
        self._require_reset("set_noise")
        if P_arrival is not None:
            raise TypeError(f"{self.name}.set_noise: a Kalman filter has no arrival cost "
                            "(P_arrival); its covariance P is set by reset(x0, P0)")
        nx, ny = self.model.nx, self.model.ny
        Q = None if Q is None else validation.covariance(f"{self.name}.set_noise Q", Q, nx)
        R = None if R is None else validation.covariance(f"{self.name}.set_noise R", R, ny,
                                                         definite=True)
        if Q is not None:
            self._kf.Q = Q.copy()
        if R is not None:
            self._kf.R = R.copy()

    @property
    def ceiling(self) -> np.ndarray:
        """(nx,) the largest variance ``P`` may hold: :data:`~.gate.MAX_INFLATION` times the
        settings' initial variances (the C's ``learnest_kalman_ceiling``)."""
        return MAX_INFLATION * np.square(self.settings.initial_std)

    def _gated_update(self, u: np.ndarray, y: np.ndarray, observed: np.ndarray) -> np.ndarray:
        """The update on the ``observed`` outputs the gate keeps (or, re-seeding, on all of
        them from ``diag(ceiling)``); returns the rejected mask."""
        rejected = np.zeros(self.model.ny, dtype=bool)
        if observed.any():
            zp, S = self._innovation(u)
            with np.errstate(over="ignore", invalid="ignore"):  # an absurd y gives d2 = inf: rejected
                rejected = self._gate.test((y - zp) ** 2 / np.diag(S), observed)
        if self._gate.reseeds(rejected):  # lost: every valid output, from the widest prior
            rejected = np.zeros(self.model.ny, dtype=bool)
            self._kf.P = np.diag(self.ceiling)
            self._reseeded()
        self._update(u, y, observed & ~rejected)
        return rejected

    @property
    def x(self) -> np.ndarray:
        """Current state estimate ``(nx,)`` (a copy)."""
        self._require_reset("x")
        return self._kf.x.copy()

    @property
    def P(self) -> np.ndarray:
        """Current covariance ``(nx, nx)`` (a copy)."""
        self._require_reset("P")
        return self._kf.P.copy()

    @property
    def Q(self) -> np.ndarray:
        """The process-noise covariance in use ``(nx, nx)`` (a copy)."""
        return self._kf.Q.copy()

    @property
    def R(self) -> np.ndarray:
        """The measurement-noise covariance in use ``(ny, ny)`` (a copy)."""
        return self._kf.R.copy()

    def _require_reset(self, what: str) -> None:
        if self._first is None:
            raise RuntimeError(f"{self.name}.{what}: call reset(x0) first")

    def run(self, U, Y, x0, P0=None, valid=None) -> np.ndarray:
        """Filter a whole run from ``x0``.

        Parameters
        ----------
        U : (T, nu) inputs; ``U[k]`` is applied from sample k to sample k+1.
        Y : (T, ny) measurements; NaN marks a missing output.
        x0, P0 : initial mean ``(nx,)`` and covariance ``(nx, nx)``.
        valid : (T, ny) which outputs each sample holds (None: those that are not NaN).

        Returns
        -------
        X_hat : (T, nx) posterior means. Sample 0 is an update only (``h`` with ``U[0]``);
            sample k >= 1 is ``step(U[k-1], Y[k])``.
        """
        Y, mask = validation.measurements(f"{self.name}.run", Y, valid, self.model.ny)
        U, Y = validation.run_arrays(f"{self.name}.run", U, Y, self.model.nu, self.model.ny,
                                     missing=True)
        self.reset(x0, P0)
        X_hat = np.empty((len(Y), self.model.nx))
        for k in range(len(Y)):
            X_hat[k] = self.step(U[max(k - 1, 0)], Y[k], None if mask is None else mask[k])
        return X_hat
