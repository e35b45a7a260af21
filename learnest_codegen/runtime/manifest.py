"""``manifest.json``: what a compiled estimator directory holds and was built from.

:class:`GeneratedEstimator` is the one result type of every generator and the manifest itself:
its fields are the file's keys. The runtime checks a manifest against what the caller expects
before loading a library, so a library built for another system, model kind or dimension fails
with a clear message instead of producing garbage. The manifest also records the library's size
and SHA-256, checked before the library is opened (a file cut short by an interrupted copy or a
full disk would otherwise kill the process inside ``dlopen`` with SIGBUS), and the fingerprint
compiled into the library, checked once it is loaded (``runtime/base.py``). This module must
not import torch.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from ..errors import ModelMismatchError
from .status import STATUS_NAMES

MANIFEST = "manifest.json"
# 2: every estimator gates its measurements (settings "gate", C status 1 MEASUREMENT_REJECTED,
# <prefix>_set_gate / _get_rejected); a version-1 library has no gate and must be recompiled.
# 3: the C kit's API (covariances in every init, per-output validity in step, predict,
# set_noise, a fingerprint in every library, <prefix>.h for every estimator).
FORMAT_VERSION = 3
_VERSION_NEWS = {2: "version 2 added the innovation gate to every estimator",
                 3: "version 3 gave every estimator the C kit's API: covariances in init, "
                    "missing outputs, predict, set_noise and a fingerprint"}


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
        news = "; ".join(v for k, v in _VERSION_NEWS.items() if k > (manifest.get("format_version") or 0))
        raise ModelMismatchError(f"{path}: format_version {manifest.get('format_version')!r}, "
                                 f"this runtime reads {FORMAT_VERSION} ({news}); recompile the "
                                 "estimator")
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
        raise ModelMismatchError(f"{where}: compiled estimator does not match: " + "; ".join(wrong)
                                 + "; use a folder compiled for these, recompile this one with them "
                                 "(learnest-compile), or drop the option that asks for them")


@dataclass(frozen=True)
class GeneratedEstimator:
    """A generated and compiled estimator folder: what every generator returns, and its
    ``manifest.json`` (each field but ``directory`` and ``extra`` is a key of the file;
    ``extra`` holds an estimator's own keys, written at the top level too).

    Attributes
    ----------
    directory : the folder.
    estimator : its name in the estimator table (``compilation.ESTIMATORS``).
    prefix : the prefix of every exported C symbol and file (``<prefix>.h``, ``<prefix>.c``).
    system, model_kind, system_fingerprint, model_hash : what the model is.
    nx, nu, ny, dt, horizon : sizes (horizon None for the UKF) and sampling period [s].
    precision : ``"float64"`` or ``"float32"``, the C real type.
    settings, settings_hash, solver : the estimator's settings (and the embedded MHE's solver).
    fingerprint : the string ``<prefix>_fingerprint()`` of the library returns.
    source_hash, code_hash : SHA-256 of the sources the fingerprint names, and of every file.
    sources, headers : the folder's C sources and headers (file names).
    library : the shared library's file name; library_bytes, library_sha256 its digest.
    generate_seconds, build_seconds, build_reused : timing, and whether the library was reused.
    code_bytes : size of the sources and headers.
    """

    directory: Path
    estimator: str
    prefix: str
    system: str
    model_kind: str
    system_fingerprint: str
    model_hash: str
    nx: int
    nu: int
    ny: int
    dt: float
    horizon: int | None
    precision: str
    settings: dict
    settings_hash: str
    solver: dict | None
    fingerprint: str
    source_hash: str
    code_hash: str
    sources: tuple[str, ...]
    headers: tuple[str, ...]
    library: str
    casadi_version: str
    generate_seconds: float
    build_seconds: float
    build_reused: bool
    code_bytes: int
    library_bytes: int | None = None
    library_sha256: str | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def reused(self) -> bool:
        """True when the library was up to date and not recompiled."""
        return self.build_reused

    @property
    def manifest_path(self) -> Path:
        return Path(self.directory) / MANIFEST

    @property
    def library_path(self) -> Path:
        return Path(self.directory) / self.library

    @property
    def header_path(self) -> Path:
        """``<prefix>.h``, the C API of the estimator."""
        return Path(self.directory) / f"{self.prefix}.h"

    @property
    def source_paths(self) -> tuple[Path, ...]:
        return tuple(Path(self.directory) / name for name in self.sources)

    def to_json(self) -> dict:
        """The manifest's content (``write_manifest`` adds the format version and digest)."""
        data = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if f.name not in ("directory", "extra")}
        data.update(sources=list(self.sources), headers=list(self.headers),
                    matrix_layout="row-major", tuning="covariances",
                    status_codes={str(k): v for k, v in STATUS_NAMES.items()})
        return {**dict(self.extra), **data}

    def write(self) -> "GeneratedEstimator":
        """Write ``manifest.json``; returns the result with the library's size and SHA-256."""
        write_manifest(self.directory, self.to_json())
        return GeneratedEstimator.read(self.directory)

    @classmethod
    def read(cls, directory: Path) -> "GeneratedEstimator":
        """The folder's manifest (checked as :func:`read_manifest` checks it)."""
        data = read_manifest(directory)
        names = {f.name for f in dataclasses.fields(cls)} - {"directory", "extra"}
        derived = {"format_version", "matrix_layout", "tuning", "status_codes"}
        missing = sorted(n for n in names if n not in data
                         and cls.__dataclass_fields__[n].default is dataclasses.MISSING)
        if missing:
            raise ModelMismatchError(f"{Path(directory) / MANIFEST}: missing {missing}; recompile "
                                     "the estimator")
        known = {k: data[k] for k in names if k in data}
        known["sources"], known["headers"] = tuple(known["sources"]), tuple(known["headers"])
        extra = {k: v for k, v in data.items() if k not in names and k not in derived}
        return cls(directory=Path(directory), **known, extra=extra)
