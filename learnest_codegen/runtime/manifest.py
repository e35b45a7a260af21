"""``manifest.json``: what a compiled estimator directory holds and was built from.

The runtime checks a manifest against what the caller expects before loading a library, so a
library built for another system, model kind or dimension fails with a clear message instead of
producing garbage. This module must not import torch.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

from ..errors import ModelMismatchError

MANIFEST = "manifest.json"
FORMAT_VERSION = 1


def write_manifest(directory: Path, content: Mapping[str, Any]) -> Path:
    """Write ``directory/manifest.json`` (adds ``format_version``)."""
    path = Path(directory) / MANIFEST
    path.write_text(json.dumps({"format_version": FORMAT_VERSION, **content}, indent=2, sort_keys=True))
    return path


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
                                 f"this runtime reads {FORMAT_VERSION}; recompile")
    return manifest


def check_manifest(manifest: Mapping[str, Any], expect: Mapping[str, Any] | None, where: str) -> None:
    """Raise :class:`ModelMismatchError` listing every key where ``manifest`` differs from ``expect``."""
    if not expect:
        return
    wrong = [f"{k}: library has {manifest.get(k)!r}, expected {v!r}"
             for k, v in expect.items() if manifest.get(k) != v]
    if wrong:
        raise ModelMismatchError(f"{where}: compiled estimator does not match: " + "; ".join(wrong))
