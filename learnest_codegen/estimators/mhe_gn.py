"""Settings of the embedded MHE: the Gauss-Newton SQP that solves eq. (2) in generated C.

The problem is :mod:`.mhe_problem`'s (the Ipopt MHE's); these settings choose how the
generated solver (:mod:`..codegen.mhe_gn`) iterates on it:

- ``"converged"`` (estimator ``mhe_gn``): Gauss-Newton iterations until the largest step
  component is at most ``tolerance``, at most ``max_iterations``. Its fixed point is a
  stationary point of the same cost, so it reproduces the Ipopt MHE (tested to 1e-6).
- ``"rti"`` (estimator ``mhe_rti``): one iteration per sample from the shifted previous
  solution (real-time iteration), reusing the Jacobians of the shifted stages.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..errors import SettingsError
from .precision import check_precision

MODES = ("converged", "rti")
# The step tolerance a precision can reach: ~1e6 ulps of O(1) states.
DEFAULT_TOLERANCE = {"float64": 1e-10, "float32": 1e-4}


@dataclass(frozen=True, kw_only=True)
class GaussNewtonSettings:
    """How the embedded MHE iterates.

    Attributes
    ----------
    mode : ``"converged"`` or ``"rti"`` (see the module docstring).
    max_iterations : iteration limit of the converged mode (reaching it is an error).
    tolerance : converged mode stops when ``max |step| <= tolerance``; ``None``: the
        precision's default (1e-10 in float64, 1e-4 in float32).
    precision : ``"float64"`` or ``"float32"``, the C real type of the generated solver.
    """

    mode: str = "converged"
    max_iterations: int = 30
    tolerance: float | None = None
    precision: str = "float64"

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise SettingsError(f"GaussNewtonSettings.mode must be one of {MODES}, got {self.mode!r}")
        check_precision(self.precision, "GaussNewtonSettings")
        if isinstance(self.max_iterations, bool) or not isinstance(self.max_iterations, int) \
                or self.max_iterations < 1:
            raise SettingsError(f"GaussNewtonSettings.max_iterations must be an integer >= 1, "
                                f"got {self.max_iterations!r}")
        tol = DEFAULT_TOLERANCE[self.precision] if self.tolerance is None else self.tolerance
        if not (isinstance(tol, (int, float)) and math.isfinite(tol) and tol > 0):
            raise SettingsError(f"GaussNewtonSettings.tolerance must be a positive number, got {tol!r}")
        object.__setattr__(self, "tolerance", float(tol))

    @property
    def estimator(self) -> str:
        """The estimator name of this mode: ``"mhe_gn"`` or ``"mhe_rti"``."""
        return "mhe_gn" if self.mode == "converged" else "mhe_rti"

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> "GaussNewtonSettings":
        return cls(**data)
