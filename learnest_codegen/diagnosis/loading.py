"""Reading the runs a diagnosis works on: run CSVs, or real recordings through their readers."""

from __future__ import annotations

from pathlib import Path

from ..data import Run, read_run
from ..errors import DataError, UnknownNameError
from ..systems import System


def load_runs(system: System, data: str | Path) -> list[Run]:
    """A run CSV, or every ``*.csv`` of a folder (sorted by name), in the project's run format."""
    data = Path(data)
    if data.is_dir():
        files = sorted(data.glob("*.csv"))
        if not files:
            raise DataError(f"{data}: no *.csv runs in this folder")
        return [read_run(f, system) for f in files]
    return [read_run(data, system)]


def _read_nanobench(path: Path) -> list[Run]:
    from ..recordings import crazyflie

    files = crazyflie.list_flights(path) if path.is_dir() else [path]
    return [crazyflie.read_flight(f).run for f in files]


def _read_dart(path: Path) -> list[Run]:
    from ..recordings import dart

    files = sorted(p for p in path.glob("*.csv")) if path.is_dir() else [path]
    # the held encoder samples as samples, until the diagnosis takes missing outputs
    return [dart.read_recording(f, dart.DartSettings(held="hold")) for f in files]


# format -> (reader of a file or folder, the system its runs belong to; None: --system decides)
FORMATS = {"run": (None, None), "nanobench": (_read_nanobench, "quadrotor"), "dart": (_read_dart, "rc_car")}


def load(system_name: str | None, data: str | Path, data_format: str = "run") -> tuple[System, list[Run]]:
    """Resolve the system and read the runs of ``data`` in ``data_format`` (see :data:`FORMATS`)."""
    from ..systems import get_system

    if data_format not in FORMATS:
        raise UnknownNameError(f"unknown data format {data_format!r}; choose from {sorted(FORMATS)}")
    reader, default_system = FORMATS[data_format]
    system = get_system(system_name or default_system or "cartpole")
    if reader is None:
        return system, load_runs(system, data)
    runs = reader(Path(data))
    if not runs:
        raise DataError(f"{data}: no {data_format} recordings found")
    if any(r.system != system.name for r in runs):
        raise DataError(f"{data}: {data_format} recordings belong to system {runs[0].system!r}, "
                        f"not {system.name!r}")
    return system, runs
