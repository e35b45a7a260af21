"""The plausibility check on the input ``u``, and the status bits every estimator step reports.

An input is a measurement too: a logged command or a force sensor can glitch. A wrong ``u``
drives the prediction, which no innovation gate can see until the state is already off, so
each component of ``u`` is checked before it is used: it must be finite and, when the
settings give ``input_limits`` (from the system file, ``System.input_limits``), inside
``[lo, hi]``. A component that fails is *rejected*: the step uses the last accepted value of
that component instead (the input held, as the actuator's zero-order hold would; before any
input was accepted, zero clipped into the limits) and reports :data:`INPUT_REJECTED`. The check
keeps no streak: the next plausible value is used at once. What a wrong but plausible input
does to the state is the innovation gate's recovery to repair (:mod:`.gate`, and the MHE's
window restart in :mod:`.mhe`). Rule and measurements: ``docs/reports/reliability.md``.

Status of a step (``last_status``), a bit set so that both can be reported at once:
``0`` OK, ``MEASUREMENT_REJECTED`` (1) the innovation gate left an output out,
``INPUT_REJECTED`` (2) a component of ``u`` was replaced. None of them is an error.
"""

from __future__ import annotations

import numpy as np

from ..systems.base import check_input_limits as check_limits

#: Status bit: the innovation gate rejected at least one output of this sample.
MEASUREMENT_REJECTED = 1
#: Status bit: at least one component of ``u`` was implausible and the held value was used.
INPUT_REJECTED = 2

__all__ = ["INPUT_REJECTED", "MEASUREMENT_REJECTED", "InputCheck", "check_limits"]


class InputCheck:
    """The input check of one estimator run (see the module docstring).

    Attributes
    ----------
    rejected : (nu,) bool, the components replaced in the last step.
    held : (nu,) the last accepted value of each component.
    rejections : components replaced since :meth:`reset`.
    """

    def __init__(self, limits: tuple[tuple[float, float], ...] | None, nu: int):
        bounds = np.array(limits if limits is not None else [(-np.inf, np.inf)] * nu, dtype=float)
        self.lo, self.hi = bounds[:, 0].copy(), bounds[:, 1].copy()
        self.nu = nu
        self.reset()

    def reset(self) -> None:
        self.held = np.clip(np.zeros(self.nu), self.lo, self.hi)
        self.rejected = np.zeros(self.nu, dtype=bool)
        self.rejections = 0

    def apply(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(u_used, rejected)`` for the input ``u (nu,)``; nothing is stored (see :meth:`record`)."""
        with np.errstate(invalid="ignore"):
            plausible = np.isfinite(u) & (u >= self.lo) & (u <= self.hi)
        return np.where(plausible, u, self.held), ~plausible

    def record(self, u_used: np.ndarray, rejected: np.ndarray) -> None:
        """Store a step's outcome (called once the step has succeeded)."""
        self.held = np.array(u_used, dtype=float)
        self.rejected = np.asarray(rejected, dtype=bool).copy()
        self.rejections += int(self.rejected.sum())
