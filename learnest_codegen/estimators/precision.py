"""The floating-point precisions generated estimators can be built in, and their C types.

float64 is the default and the reference; float32 is for microcontrollers with a
single-precision FPU (accuracy cost and guards: ``docs/reports/embedded_mhe.md``).
"""

from __future__ import annotations

from ..errors import SettingsError

PRECISIONS = {"float64": "double", "float32": "float"}


def check_precision(precision: str, where: str) -> str:
    """``precision`` if it is one of :data:`PRECISIONS`, else a SettingsError naming them."""
    if precision not in PRECISIONS:
        raise SettingsError(f"{where}: precision must be one of {tuple(PRECISIONS)}, got {precision!r}")
    return precision
