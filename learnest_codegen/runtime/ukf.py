"""ctypes binding of a compiled UKF folder (see ``codegen/ukf.py``), with :class:`UKF`'s interface:
the Kalman filters' binding (``runtime/kalman.py``) with the UKF's settings.
"""

from __future__ import annotations

from ..estimators.ukf import UKFSettings
from .kalman import CompiledKalman
from .manifest import check_manifest

SIGMA_CONSTANTS = ("alpha", "beta", "kappa")


class CompiledUKF(CompiledKalman):
    """A compiled UKF with the interface of :class:`learnest_codegen.estimators.ukf.UKF`.

    ``settings`` (:class:`UKFSettings`) must have the compiled alpha, beta and kappa (they are
    constants in the C); see :class:`~.kalman.CompiledKalman` for the rest.
    """

    ESTIMATORS = ("ukf",)
    SETTINGS = UKFSettings

    def _check_constants(self, compiled, settings) -> None:
        check_manifest({k: getattr(compiled, k) for k in SIGMA_CONSTANTS},
                       {k: getattr(settings, k) for k in SIGMA_CONSTANTS},
                       f"{self.where} settings (sigma-point constants are compiled in)")
