"""System descriptions and the registry that resolves ``--system`` names or file paths."""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path

from ..errors import SystemFileError, UnknownNameError
from .base import DiagnosisHints as DiagnosisHints
from .base import KinematicChain as KinematicChain
from .base import NoiseModel as NoiseModel
from .base import ResidualStructure as ResidualStructure
from .base import Signal as Signal
from .base import System as System
from .cartpole import CARTPOLE
from .check import check_system
from .ground_robot import GROUND_ROBOT
from .quadrotor import QUADROTORS
from .rc_car import RC_CAR

SYSTEMS: dict[str, System] = {s.name: s for s in (CARTPOLE, GROUND_ROBOT, *QUADROTORS, RC_CAR)}


def register(system: System) -> System:
    """Add a system to the registry (by its name) and return it, after :func:`check_system`."""
    check_system(system, f"system {system.name!r}")
    SYSTEMS[system.name] = system
    return system


def get_system(name_or_path: str | System) -> System:
    """Resolve a built-in name (``"cartpole"``) or a path to a Python file defining ``SYSTEM``.

    A user file must define a module-level ``SYSTEM = System(...)``; see the README. Its
    equations are checked when it is loaded (:func:`~.check.check_system`: numpy, torch and
    CasADi agree on a few points near ``x0``); a mistake is one :class:`SystemFileError` line.
    """
    if isinstance(name_or_path, System):
        return name_or_path
    key = str(name_or_path)
    if key in SYSTEMS:
        return SYSTEMS[key]
    if key.endswith(".py") or Path(key).is_file():
        return _load_system_file(Path(key))
    raise UnknownNameError(f"unknown system {key!r}; built-in systems: {sorted(SYSTEMS)} "
                           "(or give the path of a .py file that defines SYSTEM)")


def _load_system_file(path: Path) -> System:
    if not path.is_file():
        raise SystemFileError(f"system file {path} does not exist")
    digest = hashlib.sha1(str(path.resolve()).encode()).hexdigest()[:10]
    spec = importlib.util.spec_from_file_location(f"learnest_user_system_{digest}", path)
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # a user file can fail in any way; say which file
        message = " ".join(str(exc).split())
        raise SystemFileError(f"system file {path} failed to import: {type(exc).__name__}: {message}") \
            from exc
    system = getattr(module, "SYSTEM", None)
    if not isinstance(system, System):
        raise SystemFileError(f"system file {path} must define SYSTEM = learnest_codegen.System(...), "
                              f"found {type(system).__name__}")
    check_system(system, f"system file {path}")
    return system
