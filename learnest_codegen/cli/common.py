"""What every ``learnest`` command shares: one-line user errors, ``--force``/``--resample``, run
reading and the estimator option texts.

Imports neither torch nor CasADi (``learnest --help`` stays fast).
"""

from __future__ import annotations

import functools
import os

import click
import numpy as np

from ..errors import LearnestError

SYSTEM_HELP = "built-in system name (cartpole) or path to a .py file defining SYSTEM"

#: Failures a user can cause: the package's own errors, files (missing, unreadable, unwritable),
#: values out of range (settings' ValueError) and numerics that a bad input drives off a cliff.
USER_ERRORS = (LearnestError, OSError, ValueError, ArithmeticError, np.linalg.LinAlgError)


def friendly(fn):
    """Turn the failures a user can cause into a one-line error (exit 1) instead of a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except USER_ERRORS as exc:
            if os.environ.get("LEARNEST_TRACEBACK"):
                raise
            message = " ".join(str(exc).split()) or type(exc).__name__
            raise click.ClickException(message) from exc

    return wrapper


FORCE = click.option("--force", is_flag=True, help="replace an existing output")
RESAMPLE = click.option("--resample", is_flag=True,
                        help="put a run sampled at another rate on the system's time step "
                             "(default: refuse such a run)")


def read_run(data: str, system, resample: bool):
    """Read a run CSV and make sure it is sampled at the system's ``dt`` (or resample it)."""
    from ..data import check_sampling, read_run
    from ..data import resample as to_grid

    run = read_run(data, system)
    if resample:
        run = to_grid(run, system.dt)
    check_sampling(run, system.dt, str(data))
    return run


def system_named(name: str):
    from ..systems import get_system

    return get_system(name)



# the names of compilation.ESTIMATOR_NAMES (not imported here: it would load casadi for --help)
ESTIMATOR_CHOICES = ["mhe", "ukf", "mhe_gn", "mhe_rti"]
ESTIMATOR_HELP = ("mhe: the MHE solved by Ipopt (the reference); ukf: the UKF; mhe_gn: the "
                  "embedded MHE (Gauss-Newton, no Ipopt, no malloc) iterated to convergence, the "
                  "same estimates as mhe; mhe_rti: the embedded MHE with one Gauss-Newton "
                  "iteration per sample (real-time iteration, fastest)")
PRECISION_HELP = ("C real type: float32 for single-precision FPUs (ukf, mhe_gn and mhe_rti; the "
                  "float32 UKF uses sigma-point spread alpha = 0.5)")


#: The innovation gate's options (``learnest compile`` and ``learnest estimate``); the defaults
#: are :class:`~learnest_codegen.estimators.gate.GateSettings`' (written out here so that
#: ``--help`` loads no estimator module; a test checks they agree).
GATE_OPTIONS = [
    click.option("--gate-threshold", type=click.FloatRange(min=0.0), default=50.844127911818155,
                 show_default="50.84",
                 help="innovation gate: reject an output whose normalised innovation d^2 exceeds "
                      "this chi-square(1) quantile (default: 1e-12 false rejections, 7.1 sigma); "
                      "0 disables the gate and the recovery"),
    click.option("--gate-recover-after", type=click.IntRange(min=1), default=10, show_default=True,
                 help="after this many consecutive samples with a rejected output, widen the "
                      "gate until measurements are accepted again (recovery from a lost track)"),
    click.option("--gate-inflation", type=click.FloatRange(min=1.0, min_open=True), default=2.0,
                 show_default=True,
                 help="factor by which each further rejecting sample inflates the uncertainty"),
]


CLAMP_INPUTS = click.option(
    "--clamp-inputs/--no-clamp-inputs", "clamp_inputs", default=None,
    help="keep a trained net's inputs inside their training range (clamped in the generated "
         "model; default: learnest_codegen.compilation.CLAMP_INPUTS)")


def with_gate_options(fn):
    """Add :data:`GATE_OPTIONS` to a command (arguments ``gate_threshold``, ...)."""
    for option in reversed(GATE_OPTIONS):
        fn = option(fn)
    return fn


def gate_settings(threshold: float, recover_after: int, inflation: float):
    """The :class:`GateSettings` of the options, or ``None`` when they are the defaults."""
    from ..estimators.gate import GateSettings

    gate = GateSettings(threshold=threshold, recover_after=recover_after, inflation=inflation)
    return None if gate == GateSettings() else gate
