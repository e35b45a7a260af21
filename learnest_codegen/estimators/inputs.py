"""The plausibility check on the input ``u``, and the status bits every estimator step reports.

An input is a measurement too: a logged command or a force sensor can glitch. A wrong ``u``
drives the prediction, which no innovation gate can see until the state is already off, so each
component of ``u`` is checked before it is used: it must be finite and, when the settings give
``input_limits``, inside ``[lo, hi]``. The settings' default is :func:`plausible_inputs`: the
system file's ``input_limits`` where it declares them (the actuator's real range), otherwise a
range derived from the inputs its own excitation drives (the range the system's runs, and a
model trained on them, cover), widened tenfold about its centre: on the ground robot, which
declares none, one ``u = 1e6`` sample threw the UKF off for good (MSE 1.2e8 against 0.0087),
and ``u = 1e30`` made both embedded MHEs fail every later step. A component that fails is
*rejected*: the step uses the last accepted value of that component instead (the input held, as
the actuator's zero-order hold would; before any input was accepted, zero clipped into the
limits) and reports :data:`INPUT_REJECTED`. The check keeps no streak: the next plausible value
is used at once. What a wrong but plausible input does to the state is the innovation gate's
recovery to repair (:mod:`.gate`, and the MHE's window restart in :mod:`.mhe`). Rule and
measurements: ``docs/reports/reliability.md``.

Status of a step (``last_status``), a bit set so that several can be reported at once:
``0`` OK, ``MEASUREMENT_REJECTED`` (1) the innovation gate left an output out,
``INPUT_REJECTED`` (2) a component of ``u`` was replaced, ``UNRELIABLE`` (4) the estimate is
lost (:mod:`.gate`). None of them is an error.
"""

from __future__ import annotations

import numpy as np

from ..systems.base import System
from ..systems.base import check_input_limits as check_limits

#: Status bit: the innovation gate rejected at least one output of this sample.
MEASUREMENT_REJECTED = 1
#: Status bit: at least one component of ``u`` was implausible and the held value was used.
INPUT_REJECTED = 2

__all__ = ["INPUT_REJECTED", "MEASUREMENT_REJECTED", "InputCheck", "check_limits", "plausible_inputs"]

#: Seeds of the excitation whose inputs :func:`plausible_inputs` spans.
PLAUSIBLE_SEEDS = (0, 1, 2, 3)
#: How far :func:`plausible_inputs` widens the excitation's range about its centre.
PLAUSIBLE_WIDENING = 10.0


def plausible_inputs(system: System) -> tuple[tuple[float, float], ...]:
    """The plausible range of each input of ``system``: its declared ``input_limits``, or
    ``(c - 10 h, c + 10 h)`` with ``c`` and ``h`` the centre and half-width of the range its
    excitation spans over its default duration (seeds :data:`PLAUSIBLE_SEEDS`; ``h`` at least
    ``max(|c|, 1)`` / 10 for an input the excitation holds constant)."""
    if system.input_limits is not None:
        return system.input_limits
    t = np.arange(int(round(system.duration / system.dt)) + 1) * system.dt
    U = np.concatenate([np.asarray(system.excitation(t, np.random.default_rng(seed)), dtype=float)
                        .reshape(len(t), system.nu) for seed in PLAUSIBLE_SEEDS])
    U = np.where(np.isfinite(U), U, np.nan)
    lo, hi = np.nanmin(U, axis=0), np.nanmax(U, axis=0)
    centre, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    half = np.maximum(half, np.maximum(np.abs(centre), 1.0) / PLAUSIBLE_WIDENING)
    return tuple((float(c - PLAUSIBLE_WIDENING * h), float(c + PLAUSIBLE_WIDENING * h))
                 for c, h in zip(centre, half))


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
