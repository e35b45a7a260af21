"""What the generated Kalman filters (the UKF, ``ukf.py``; the EKF, ``ekf.py``) share: one
handle (the C kit's ``learnest_kalman.h``), so one set of defaults, workspace counts, header text
and extra declaration (``get_covariance``) around each filter's model functions and kit file.
"""

from __future__ import annotations

from typing import Mapping

import casadi as cs
import numpy as np

from ..estimators.kalman import KalmanSettings
from ..export import DiscreteModel
from .emit import Design, comment


def kalman_design(model: DiscreteModel, settings: KalmanSettings, *, estimator: str, title: str,
                  kit: str, functions: tuple[cs.Function, ...], hooks: Mapping[str, str],
                  precision: str, description: str, predicted: tuple[str, str]) -> Design:
    """The :class:`Design` of a Kalman filter of ``model`` with ``settings`` (validated).

    ``description`` says what the filter computes (the header adds what the kit runs around
    it); ``predicted`` names the predicted output and says what it and its covariance ``S``
    are, for the gate's paragraph."""
    settings.validate_for(model)
    nx, ny = model.nx, model.ny
    return Design(
        estimator=estimator, title=title, kit=kit, functions=functions, hooks=hooks,
        defaults={"x0": np.asarray(model.system.x0, dtype=float), "P0": settings.P0(),
                  "Q": settings.Q(), "R": settings.R()},
        gate=settings.gate, precision=precision, settings=settings.to_json(), solver=None,
        horizon=None, doc=header_doc(description, predicted), declarations=("kalman.h.in",),
        workspace={"reals": 4 + nx + 2 * nx * nx + ny * ny + model.nu, "ints": 6 + ny + model.nu,
                   "members": 19})


def header_doc(description: str, predicted: tuple[str, str]) -> dict[str, str]:
    """A Kalman filter's paragraphs of its header (see :func:`kalman_design`)."""
    name, meaning = predicted
    return {
        "description": comment(f"{description}; the kit also runs the samples, the gate and the "
                               "covariance guards around it."),
        "arrival_note": "", "reset_keeps": "", "init_options": "", "threads": "",
        "covariance_rule": "P0 and Q must be symmetric positive semidefinite (to rounding) and R "
                           "positive definite, else\n * LEARNEST_NOT_POSITIVE_DEFINITE; every "
                           "variance in the precision's range (LEARNEST_VARIANCE_MIN/_MAX;\n * "
                           "P0's and Q's may be 0), else LEARNEST_BAD_ARGUMENT.",
        "set_noise_keeps": "the state, its covariance and the gate",
        "gate_doc": f"each step computes, per valid output j, d2_j = (y_j - {name}_j)^2 / S_jj "
                    f"with\n *   {meaning}.",
        "recovery_doc": "the variances (the diagonal of P; the covariances\n"
                        " *   stay, so stale correlations fade) are multiplied by it. No variance "
                        "of P exceeds\n *   its ceiling, the cap times the initial variance "
                        "(the default P0's diagonal).",
        "reseed_doc": "the update is redone from the prior covariance\n"
                      " *   diag(ceiling) with every valid output.",
    }
