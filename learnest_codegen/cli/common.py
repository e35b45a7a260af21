"""What every ``learnest`` command shares: one-line user errors, ``--force``/``--resample``, run
reading and the estimator option texts (from the one table of estimators,
:data:`~learnest_codegen.compilation.ESTIMATORS`).

Imports no torch (``learnest --help`` stays fast).
"""

from __future__ import annotations

import functools
import os

import click
import numpy as np

from ..compilation import ESTIMATOR_NAMES, ESTIMATORS, estimator_help
from ..errors import LearnestError
from ..runtime.limits import LIMITS

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


def read_run(data: str, system, resample: bool, measured: bool = True):
    """Read a run CSV and make sure it is sampled at the system's ``dt`` (or resample it).

    With ``measured``, a run without any measurement is an error and an output column without
    a single sample is said on stderr (the estimate or the model then rests on the others)."""
    from ..data import check_sampling, read_run, unmeasured_outputs
    from ..data import resample as to_grid

    run = read_run(data, system)
    if resample:
        run = to_grid(run, system.dt)
    check_sampling(run, system.dt, str(data))
    if measured:
        for name in unmeasured_outputs(run, system, str(data)):
            click.echo(f"Warning: {data}: column y_{name} holds no sample ({len(run)} empty cells): "
                       f"output {name} is never measured, so what it would tell comes from the "
                       "model and the other outputs alone; check the column (an empty cell means "
                       "a missing sample)", err=True)
    return run


def missing_note(run, gate, dt: float) -> str:
    """The summary's words on the missing outputs of ``run``: their count and, when no output
    arrives for the gate's ``lost_after`` samples or more, the longest such gap (the estimate
    there is a prediction, flagged unreliable). Empty when nothing is missing."""
    from ..data import longest_gap
    from ..estimators.gate import lost_after

    missing = int(run.missing.sum())
    if not missing:
        return ""
    (start, length), lost = longest_gap(run), lost_after(gate)
    if length < lost:
        return f", {missing} missing"
    return (f", {missing} missing (longest gap without any measurement: {length} samples from row "
            f"{start + 1}, {length * dt:.3g} s; the estimate there is a prediction, unreliable "
            f"after {lost} samples)")


def system_named(name: str):
    from ..systems import get_system

    try:
        name.encode("utf-8")
    except UnicodeEncodeError as exc:  # a path of bytes that are not UTF-8 (surrogate escapes)
        raw = os.fsencode(name)
        bad = raw[len(name[:exc.start].encode("utf-8", "surrogateescape")):][:1]
        raise click.BadParameter(f"system file {raw.decode('utf-8', 'backslashreplace')}: its path "
                                 f"is not UTF-8 (byte {bad!r}); rename the file or its folder with "
                                 "UTF-8 characters", param_hint="--system") from None
    return get_system(name)


def resolve_system(system_name: str | None, model: str | None = None, compiled: str | None = None,
                   default: str | None = "cartpole"):
    """The system of a command: ``--system`` when given; else the one a model directory
    (``--model``) or a compiled estimator folder (``--compiled``) records (a built-in by name, a
    system file by path, refused when the file changed); else ``default``."""
    from pathlib import Path

    from ..learning.source import KEY, model_meta, read_sidecar, system_from_source

    if system_name is not None:
        return system_named(system_name)
    if model is not None and model not in ("nominal", "true"):
        meta = model_meta(model)
        return system_from_source(meta.get(KEY), meta.get("system"), f"model {model}")
    if compiled is not None:
        from ..runtime.manifest import read_manifest

        return system_from_source(read_sidecar(compiled), read_manifest(Path(compiled)).get("system"),
                                  f"compiled estimator {compiled}")
    if default is None:
        raise click.UsageError("give --system (a built-in name or a system file)")
    return system_named(default)



class EstimatorChoice(click.Choice):
    """``--estimator``: a name of :data:`~learnest_codegen.compilation.ESTIMATORS`, read when the
    command runs or shows its help (the one table of estimators)."""

    def __init__(self):
        super().__init__([])

    @property
    def choices(self):
        return tuple(ESTIMATOR_NAMES)

    @choices.setter
    def choices(self, value):  # click sets it in __init__; the table is the list
        pass


ESTIMATOR_HELP = estimator_help()
PRECISION_HELP = ("C real type: float32 for single-precision FPUs ("
                  + ", ".join(n for n, k in ESTIMATORS.items() if "float32" in k.precisions)
                  + "; the float32 UKF uses sigma-point spread alpha = 0.5)")


class InRange(click.ParamType):
    """A number checked against its range in :data:`~learnest_codegen.runtime.limits.LIMITS`, so
    an option out of range fails naming the option (and a C ``int`` never wraps)."""

    def __init__(self, name: str):
        from ..runtime.limits import LIMITS

        self.limit = LIMITS[name]
        self.name = "integer" if self.limit.integer else "float"

    def convert(self, value, param, ctx):
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            number = value
        else:
            try:
                number = int(value) if self.limit.integer else float(value)
            except (TypeError, ValueError):
                self.fail(f"{value!r} is not {self.limit.describe()}", param, ctx)
        if not self.limit.contains(number):
            self.fail(f"{value!r} is not {self.limit.describe()}", param, ctx)
        return number


#: The innovation gate's options (``learnest compile`` and ``learnest estimate``); the defaults
#: are :class:`~learnest_codegen.estimators.gate.GateSettings`' (written out here so that
#: ``--help`` loads no estimator module; a test checks they agree), the ranges those of
#: ``runtime/limits.py``.
GATE_OPTIONS = [
    click.option("--gate-threshold", type=InRange("gate_threshold"), default=50.844127911818155,
                 show_default="50.84",
                 help="innovation gate: reject an output whose normalised innovation d^2 exceeds "
                      "this chi-square(1) quantile (default: 1e-12 false rejections, 7.1 sigma; "
                      "1 to 1e12); 0 disables the gate and the recovery"),
    click.option("--gate-recover-after", type=InRange("gate_recover_after"), default=10,
                 show_default=True,
                 help="after this many consecutive samples with a rejected output (1 to 1e6), "
                      "widen the gate until measurements are accepted again (recovery from a "
                      "lost track)"),
    click.option("--gate-inflation", type=InRange("gate_inflation"), default=2.0,
                 show_default=True,
                 help="factor (1 < f <= 100) by which each further rejecting sample inflates "
                      "the uncertainty"),
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


_N = LIMITS["horizon"]
HORIZON = click.option("--horizon", type=click.IntRange(min=int(_N.low), max=int(_N.high)), default=None,
                       help="MHE horizon N, the samples in the window minus one (mhe, mhe_gn, "
                            f"mhe_rti; default 20; {_N.describe()})")


def parse_vector(text: str | None, n: int, option: str) -> np.ndarray | None:
    """``"a,b,c"`` as an ``(n,)`` array of finite numbers (``None`` stays ``None``)."""
    if text is None:
        return None
    try:
        values = np.array([float(v) for v in text.replace(" ", "").split(",")])
    except ValueError as exc:
        raise click.BadParameter(f"expected {n} comma-separated numbers, got {text!r}",
                                 param_hint=option) from exc
    if values.shape != (n,) or not np.all(np.isfinite(values)):
        raise click.BadParameter(f"expected {n} finite comma-separated numbers, got {text!r}",
                                 param_hint=option)
    return values


def parse_covariance(text: str | None, system, option: str = "--P0") -> np.ndarray | None:
    """``--P0``: ``initial`` (the system's ``initial_std**2``), nx variances (the diagonal) or
    nx*nx entries row by row; ``None`` stays ``None`` (the estimator's own)."""
    if text is None:
        return None
    from ..errors import DataError
    from ..estimators.validation import covariance

    n = system.nx
    if text.strip() == "initial":
        return np.diag(np.square(system.noise.initial_std))
    count = len(text.split(","))
    if count not in (n, n * n):
        raise click.BadParameter(f"expected 'initial', {n} variances or {n * n} entries, got "
                                 f"{count} values", param_hint=option)
    P0 = np.diag(parse_vector(text, n, option)) if count == n else \
        parse_vector(text, n * n, option).reshape(n, n)
    try:
        return covariance(option, P0, n)
    except DataError as exc:
        raise click.BadParameter(str(exc).removeprefix(f"{option}: "), param_hint=option) from exc
