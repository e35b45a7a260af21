"""The documented range of every run-time option, at the C boundary and in Python.

One table: ``learnest_status.h`` renders it as ``LEARNEST_<NAME>_MIN/_MAX`` (a C call outside
it returns ``LEARNEST_BAD_ARGUMENT`` and changes nothing) and the Python settings check the same
numbers, so both refuse the same values. Why these ranges: docs/c_api.md. Torch-free.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Limit:
    """An option's closed range ``[low, high]`` (``low_open``: ``(low, high]``)."""

    name: str
    low: float
    high: float
    meaning: str
    low_open: bool = False
    integer: bool = False

    def contains(self, value) -> bool:
        if self.integer and (isinstance(value, bool) or int(value) != value):
            return False
        value = float(value)
        above = value > self.low if self.low_open else value >= self.low
        return math.isfinite(value) and above and value <= self.high

    def describe(self) -> str:
        left = "(" if self.low_open else "["
        kind = "an integer" if self.integer else "a number"
        return f"{kind} in {left}{self.low:g}, {self.high:g}]"


#: name -> Limit; the C macros are LEARNEST_<NAME>_MIN and LEARNEST_<NAME>_MAX.
LIMITS = {limit.name: limit for limit in (
    Limit("MAX_ITER", 1, 1000, "Gauss-Newton iterations of one converged step", integer=True),
    Limit("TOL", 1e-14, 1e-3, "converged mode: stop when no state moves by more than this"),
    Limit("THRESHOLD", 1.0, 1e12, "the innovation gate's chi-square(1) threshold (0 or +inf: "
          "no gate)"),
    Limit("RECOVER_AFTER", 1, 1_000_000, "rejecting steps in a row before the recovery inflates",
          integer=True),
    Limit("INFLATION", 1.0, 1e3, "the recovery's factor per step", low_open=True),
)}


def check(name: str, value, where: str) -> None:
    """Raise ValueError naming ``where``, the range and the value unless ``value`` is in it."""
    limit = LIMITS[name]
    if not limit.contains(value):
        raise ValueError(f"{where} must be {limit.describe()} ({limit.meaning}), got {value!r}")


def c_macros() -> str:
    """The ranges as C ``#define`` lines of ``learnest_status.h``."""
    lines = []
    for limit in LIMITS.values():
        fmt = (lambda v: str(int(v))) if limit.integer else (lambda v: repr(float(v)))
        bound = "exclusive" if limit.low_open else "inclusive"
        lines.append(f"/* {limit.meaning}: {limit.describe()}. */")
        lines.append(f"#define LEARNEST_{limit.name}_MIN {fmt(limit.low)} /* {bound} */")
        lines.append(f"#define LEARNEST_{limit.name}_MAX {fmt(limit.high)}")
    return "\n".join(lines)
