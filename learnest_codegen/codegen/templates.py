"""The C text of the generated APIs: template files in ``templates/`` filled with ``string.Template``.

Each ``*.h.in`` / ``*.c.in`` is C with ``${name}`` fields (C has no ``$``), so the C API
reads and diffs as C, not as Python strings.
"""

from __future__ import annotations

from pathlib import Path
from string import Template
from typing import Mapping

from ..runtime.status import STATUSES

TEMPLATES = Path(__file__).resolve().parent / "templates"
STATUS_HEADER = "learnest_status.h"
GATE_HEADER = "learnest_gate.h"


def render(name: str, values: Mapping[str, object]) -> str:
    """Template ``templates/<name>`` with ``values`` substituted (every field must be given)."""
    return Template((TEMPLATES / name).read_text()).substitute(values)


def write(out: Path, template: str, filename: str, values: Mapping[str, object]) -> Path:
    """Render ``template`` into ``out/filename`` and return the path."""
    path = Path(out) / filename
    path.write_text(render(template, values))
    return path


def write_status_header(out: Path) -> Path:
    """``out/learnest_status.h``: the shared status codes (``runtime/status.py``) as C."""
    lines = []
    for s in STATUSES:
        lines.append(f"/* {s.meaning}.\n * Recovery: {s.recovery}. */")
        lines.append(f"#define LEARNEST_{s.name} ({s.code})")
    return write(out, f"{STATUS_HEADER}.in", STATUS_HEADER, {"codes": "\n".join(lines)})


def gate_header_digest() -> str:
    """SHA-256 of ``learnest_gate.h``: the sources that include it quote it, so a change of the
    header changes them and the toolchain (which hashes the .c files) rebuilds."""
    import hashlib

    return hashlib.sha256((TEMPLATES / f"{GATE_HEADER}.in").read_bytes()).hexdigest()


def write_gate_header(out: Path) -> Path:
    """``out/learnest_gate.h``: the innovation gate's C, shared by every estimator."""
    return write(out, f"{GATE_HEADER}.in", GATE_HEADER, {})
