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
from dataclasses import dataclass

from ..errors import SettingsError
from ..runtime.limits import check_option
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
    max_iterations : iteration limit of the converged mode (reaching it is an error), 1 to
        1000.
    tolerance : converged mode stops when ``max |step| <= tolerance``; ``None``: the
        precision's default (1e-10 in float64, 1e-4 in float32). 1e-14 to 1e-3 in float64,
        1e-6 to 1e-3 in float32 (``runtime/limits.py`` says why).
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
        object.__setattr__(self, "max_iterations", check_option(
            "max_iterations", self.max_iterations, "GaussNewtonSettings.max_iterations"))
        tol = DEFAULT_TOLERANCE[self.precision] if self.tolerance is None else self.tolerance
        object.__setattr__(self, "tolerance", check_option(
            "tolerance", tol, f"GaussNewtonSettings.tolerance ({self.precision})",
            precision=self.precision))

    @property
    def estimator(self) -> str:
        """The estimator name of this mode: ``"mhe_gn"`` or ``"mhe_rti"``."""
        return "mhe_gn" if self.mode == "converged" else "mhe_rti"

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> "GaussNewtonSettings":
        return cls(**data)
