"""ctypes binding of a compiled EKF folder (see ``codegen/ekf.py``), with :class:`EKF`'s interface:
the Kalman filters' binding (``runtime/kalman.py``) with the EKF's settings.
"""

from __future__ import annotations

from ..estimators.ekf import EKFSettings
from .kalman import CompiledKalman


class CompiledEKF(CompiledKalman):
    """A compiled EKF with the interface of :class:`learnest_codegen.estimators.ekf.EKF`; see
    :class:`~.kalman.CompiledKalman`."""

    ESTIMATORS = ("ekf",)
    SETTINGS = EKFSettings
