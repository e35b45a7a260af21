"""ctypes binding of a compiled UKF folder (see ``codegen/ukf.py``), with :class:`UKF`'s interface.

Imports neither torch nor filterpy: a deployed estimator needs numpy and the library only.
The API it wraps is the C kit's (``runtime/base.py``); this module adds the UKF's settings and
its covariance.
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from ..estimators import validation
from ..estimators.ukf import UKFSettings
from .base import HANDLE, INT, CompiledEstimator, _locked
from .manifest import check_manifest


class _Sizes:
    """The sizes in a manifest, as the attributes ``nx, nu, ny`` that a DiscreteModel has."""

    def __init__(self, manifest: Mapping[str, Any]):
        self.nx, self.nu, self.ny = (int(manifest[k]) for k in ("nx", "nu", "ny"))


class CompiledUKF(CompiledEstimator):
    """A compiled UKF with the interface of :class:`learnest_codegen.estimators.ukf.UKF`.

    Parameters
    ----------
    directory : folder written by :func:`learnest_codegen.codegen.ukf.generate_ukf`.
    expect : manifest entries the caller requires, e.g. ``{"system": "cartpole", "nx": 4}``;
        any difference raises :class:`ModelMismatchError`.
    settings : :class:`UKFSettings` whose Q, R, P0 and gate to use (default: those compiled
        with the library). Its alpha, beta and kappa must equal the compiled ones (they are
        constants in the C).

    Attributes
    ----------
    rejected, last_status, rejections : as :class:`~learnest_codegen.estimators.ukf.UKF`.
    """

    ESTIMATORS = ("ukf",)
    DEFINITE = False  # P0 and Q may be semidefinite (an exactly known direction)

    def __init__(self, directory, *, expect: Mapping[str, Any] | None = None,
                 settings: UKFSettings | None = None):
        super().__init__(directory, expect, settings)
        self.sizes = _Sizes(self.manifest)

    def extra_signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        return {"get_covariance": (INT, [HANDLE, self.real_pointer])}

    def _settings(self, settings: UKFSettings | None) -> UKFSettings:
        compiled = UKFSettings(**self.manifest["settings"])
        if settings is None:
            return compiled
        check_manifest({k: getattr(compiled, k) for k in ("alpha", "beta", "kappa")},
                       {k: getattr(settings, k) for k in ("alpha", "beta", "kappa")},
                       f"{self.where} settings (sigma-point constants are compiled in)")
        settings.validate_for(_Sizes(self.manifest))
        return settings

    def _covariances(self, P0):
        P0 = self.settings.P0() if P0 is None else P0
        P0 = validation.covariance("CompiledUKF.reset P0", P0, self.nx, precision=self.precision)
        return P0, self.settings.Q(), self.settings.R()

    @property
    @_locked
    def P(self) -> np.ndarray:
        """Current covariance ``(nx, nx)``."""
        P = np.empty((self.nx, self.nx), dtype=self.dtype)
        self.check_status("P", self._c["get_covariance"](self._started("P"), P))
        return P.astype(float)
