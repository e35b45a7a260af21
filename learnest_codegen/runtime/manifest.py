"""``manifest.json``: what a compiled estimator directory holds and was built from.

The runtime checks a manifest against what the caller expects before loading a library, so a
library built for another system, model kind or dimension fails with a clear message instead of
producing garbage. The manifest also records the library's size and SHA-256, checked before the
library is opened: a file cut short by an interrupted copy or a full disk would otherwise kill
the process inside ``dlopen`` (SIGBUS) with no message. This module must not import torch.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Mapping

from ..errors import ModelMismatchError

MANIFEST = "manifest.json"
# 2: every estimator gates its measurements (settings "gate", C status 1 MEASUREMENT_REJECTED,
# <prefix>_set_gate / _get_rejected); a version-1 library has no gate and must be recompiled.
FORMAT_VERSION = 2


def settings_hash(settings: Mapping[str, Any]) -> str:
    """SHA-256 of the settings' canonical JSON (sorted keys), as recorded in manifests."""
    text = json.dumps(settings, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def library_digest(path: Path) -> dict:
    """``{"library_bytes", "library_sha256"}`` of a built library file."""
    data = Path(path).read_bytes()
    return {"library_bytes": len(data), "library_sha256": hashlib.sha256(data).hexdigest()}


def write_manifest(directory: Path, content: Mapping[str, Any]) -> Path:
    """Write ``directory/manifest.json`` (adds ``format_version`` and, when ``content`` names a
    ``library``, its size and SHA-256).

    The library must be the file the toolchain built: its build stamp (``<library>.stamp``,
    written by :func:`~learnest_codegen.toolchain.build_shared`) records the size and SHA-256
    of what the compiler produced, and a library that differs from it (cut short, altered,
    swapped for another build) raises :class:`ModelMismatchError` instead of being described.
    """
    directory = Path(directory)
    content = dict(content)
    library = directory / str(content.get("library", ""))
    if "library" in content and library.is_file():
        digest = library_digest(library)
        built = _built_digest(library)
        if built != digest:
            raise ModelMismatchError(f"refusing to write {directory / MANIFEST}: {library} is not the "
                                     "library the toolchain built (no build stamp, or its size or "
                                     "SHA-256 differs from the stamp's); rebuild it")
        content.update(digest)
    path = directory / MANIFEST
    path.write_text(json.dumps({"format_version": FORMAT_VERSION, **content}, indent=2, sort_keys=True))
    return path


def _built_digest(library: Path) -> dict | None:
    """Size and SHA-256 the build stamp beside ``library`` recorded, or None without one."""
    try:
        stamp = json.loads(library.with_suffix(library.suffix + ".stamp").read_text())
        return {k: stamp[k] for k in ("library_bytes", "library_sha256")}
    except (OSError, ValueError, KeyError, TypeError):
        return None


def verify_library(directory: Path, manifest: Mapping[str, Any]) -> Path:
    """The library file the manifest names, after checking its size and SHA-256 against it.

    Raises :class:`ModelMismatchError` (before anything opens the file) when it is missing,
    shorter or longer than built, or altered.
    """
    library = Path(directory) / str(manifest.get("library", ""))
    if not library.is_file():
        raise FileNotFoundError(f"compiled library {library} does not exist; regenerate the folder")
    expected_bytes = manifest.get("library_bytes")
    if expected_bytes is None:  # a folder built before the manifest recorded the digest
        return library
    size = library.stat().st_size
    if size != expected_bytes:
        raise ModelMismatchError(f"{library} has {size} bytes, but {expected_bytes} were built "
                                 "(cut short by an interrupted copy or a full disk?); recompile it")
    if library_digest(library)["library_sha256"] != manifest.get("library_sha256"):
        raise ModelMismatchError(f"{library} is not the library that was built here (its SHA-256 "
                                 "differs from the manifest's); recompile it")
    return library


def read_manifest(directory: Path) -> dict:
    """Read ``directory/manifest.json`` with a clear error when it is missing or malformed."""
    path = Path(directory) / MANIFEST
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: is {directory} a compiled estimator directory?")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ModelMismatchError(f"{path} is not valid JSON: {exc}") from exc
    if manifest.get("format_version") != FORMAT_VERSION:
        raise ModelMismatchError(f"{path}: format_version {manifest.get('format_version')!r}, "
                                 f"this runtime reads {FORMAT_VERSION} (version 2 added the "
                                 "innovation gate to every estimator); recompile the estimator")
    if "settings" in manifest and "settings_hash" in manifest \
            and settings_hash(manifest["settings"]) != manifest["settings_hash"]:
        raise ModelMismatchError(f"{path}: its settings were edited after the library was built "
                                 "(settings_hash differs); recompile the estimator")
    if "library" in manifest:
        verify_library(directory, manifest)
    return manifest


def check_manifest(manifest: Mapping[str, Any], expect: Mapping[str, Any] | None, where: str) -> None:
    """Raise :class:`ModelMismatchError` listing every key where ``manifest`` differs from ``expect``."""
    if not expect:
        return
    wrong = [f"{k}: library has {manifest[k]!r}, expected {v!r}" if k in manifest
             else f"{k}: not recorded (built by an older version; recompile)"
             for k, v in expect.items() if manifest.get(k) != v]
    if wrong:
        raise ModelMismatchError(f"{where}: compiled estimator does not match: " + "; ".join(wrong))
