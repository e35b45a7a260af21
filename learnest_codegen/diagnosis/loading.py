"""Reading the runs a diagnosis works on: run CSVs, or real recordings through their readers.

A real recording may come with its own reference (what estimators are scored against) and start
state. NanoBench flights use exactly the quadrotor study's
(:mod:`~learnest_codegen.experiments.quadrotor`): the Savitzky-Golay states of Vicon position
(:func:`~learnest_codegen.recordings.crazyflie.reference_states`) and :func:`start_state`, so
``diagnose`` and the study score the same thing. A recording that cannot be used (a flight that
never leaves the ground) is skipped with its reason, as the study does, instead of stopping the
diagnosis.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..data import Run, read_run
from ..errors import DataError, UnknownNameError
from ..systems import System


@dataclass(frozen=True)
class Recordings:
    """Runs with what a diagnosis needs to know about them.

    Attributes
    ----------
    runs : the runs.
    names : one name per run (the file's stem).
    references : per run, ``(T, nx)`` states the estimators are scored against (``None``: the
        truth, else the observer's state observations).
    starts : per run, ``(nx,)`` state the estimators start from (``None``: the reference's first).
    reference : what the references are, for the report.
    skipped : recording name -> why it was left out.
    """

    runs: list[Run]
    names: list[str]
    references: list[np.ndarray] | None = None
    starts: list[np.ndarray] | None = None
    reference: str | None = None
    skipped: dict[str, str] = field(default_factory=dict)


def load_runs(system: System, data: str | Path) -> list[Run]:
    """A run CSV, or every ``*.csv`` of a folder (sorted by name), in the project's run format."""
    return _run_files(system, Path(data)).runs


def _run_files(system: System, data: Path) -> Recordings:
    if data.is_dir():
        files = sorted(data.glob("*.csv"))
        if not files:
            raise DataError(f"{data}: no *.csv runs in this folder")
        return Recordings([read_run(f, system) for f in files], [f.stem for f in files])
    return Recordings([read_run(data, system)], [data.stem])


def start_state(run: Run, fit_samples: int = 11) -> np.ndarray:
    """(9,) the quadrotor study's start state: position and acceleration as first measured,
    velocity the slope of a line through the first ``fit_samples`` positions."""
    n = min(fit_samples, len(run))
    velocity = np.polyfit(run.t[:n] - run.t[0], run.y[:n, :3], 1)[0]
    return np.concatenate([run.y[0, :3], velocity, run.y[0, 3:6]])


def _read_nanobench(path: Path) -> Recordings:
    from ..recordings import crazyflie
    from ..systems.quadrotor import QUADROTOR

    files = crazyflie.list_flights(path) if path.is_dir() else [path]
    flights, skipped = [], {}
    for f in files:
        try:
            flight = crazyflie.read_flight(f)
            if abs(flight.timing.dt - QUADROTOR.dt) > 1e-3 * QUADROTOR.dt:
                raise DataError(f"flight {flight.name}: sampled every {flight.timing.dt} s, but the "
                                f"quadrotor model steps {QUADROTOR.dt} s")
        except DataError as exc:
            skipped[Path(f).stem] = str(exc)
            continue
        flights.append(flight)
    return Recordings([f.run for f in flights], [f.name for f in flights], [f.reference for f in flights],
                      [start_state(f.run) for f in flights],
                      "the quadrotor study's reference (Vicon position, Savitzky-Golay velocity and "
                      "acceleration)", skipped)


def _read_dart(path: Path) -> Recordings:
    from ..recordings import dart

    files = sorted(p for p in path.glob("*.csv")) if path.is_dir() else [path]
    runs, names, skipped = [], [], {}
    for f in files:
        try:
            runs.append(dart.read_recording(f))
            names.append(f.stem)
        except DataError as exc:
            skipped[f.stem] = str(exc)
    return Recordings(runs, names, skipped=skipped)


# format -> (reader of a file or folder, the system its runs belong to; None: --system decides)
FORMATS = {"run": (None, None), "nanobench": (_read_nanobench, "quadrotor"), "dart": (_read_dart, "rc_car")}


def load_recordings(system_name: str | None, data: str | Path,
                    data_format: str = "run") -> tuple[System, Recordings]:
    """Resolve the system and read ``data`` in ``data_format`` (see :data:`FORMATS`); recordings
    a reader cannot use are listed under ``skipped``."""
    from ..systems import get_system

    if data_format not in FORMATS:
        raise UnknownNameError(f"unknown data format {data_format!r}; choose from {sorted(FORMATS)}")
    reader, default_system = FORMATS[data_format]
    system = get_system(system_name or default_system or "cartpole")
    if reader is None:
        return system, _run_files(system, Path(data))
    found = reader(Path(data))
    if not found.runs:
        why = "; ".join(f"{k}: {v}" for k, v in found.skipped.items())
        raise DataError(f"{data}: no usable {data_format} recordings" + (f" ({why})" if why else ""))
    if any(r.system != system.name for r in found.runs):
        raise DataError(f"{data}: {data_format} recordings belong to system {found.runs[0].system!r}, "
                        f"not {system.name!r}")
    return system, found


def load(system_name: str | None, data: str | Path, data_format: str = "run") -> tuple[System, list[Run]]:
    """Resolve the system and read the runs of ``data`` in ``data_format`` (see :data:`FORMATS`;
    :func:`load_recordings` also gives their references and the recordings skipped)."""
    system, found = load_recordings(system_name, data, data_format)
    return system, found.runs
