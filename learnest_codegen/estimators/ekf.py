"""The reference extended Kalman filter: FilterPy's ``ExtendedKalmanFilter`` over a
:class:`DiscreteModel`, with the Jacobians ``A = dF/dx`` and ``C = dh/dx`` from CasADi's AD.

The generated C filter (``codegen/ekf.py``, the C kit's ``learnest_ekf.h``) runs the same
predict (``x = F(x, u)``, ``P = A P A^T + Q`` with ``A`` at the previous estimate) and update
(``K = P C^T S^-1`` with ``S = C P C^T + R`` at the prediction); FilterPy writes the covariance
update in Joseph form and the kit as ``P - K C P``, equal to rounding. The step around them
(missing outputs, the gate, the re-seed, the guards) is :mod:`.kalman`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import casadi as cs
import numpy as np

from ..export import DiscreteModel
from .kalman import KalmanFilter, KalmanSettings


@dataclass(frozen=True, kw_only=True)
class EKFSettings(KalmanSettings):
    """Tuning of the EKF: :class:`~.kalman.KalmanSettings` (noise stds, gate, input limits);
    the EKF has no constants of its own."""


def jacobians(model: DiscreteModel) -> tuple[cs.Function, cs.Function]:
    """``(A(x, u) = dF/dx, C(x, u) = dh/dx)`` as CasADi functions, dense."""
    x, u = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    return (cs.Function("A", [x, u], [cs.densify(cs.jacobian(model.F(x, u), x))]),
            cs.Function("C", [x, u], [cs.densify(cs.jacobian(model.h(x, u), x))]))


class EKF(KalmanFilter):
    """Reference EKF (FilterPy) with ``x+ = model.step(x, u)`` and ``y = model.measure(x, u)``,
    in the step of :class:`~.kalman.KalmanFilter` (gate, missing outputs, re-seed, ceiling).

    Parameters
    ----------
    model : the discrete model ``x+ = F(x, u)``, ``y = h(x, u)``.
    settings : tuning; default ``EKFSettings.from_system(model.system)``.
    """

    SETTINGS = EKFSettings

    def _make_filter(self):
        # filterpy is imported here, not at the top, so that the settings of this module stay
        # importable by the filterpy-free runtime.
        from filterpy.kalman import ExtendedKalmanFilter

        self._A, self._C = jacobians(self.model)
        kf = ExtendedKalmanFilter(self.model.nx, self.model.ny)
        kf.predict_x = self._predict_x  # FilterPy's predict: predict_x(u), then P = F P F' + Q
        return kf

    def _predict_x(self, u: np.ndarray) -> None:
        self._kf.x = self.model.step(self._kf.x, u)

    def _jacobian_h(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        return np.asarray(self._C(x, u))

    def _predict(self, u: np.ndarray) -> None:
        self._kf.F = np.asarray(self._A(self._kf.x, u))  # at the previous estimate
        self._kf.predict(u=u)

    def _innovation(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kf = self._kf
        C = self._jacobian_h(kf.x, u)
        return self.model.measure(kf.x, u), C @ kf.P @ C.T + kf.R

    def _update(self, u: np.ndarray, y: np.ndarray, keep: np.ndarray) -> None:
        kf = self._kf
        if not keep.any():
            kf.update(None, None, None)  # the prediction stands
            return
        kf.update(y[keep], lambda x, u: self._jacobian_h(x, u)[keep],
                  lambda x, u: self.model.measure(x, u)[keep], R=kf.R[np.ix_(keep, keep)],
                  args=(u,), hx_args=(u,))
