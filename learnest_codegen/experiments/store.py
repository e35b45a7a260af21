"""What the studies keep on disk: content hashes, atomic JSON files and the hash of the code.

A study's results are keyed by :func:`content_hash` of their configuration (a resumed study
skips what it has) and record :func:`code_hash`, the hash of the package's sources that made
them (a resumed study names results made by other code).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path
from typing import Any


def content_hash(obj: Any) -> str:
    """16 hex digits of the SHA-256 of ``obj`` as sorted JSON."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def write_json(path: Path, content: Any) -> None:
    """Write JSON atomically (an interrupted job never leaves a truncated results file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(content, indent=2, sort_keys=True, allow_nan=True))
    os.replace(tmp, path)


@functools.lru_cache(maxsize=1)
def code_hash() -> str:
    """Hash of the package's sources (paths and contents: the Python modules, the C kit and the
    generators' templates): which code made a result. A change to the C an estimator is built
    from changes its results as much as a change to the Python around it."""
    return tree_hash(Path(__file__).resolve().parents[1])


def tree_hash(root: Path) -> str:
    """16 hex digits of the SHA-256 of every file under ``root`` (relative paths and contents,
    in sorted order; byte-code caches left out)."""
    h = hashlib.sha256()
    for path in sorted(p for p in Path(root).rglob("*") if p.is_file() and "__pycache__" not in p.parts):
        h.update(path.relative_to(root).as_posix().encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()[:16]
