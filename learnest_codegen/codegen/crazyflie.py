"""The Crazyflie target: a generated estimator as the out-of-tree state estimator of the
Crazyflie 2.x firmware (``learnest-compile MODEL --target crazyflie``; docs/guide/crazyflie.md).

:func:`write_app` turns a generated estimator folder into an app folder that the firmware's own
build compiles (``make CRAZYFLIE_BASE=...``, through the firmware's ``tools/make/oot.mk``)::

    <prefix>_crazyflie/
        Makefile            CRAZYFLIE_BASE, the app's include folders, oot.mk
        Kbuild, app-config  what the firmware builds; the app layer and CONFIG_ESTIMATOR_OOT
        src/Kbuild
        src/estimator_out_of_tree.c   the firmware side (templates/crazyflie/src): the
                                      measurement queue, state_t, param and log, the estimator task
        src/learnest_app.h  names the estimator and the state, output and input indices
        src/<prefix>/       the estimator's C (its sources and headers, its build fragment
                            <prefix>.mk) and its Kbuild, which compiles it with the flags it
                            was verified with

The algorithm stays in the generated folder (the C kit and the model); the app only adapts it.
It serves the quadrotor systems (state ``[p, v, a]``, outputs ``[p, a]``, inputs ``[T, vbat]``,
:mod:`learnest_codegen.systems.quadrotor`) and the embedded estimators in float32.
"""

from __future__ import annotations

import re
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ..errors import ModelMismatchError, SettingsError
from ..outputs import atomic_dir
from ..recordings.crazyflie import GRAVITY
from ..runtime.manifest import GeneratedEstimator
from ..systems import System
from ..toolchain import CFLAGS
from . import emit, templates
from .mhe_gn import gn_workspace

TEMPLATES = templates.TEMPLATES / "crazyflie"
#: The precision of an app (the STM32F405's FPU is single precision). Which estimators an app
#: runs is the estimator table's ``crazyflie`` field (``compilation.CRAZYFLIE_NAMES``).
PRECISION = "float32"
#: The stabilizer loop's rates a sample can be due at (the firmware's RATE_* of
#: stabilizer_types.h, divisors of its 1 kHz loop).
RATES_HZ = (1000, 500, 250, 100, 50, 25)
#: The signals the firmware side reads and writes, as contiguous triples.
STATES = {"P": ("px", "py", "pz"), "V": ("vx", "vy", "vz"), "A": ("ax", "ay", "az")}
OUTPUTS = {"P": ("px", "py", "pz"), "A": ("ax", "ay", "az")}
INPUTS = {"T": ("Tx", "Ty", "Tz"), "VBAT": ("vbat",)}
#: The app task: the priority of the firmware's Kalman task (KALMAN_TASK_PRI), below the
#: stabilizer's; its stack in 32-bit words. The UKF's step of the quadrotor keeps its sigma
#: points on the stack: 4.7 KB at the most under QEMU with the replay's own frame
#: (docs/guide/crazyflie.md), so 5 KB.
PRIORITY = 2
STACK_WORDS = 1280
APP_SOURCE = "estimator_out_of_tree.c"
#: The RAM the firmware leaves free as it comes [B]: crazyflie-firmware 2a18fc29 (the tarball of
#: ../shared/vendor), ``make cf2_defconfig && make`` with arm-none-eabi-gcc 12.2, its size report
#: (scripts/bench_crazyflie.py measures it again: docs/figures/crazyflie.json,
#: ``firmware.before.ram.free``). The estimator's workspace and the app task's stack live there.
FREE_RAM_BYTES = 37_888


@dataclass(frozen=True)
class CrazyflieApp:
    """An app folder written by :func:`write_app`."""

    directory: Path
    prefix: str
    estimator: str
    sample_rate_hz: int
    workspace_bytes: int

    @property
    def estimator_dir(self) -> Path:
        """The estimator's C inside the app."""
        return self.directory / "src" / self.prefix


def app_name(prefix: str) -> str:
    """The app folder of the estimator ``prefix``."""
    return f"{prefix}_crazyflie"


def _indices(names: tuple[str, ...], groups: dict[str, tuple[str, ...]], what: str, system: str) -> dict:
    """Where each group of ``groups`` starts in ``names``; each must be there, in order."""
    out = {}
    for key, group in groups.items():
        start = names.index(group[0]) if group[0] in names else -1
        if start < 0 or tuple(names[start:start + len(group)]) != group:
            raise ModelMismatchError(
                f"the crazyflie target needs the quadrotor's {what} {list(group)} in a row; system "
                f"{system!r} has {list(names)} (use a quadrotor system: quadrotor, quadrotor_state, "
                "quadrotor_linear, quadrotor_thrust_linear)")
        out[key] = start
    return out


def sample_rate_hz(dt: float) -> int:
    """The stabilizer rate (:data:`RATES_HZ`) one sample every ``dt`` seconds is due at."""
    rate = 1.0 / dt
    for hz in RATES_HZ:
        if abs(rate - hz) <= 1e-9 * hz:
            return hz
    raise ModelMismatchError(f"the crazyflie target steps the estimator at one of {list(RATES_HZ)} Hz "
                             f"(the stabilizer loop's rates); the model's dt {dt} s is {rate:g} Hz")


def check_target(precision: str, system: System | None) -> dict[str, int]:
    """The app's index macros for an estimator in ``precision`` of ``system``, or why it cannot
    run on a Crazyflie (:class:`SettingsError`, :class:`ModelMismatchError`); with ``system``
    None, only the precision is checked (the estimator: ``compilation.check_crazyflie``)."""
    if precision != PRECISION:
        raise SettingsError(f"the crazyflie target needs {PRECISION} (the STM32F405's FPU is single "
                            f"precision), got {precision}; give --precision {PRECISION}")
    if system is None:
        return {}
    sample_rate_hz(system.dt)
    name = system.name
    found = {f"state_{k.lower()}": v for k, v in _indices(system.state_names, STATES, "states", name).items()}
    found.update({f"output_{k.lower()}": v for k, v in
                  _indices(system.output_names, OUTPUTS, "outputs", name).items()})
    found.update({f"input_{k.lower()}": v for k, v in
                  _indices(system.input_names, INPUTS, "inputs", name).items()})
    return found


def workspace_bytes(header: Path, prefix: str) -> int:
    """``<PREFIX>_WORKSPACE_BYTES`` of a generated header."""
    match = re.search(rf"#define {prefix.upper()}_WORKSPACE_BYTES (\d+)", header.read_text())
    if not match:
        raise ModelMismatchError(f"{header} does not define {prefix.upper()}_WORKSPACE_BYTES")
    return int(match.group(1))


def _horizon_bytes(estimator: GeneratedEstimator, horizon: int) -> int:
    """The workspace of ``estimator`` (an embedded MHE) at another ``horizon``: only the counts
    of :func:`~.mhe_gn.gn_workspace` change with it, CasADi's work arrays do not."""
    bounded = estimator.settings.get("state_bounds") is not None

    def counts(n: int) -> int:
        return emit.workspace_bytes(gn_workspace(estimator.nx, estimator.nu, estimator.ny, n, bounded),
                                    estimator.precision)

    header = Path(estimator.directory) / f"{estimator.prefix}.h"
    return workspace_bytes(header, estimator.prefix) + counts(horizon) - counts(estimator.horizon)


def check_fits(estimator: GeneratedEstimator, undo: Sequence[Path] = ()) -> int:
    """The workspace of ``estimator`` [B], or :class:`SettingsError` when it and the app task's
    stack need more than the :data:`FREE_RAM_BYTES` the firmware leaves free (the firmware's link
    would fail); the folders of ``undo`` (generated for this app only) are removed before it
    raises."""
    workspace = workspace_bytes(Path(estimator.directory) / f"{estimator.prefix}.h", estimator.prefix)
    stack = 4 * STACK_WORDS
    if workspace + stack <= FREE_RAM_BYTES:
        return workspace
    remedy = "give --estimator ukf"
    if estimator.horizon is not None:
        fits = [n for n in range(1, estimator.horizon)
                if _horizon_bytes(estimator, n) + stack <= FREE_RAM_BYTES]
        if fits:
            remedy += (f", or --horizon {fits[-1]} or less (N = {fits[-1]} needs "
                       f"{_horizon_bytes(estimator, fits[-1]):,} B)")
    at = f" at N = {estimator.horizon}" if estimator.horizon is not None else ""
    for folder in undo:
        shutil.rmtree(folder, ignore_errors=True)
    raise SettingsError(
        f"the crazyflie target: {estimator.estimator}{at} needs a {workspace:,} B workspace; with the "
        f"app task's {stack:,} B stack that is more than the {FREE_RAM_BYTES:,} B of RAM the firmware "
        f"leaves free (cf2_defconfig); {remedy}")


def write_app(estimator: GeneratedEstimator, system: System, out: str | Path) -> CrazyflieApp:
    """Write the app folder of ``estimator`` (of ``system``) as ``out/<prefix>_crazyflie``,
    whole or not at all; returns it. Refused when it does not fit the firmware's RAM
    (:func:`check_fits`)."""
    indices = check_target(estimator.precision, system)
    workspace = check_fits(estimator)
    prefix, source = estimator.prefix, Path(estimator.directory)
    rate = sample_rate_hz(estimator.dt)
    values = {"p": prefix, "P": prefix.upper(), "rate_hz": rate, "dt_ms": round(1000 * estimator.dt),
              "gravity": repr(float(GRAVITY)), "priority": PRIORITY, "stack_words": STACK_WORDS,
              "cflags": " ".join(CFLAGS), **indices}
    directory = Path(out) / app_name(prefix)
    with atomic_dir(directory) as tmp:
        (tmp / "src" / prefix).mkdir(parents=True)
        for name in ("Makefile", "Kbuild", "app-config", "src/Kbuild", "src/learnest_app.h"):
            (tmp / name).write_text(templates.render(f"{name}.in", values, TEMPLATES))
        (tmp / "src" / prefix / "Kbuild").write_text(
            templates.render("src/estimator.Kbuild.in", values, TEMPLATES))
        shutil.copyfile(TEMPLATES / "src" / APP_SOURCE, tmp / "src" / APP_SOURCE)
        for name in (*estimator.sources, *estimator.headers, f"{prefix}.mk"):
            shutil.copyfile(source / name, tmp / "src" / prefix / name)
    return CrazyflieApp(directory, prefix, estimator.estimator, rate, workspace)
