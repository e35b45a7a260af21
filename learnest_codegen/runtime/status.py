"""The one status table of every generated estimator's C API (``learnest_status.h``).

Each code is a name, a meaning and how the caller recovers. :mod:`..codegen.status` renders
the table into the C header every estimator includes, and the ctypes bindings read names from
it here, so C and Python cannot disagree. Zero and positive codes are not errors; negative
codes are, and a step that returns one leaves the estimator as it was. The positive codes are
bits (1 an output rejected, 2 an input rejected; a step that did both returns 3). Torch-free.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Status:
    """One C return code: ``LEARNEST_<name>``."""

    code: int
    name: str
    meaning: str
    recovery: str


STATUSES = (
    Status(0, "OK", "the call did what it says", "nothing to do"),
    Status(1, "MEASUREMENT_REJECTED",
           "the innovation gate rejected at least one output of this sample (its normalised "
           "innovation exceeded the threshold): the step succeeded without those outputs, and "
           "<prefix>_get_rejected says which; after recover_after such steps in a row the "
           "estimator inflates its uncertainty to re-acquire a lost track",
           "not an error; keep stepping (a long run of it means the sensor or the model is off)"),
    Status(2, "INPUT_REJECTED",
           "the input plausibility check replaced a component of u that was not finite or "
           "outside the system's input limits by its last accepted value (a bit: OR-ed with "
           "MEASUREMENT_REJECTED; get_input_rejected says which)",
           "not an error; keep stepping (a long run of it means the actuator, its command log "
           "or the declared range is wrong)"),
    Status(4, "UNRELIABLE",
           "the estimate is not backed by the measurements: no output has been accepted for as "
           "many steps as the gate needs to open fully (recover_after plus the widenings up to "
           "its cap), after a long run of predictions or a lost track (a bit: OR-ed with the "
           "others); the next step whose gate rejects a valid output re-seeds the estimate from "
           "the measurements, and the next accepted output clears it",
           "not an error; do not act on the estimate until it clears (a long run of it means "
           "the sensors are off or the measurements stopped)"),
    Status(-1, "NOT_INITIALISED", "the handle is NULL or was not made by init",
           "call <prefix>_init on the workspace first"),
    Status(-2, "BAD_ARGUMENT",
           "a NULL pointer, a size, a validity flag other than 0 or 1, or an option or a "
           "covariance's variance outside its documented range (LEARNEST_*_MIN/_MAX below)",
           "fix the call; nothing was changed"),
    Status(-3, "NONFINITE_INPUT",
           "a valid output of y, x0 or a covariance is NaN or infinite (a non-finite u is "
           "replaced, INPUT_REJECTED)",
           "mark a missing output missing (valid[j] = 0) or call predict; the estimator is "
           "unchanged"),
    Status(-4, "NO_MEMORY", "the workspace is smaller than <prefix>_workspace_size()",
           "give a larger buffer"),
    Status(-5, "NONFINITE_RESULT", "the solution or covariance came out NaN or infinite",
           "the estimator is unchanged; reset it, or check the weights and the model"),
    Status(-6, "NOT_POSITIVE_DEFINITE",
           "a Cholesky factorisation failed (covariance or normal equations not positive "
           "definite)",
           "the estimator is unchanged; reset it, or raise the noise covariances"),
    Status(-7, "MAX_ITERATIONS", "the solver reached its iteration limit before its tolerance",
           "the estimator is unchanged; raise the limit or the tolerance, or use RTI mode"),
    Status(-8, "LINE_SEARCH_FAILED", "no step length decreased the cost",
           "the estimator is unchanged; reset it near the true state"),
    Status(-9, "SOLVER_FAILED", "the NLP solver (Ipopt) reported a failure",
           "the estimator is unchanged; reset it, or check the weights"),
)

STATUS_NAMES = {s.code: s.name for s in STATUSES}
STATUS_BY_CODE = {s.code: s for s in STATUSES}


def status_name(code: int) -> str:
    """``"OK"``, ``"NOT_POSITIVE_DEFINITE"``, ... or ``"UNKNOWN(<code>)"``."""
    return STATUS_NAMES.get(code, f"UNKNOWN({code})")
