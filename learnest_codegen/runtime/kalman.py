"""ctypes binding of a compiled Kalman filter folder (the UKF, ``codegen/ukf.py``; the EKF,
``codegen/ekf.py``): what the two share, as their C shares ``learnest_kalman.h``.

Imports neither torch nor filterpy: a deployed estimator needs numpy and the library only.
The API it wraps is the C kit's (``runtime/base.py``); this module adds the settings and the
covariance.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from ..estimators import validation
from ..estimators.kalman import KalmanSettings
from .base import HANDLE, INT, CompiledEstimator, _locked


class Sizes:
    """The sizes in a manifest, as the attributes ``nx, nu, ny`` that a DiscreteModel has."""

    def __init__(self, manifest: Mapping[str, Any]):
        self.nx, self.nu, self.ny = (int(manifest[k]) for k in ("nx", "nu", "ny"))


class CompiledKalman(CompiledEstimator):
    """A compiled Kalman filter with the interface of its reference
    (:class:`~learnest_codegen.estimators.kalman.KalmanFilter`).

    Parameters
    ----------
    directory : the folder its generator wrote.
    expect : manifest entries the caller requires, e.g. ``{"system": "cartpole", "nx": 4}``;
        any difference raises :class:`ModelMismatchError`.
    settings : settings (of :attr:`SETTINGS`) whose Q, R, P0 and gate to use (default: those
        compiled with the library).
    """

    SETTINGS: type[KalmanSettings] = KalmanSettings
    DEFINITE = False  # P0 and Q may be semidefinite (an exactly known direction)

    def __init__(self, directory, *, expect: Mapping[str, Any] | None = None,
                 settings: KalmanSettings | None = None):
        super().__init__(directory, expect, settings)
        self.sizes = Sizes(self.manifest)

    def extra_signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        return {"get_covariance": (INT, [HANDLE, self.real_pointer])}

    def _settings(self, settings: KalmanSettings | None) -> KalmanSettings:
        compiled = self.SETTINGS(**self.manifest["settings"])
        if settings is None:
            return compiled
        self._check_constants(compiled, settings)
        settings.validate_for(Sizes(self.manifest))
        return settings

    def _check_constants(self, compiled: KalmanSettings, settings: KalmanSettings) -> None:
        """Raise when ``settings`` differ from the ``compiled`` ones in a constant of the C."""

    def _covariances(self, P0):
        P0 = self.settings.P0() if P0 is None else P0
        P0 = validation.covariance(f"{type(self).__name__}.reset P0", P0, self.nx,
                                   precision=self.precision)
        return P0, self.settings.Q(), self.settings.R()

    @property
    @_locked
    def P(self) -> np.ndarray:
        """Current covariance ``(nx, nx)``."""
        return self.read("P", "get_covariance", (self.nx, self.nx)).astype(float)
