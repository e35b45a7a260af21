"""The one table of ranges of the estimators' options, for Python and for the C API.

Every option a user sets (the Gauss-Newton iteration limit and tolerance, the innovation
gate's values, the horizon, the noise stds) has a documented range here, with the reason for
its ends. The settings classes check their fields with :func:`check_option`, the command line takes
its click ranges from :data:`LIMITS`, and the generated C's argument checks
(``<prefix>_set_options``, ``<prefix>_set_gate``) test the same numbers, rendered into
``learnest_status.h`` as ``LEARNEST_<C_NAME>_MIN/_MAX`` by :func:`c_macros`, so Python and C cannot
disagree (as ``status.py`` does for the
status codes). An integer option is a C ``int``: its range lies inside ``[1, INT_MAX]``, so a
Python int never wraps on its way to C. Torch-free.
"""

from __future__ import annotations

import math
import numbers
import re
from dataclasses import dataclass

from ..errors import SettingsError

#: The largest C ``int`` (32 bits on every target the generated C supports).
C_INT_MAX = 2**31 - 1


@dataclass(frozen=True)
class Limit:
    """The range of one option: ``low .. high`` (each end closed unless ``*_open``).

    ``off`` lists values outside the range that are accepted with a meaning of their own (the
    gate threshold's 0 and inf: no gate). ``integer`` options are C ``int``\\ s.
    """

    name: str
    low: float
    high: float
    why: str
    integer: bool = False
    low_open: bool = False
    high_open: bool = False
    off: tuple[float, ...] = ()
    c_name: str = ""

    def contains(self, value: float) -> bool:
        if value in self.off:
            return True
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return bool(above and below)

    def describe(self) -> str:
        """``"an integer in [1, 1000]"``, ``"a number in (1, 100]"``, ... (with the off values)."""
        left, right = "(" if self.low_open else "[", ")" if self.high_open else "]"
        text = (f"{'an integer' if self.integer else 'a number'} in "
                f"{left}{_number(self.low)}, {_number(self.high)}{right}")
        if self.off:
            text += " (or " + " or ".join(_number(v) for v in self.off) + ": off)"
        return text

    def c_condition(self, var: str) -> str:
        """The C expression that holds when ``var`` is in range (NaN fails it)."""
        lo, hi = ">" if self.low_open else ">=", "<" if self.high_open else "<="
        inside = f"({var} {lo} {self.low!r} && {var} {hi} {self.high!r})"
        for v in self.off:
            if math.isinf(v):
                inside += f" || (isinf({var}) && {var} {'>' if v > 0 else '<'} 0)"
            else:
                inside += f" || {var} == {v!r}"
        return f"({inside})" if self.off else inside


def _number(v: float) -> str:
    """``1e-6``, ``1e12``, ``1000``, ``2147483647``: short and exact enough for a message."""
    if float(v).is_integer() and abs(v) < 1e10:
        return str(int(v))
    return re.sub(r"e([+-])0*(\d)", lambda m: "e" + ("-" if m.group(1) == "-" else "") + m.group(2),
                  f"{v:g}")


_TOLERANCE_WHY = ("the converged Gauss-Newton step stops when its largest component is at most "
                  "the tolerance, so above 1e-3 it stops before any step that matters (at 1e300 "
                  "it takes none: 12.8 times the MSE on a cartpole run), and below about 10 "
                  "rounding units of O(1) states it cannot be met")

#: Every option's range; a key with ``[precision]`` depends on the C real type.
LIMITS: dict[str, Limit] = {limit.name: limit for limit in (
    Limit("max_iterations", 1, 1000, integer=True, c_name="MAX_ITER",
          why="bounds the time of a converged step that cannot reach its tolerance (the "
              "KNODE cartpole takes 2 iterations on 94 % of samples, at most 18); a larger "
              "limit only waits longer"),
    Limit("tolerance[float64]", 1e-14, 1e-3, why=_TOLERANCE_WHY, c_name="TOL"),
    Limit("tolerance[float32]", 1e-6, 1e-3, why=_TOLERANCE_WHY, c_name="TOL_FLOAT32"),
    Limit("gate_threshold", 1.0, 1e12, off=(0.0, math.inf), c_name="THRESHOLD",
          why="a chi-square(1) quantile: below 1 the gate rejects a third of clean outputs or "
              "more; above 1e12 (a 1e6-sigma innovation) it is an 'off' that still runs the "
              "recovery (say 0 to turn the gate off)"),
    Limit("gate_recover_after", 1, 1_000_000, integer=True, c_name="RECOVER_AFTER",
          why="consecutive rejecting samples before the recovery starts; a C int, and beyond a "
              "million the recovery is in effect off"),
    Limit("gate_inflation", 1.0, 100.0, low_open=True, c_name="INFLATION",
          why="the recovery's factor per rejecting sample: at 1 nothing grows, and a factor "
              "above the inflation cap (1e6 in float32) would never be applied"),
    Limit("horizon", 1, 1000, integer=True, c_name="HORIZON",
          why="MHE window transitions; the workspace and the solve grow with it, and a window "
              "of a thousand samples is already seconds of data at the usual rates"),
    Limit("std", 1e-100, 1e100,
          why="noise standard deviations: their squares and inverse squares (the weights) "
              "must be finite and non-zero in float64"),
    Limit("variance[float64]", 1e-200, 1e200, c_name="VARIANCE",
          why="a variance of a covariance given at run time (P0, Q, R, P_arrival), the std's "
              "range squared: its inverse weighs a cost and its square enters the updates, so "
              "both must stay finite and non-zero (R = 1e-300 I made the UKF drift to an error "
              "of 9-12, P_arrival = 1e-300 I the mhe_gn to 14.7)"),
    Limit("variance[float32]", 1e-30, 1e30, c_name="VARIANCE_FLOAT32",
          why="the same in a float32 build, whose reals end at 3.4e38 and lose precision "
              "below 1.2e-38"),
    Limit("ukf_alpha", 0.0, 1.0, low_open=True,
          why="the Merwe sigma-point spread: 0 < alpha <= 1"),
    Limit("run_length", 1, C_INT_MAX, integer=True, why="T of <prefix>_run is a C int"),
)}


def limit(name: str, precision: str | None = None) -> Limit:
    """The limit of option ``name`` (``tolerance`` needs the precision)."""
    return LIMITS[f"{name}[{precision}]"] if f"{name}[{precision}]" in LIMITS else LIMITS[name]


def check_option(name: str, value, where: str, *, precision: str | None = None) -> float | int:
    """``value`` as the option's type (int or float) if it is in range, else :class:`SettingsError`.

    ``where`` names the field in the message, e.g. ``"GateSettings.inflation"``.
    """
    lim = limit(name, precision)
    if lim.integer:
        ok_type = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    else:
        ok_type = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if ok_type:
        number = int(value) if lim.integer else float(value)
        if lim.contains(number):
            return number
    raise SettingsError(f"{where} must be {lim.describe()}, got {value!r}")


def c_macros() -> str:
    """The ranges the C API checks, as ``#define LEARNEST_<C_NAME>_MIN/_MAX`` lines of
    ``learnest_status.h`` (an open lower end is said in a comment; the C compares with ``>``)."""
    lines = []
    for lim in LIMITS.values():
        if not lim.c_name:
            continue
        fmt = (lambda v: str(int(v))) if lim.integer else (lambda v: repr(float(v)))
        bound = "exclusive" if lim.low_open else "inclusive"
        lines.append(f"/* {lim.name}: {lim.describe()}. */")
        lines.append(f"#define LEARNEST_{lim.c_name}_MIN {fmt(lim.low)} /* {bound} */")
        lines.append(f"#define LEARNEST_{lim.c_name}_MAX {fmt(lim.high)}")
    return "\n".join(lines)
