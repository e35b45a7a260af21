"""The reference Unscented Kalman Filter: FilterPy's UKF over a :class:`DiscreteModel`.

The generated C filter (``codegen/ukf.py``) reproduces this filter's arithmetic; the parity
tests compare the two. The step around FilterPy's predict and update (missing outputs, the gate,
the re-seed, the guards, :meth:`~.kalman.KalmanFilter.run`'s sample convention) is the one every
reference Kalman filter shares (:mod:`.kalman`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import SettingsError
from ..export import DiscreteModel
from ..runtime.limits import check_option
from .kalman import KalmanFilter, KalmanSettings

#: The smallest sigma-point spread a float32 UKF accepts (docs/reports/embedded_mhe.md, float32
#: table): with a smaller one the sigma-point weights cancel in single precision.
FLOAT32_MIN_ALPHA = 0.5


@dataclass(frozen=True, kw_only=True)
class UKFSettings(KalmanSettings):
    """Tuning of the UKF: Merwe scaled sigma points and :class:`~.kalman.KalmanSettings`.

    Attributes
    ----------
    alpha, beta, kappa : sigma-point spread (0 < alpha <= 1), prior-distribution and
        secondary scaling parameters of :class:`filterpy.kalman.MerweScaledSigmaPoints`.
    process_std, measurement_std, initial_std, gate, input_limits : as
        :class:`~.kalman.KalmanSettings`.
    """

    alpha: float = 0.1
    beta: float = 2.0
    kappa: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        for name in ("alpha", "beta", "kappa"):
            value = float(getattr(self, name))
            if not math.isfinite(value):
                raise SettingsError(f"UKFSettings.{name} must be finite, got {value}")
            object.__setattr__(self, name, value)
        check_option("ukf_alpha", self.alpha, "UKFSettings.alpha")

    def validate_for(self, model: DiscreteModel) -> None:
        """:meth:`KalmanSettings.validate_for`, and ``kappa > -nx``."""
        super().validate_for(model)
        # The sigma points scale P by alpha**2 (n + kappa); it must stay positive.
        if not self.alpha**2 * (model.nx + self.kappa) > 0:
            raise SettingsError(f"UKFSettings: need kappa > -nx = {-model.nx}, got {self.kappa}")


class UKF(KalmanFilter):
    """Reference UKF (FilterPy) with ``fx = model.step`` and ``hx = model.measure``, in the
    step of :class:`~.kalman.KalmanFilter` (gate, missing outputs, re-seed, ceiling).

    Parameters
    ----------
    model : the discrete model ``x+ = F(x, u)``, ``y = h(x, u)``.
    settings : tuning; default ``UKFSettings.from_system(model.system)``.
    """

    SETTINGS = UKFSettings
    SAVED = ("x", "P", "sigmas_f")

    def _make_filter(self):
        # filterpy is imported here, not at the top, so that the settings and array checks of
        # this module stay importable by the filterpy- and torch-free runtime.
        from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

        s, model = self.settings, self.model
        self._points = MerweScaledSigmaPoints(model.nx, s.alpha, s.beta, s.kappa)
        return UnscentedKalmanFilter(model.nx, model.ny, model.dt, hx=self._hx, fx=self._fx,
                                     points=self._points)

    def _fx(self, x: np.ndarray, dt: float, u: np.ndarray) -> np.ndarray:
        return self.model.step(x, u)  # dt is fixed inside the discrete model

    def _hx(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return self.model.measure(x, u)

    def _start(self) -> None:
        # FilterPy's update() transforms the sigma points that predict() leaves behind; sample
        # 0 has no predict, so draw them from (x0, P0) as predict would.
        self._reseeded()

    def _predict(self, u: np.ndarray) -> None:
        self._kf.predict(u=u)

    def _innovation(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from filterpy.kalman import unscented_transform

        kf = self._kf
        sigmas_h = np.atleast_2d([self._hx(s, u) for s in kf.sigmas_f])
        return unscented_transform(sigmas_h, kf.Wm, kf.Wc, kf.R)

    def _reseeded(self) -> None:
        self._kf.sigmas_f = self._points.sigma_points(self._kf.x, self._kf.P)

    def _update(self, u: np.ndarray, y: np.ndarray, keep: np.ndarray) -> None:
        kf = self._kf
        if keep.all():
            kf.update(y, u=u)
        elif not keep.any():
            kf.update(None)  # the prediction stands
        else:
            kf.update(y[keep], R=kf.R[np.ix_(keep, keep)],
                      hx=lambda x, u: self._hx(x, u)[keep], u=u)
