"""Where a model's system comes from, so that a model (and its compiled estimators) find it again.

A trained model records its system under ``model.json``'s ``system_source`` key: a built-in
system by name (with its prior parameters when they were fitted to recordings), a system file
by its absolute path and the SHA-256 of its content. Loading the
model without naming a system takes the built-in, or loads the file after checking that it is
the same file as at training; an edited, moved or unrecorded file is refused in one line that
says what to do. The same record is written beside each compiled estimator
(``system_source.json``) for :func:`~learnest_codegen.pipeline.load_estimator`.

Imports neither torch nor CasADi.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import json
from pathlib import Path
from typing import Any, Mapping

from ..errors import ModelMismatchError, SystemFileError
from ..systems import SYSTEMS, System, get_system

#: the key of a model's ``model.json`` and the file beside a compiled estimator
KEY, SIDECAR = "system_source", "system_source.json"
PACKAGE = Path(__file__).resolve().parents[1]


def model_meta(directory: str | Path) -> dict[str, Any]:
    """A model directory's ``model.json``, checked: one clear error when it is missing, damaged
    or no model description (no torch needed)."""
    meta_path = Path(directory) / "model.json"
    if not meta_path.is_file() or not (Path(directory) / "weights.pt").is_file():
        raise FileNotFoundError(f"{directory} is not a model directory (needs model.json and weights.pt)")
    try:
        meta = json.loads(meta_path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ModelMismatchError(f"{meta_path} is not valid JSON ({exc}); the model directory is "
                                 "damaged: retrain or restore it") from exc
    if not isinstance(meta, dict) or "network" not in meta:
        raise ModelMismatchError(f"{meta_path} holds no model description; retrain or restore it")
    return meta


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def system_source(system: System) -> dict[str, Any]:
    """The record of where ``system`` comes from.

    ``{"name", "fingerprint", "builtin": True}`` for the registered built-in of that name, with
    ``"params"`` when it is that built-in with other prior parameters (a grey-box prior fitted
    to recordings);
    ``{"name", "fingerprint", "file", "sha256"}`` for a system that a Python file defines as
    ``SYSTEM`` (the file that defines its dynamics, measurement or excitation, loaded again and
    found to compute the same, :meth:`~learnest_codegen.systems.System.fingerprint`);
    otherwise ``{"name", "fingerprint"}`` (a system built in code: whoever loads the model
    passes it).
    """
    fingerprint = system.fingerprint()
    record: dict[str, Any] = {"name": system.name, "fingerprint": fingerprint}
    builtin = SYSTEMS.get(system.name)
    if builtin is system or (builtin is not None and _same(builtin, fingerprint)):
        return {**record, "builtin": True}
    params = {k: float(v) for k, v in system.params.items()}
    if builtin is not None and set(params) == set(builtin.params) and params != dict(builtin.params) \
            and _same(dataclasses.replace(builtin, params=params), fingerprint):
        return {**record, "builtin": True, "params": params}  # a prior fitted to recordings
    for path in _defining_files(system):
        try:
            candidate = get_system(str(path))
        except Exception:  # noqa: BLE001 - not a system file (a helper module): try the next
            continue
        if candidate.name == system.name and _same(candidate, fingerprint):
            return {**record, "file": str(path), "sha256": file_sha256(path)}
    return record


def _same(system: System, fingerprint: str) -> bool:
    try:
        return system.fingerprint() == fingerprint
    except Exception:  # noqa: BLE001 - a system that cannot even be fingerprinted is not this one
        return False


def _defining_files(system: System) -> list[Path]:
    files = []
    for fn in (system.dynamics, system.measurement, system.excitation, system.true_dynamics):
        try:
            path = Path(inspect.getsourcefile(fn) or "").resolve()
        except TypeError:  # a builtin or a C function
            continue
        if path.suffix == ".py" and path.is_file() and PACKAGE not in path.parents and path not in files:
            files.append(path)
    return files


def system_from_source(record: Mapping[str, Any] | None, name: str | None, where: str) -> System:
    """The system a record names, checked; ``where`` names the model or folder in messages.

    ``record`` ``None`` (a model saved before systems were recorded) loads the built-in
    ``name``.
    """
    if not record:
        if name in SYSTEMS:
            return SYSTEMS[name]
        raise ModelMismatchError(f"{where} records no system file for system {name!r}; pass the "
                                 "system (--system FILE, or system=)")
    if record.get("builtin"):
        system = get_system(record["name"])
        if record.get("params"):
            unknown = sorted(set(record["params"]) - set(system.params))
            if unknown:
                raise ModelMismatchError(f"{where} sets prior parameters {unknown} that the built-in "
                                         f"system {system.name!r} no longer has; retrain or recompile")
            system = dataclasses.replace(system, params={k: float(v) for k, v in record["params"].items()})
        return system
    path = record.get("file")
    if path is None:
        raise ModelMismatchError(f"{where} was trained for system {record['name']!r}, which was built in "
                                 "code rather than loaded from a file; pass the system (--system NAME or "
                                 "FILE, or system=)")
    if not Path(path).is_file():
        raise SystemFileError(f"{where} was trained for the system file {path}, which no longer exists; "
                              "pass --system FILE (or system=) where it is now")
    now = file_sha256(path)
    if now != record.get("sha256"):
        raise ModelMismatchError(f"system file {path} changed since {where} was trained on it (sha256 "
                                 f"{str(record.get('sha256'))[:12]}... then, {now[:12]}... now); retrain, or "
                                 "pass --system (system=) to use it as it is")
    system = get_system(path)
    if system.name != record["name"]:
        raise ModelMismatchError(f"system file {path} now defines system {system.name!r}, but {where} "
                                 f"was trained for {record['name']!r}; retrain or pass --system")
    return system


def write_sidecar(directory: str | Path, record: Mapping[str, Any]) -> Path:
    """Write ``record`` beside a compiled estimator (``system_source.json``)."""
    path = Path(directory) / SIDECAR
    path.write_text(json.dumps(dict(record), indent=2, sort_keys=True))
    return path


def read_sidecar(directory: str | Path) -> dict[str, Any] | None:
    """The record beside a compiled estimator, or ``None``."""
    path = Path(directory) / SIDECAR
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ModelMismatchError(f"{path} is not valid JSON ({exc}); recompile the estimator") from exc
