"""The text of a generated folder: the C kit's files, and the templates filled for a build.

The kit (``learnest_codegen/ckit/learnest_*.h``) is copied as it is into every generated folder,
so the folder builds without Python, and the kit's own tests build it alone. Its
``learnest_status.h`` is the rendering of the one status table (``runtime/status.py``) and the
option ranges (``runtime/limits.py``) through ``templates/learnest_status.h.in``: a test checks
that it still is (:func:`write_status_header` renders it again after a change to either). The templates in
``templates/`` (``*.in``: C, make and CMake text with ``${name}`` fields, filled with
``string.Template``) give the public header, the glue naming the generated model, and the build
fragments.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from string import Template
from typing import Mapping

from ..runtime.limits import c_macros
from ..runtime.status import STATUSES

TEMPLATES = Path(__file__).resolve().parent / "templates"
KIT = Path(__file__).resolve().parents[1] / "ckit"
STATUS_HEADER = "learnest_status.h"


def render(name: str, values: Mapping[str, object], directory: Path = TEMPLATES) -> str:
    """Template ``directory/<name>`` with ``values`` substituted (every field must be given)."""
    return Template((directory / name).read_text()).substitute(values)


def write(out: Path, template: str, filename: str, values: Mapping[str, object]) -> Path:
    """Render ``template`` into ``out/filename`` and return the path."""
    path = Path(out) / filename
    path.write_text(render(template, values))
    return path


def status_header_text() -> str:
    """``learnest_status.h``: the status codes and the option ranges as C."""
    lines = []
    for s in STATUSES:
        lines.append(f"/* {s.meaning}.\n * Recovery: {s.recovery}. */")
        lines.append(f"#define LEARNEST_{s.name} ({s.code})")
    return render(f"{STATUS_HEADER}.in", {"codes": "\n".join(lines), "limits": c_macros()})


def write_status_header() -> Path:
    """Render the kit's ``learnest_status.h`` from the status table and the option ranges."""
    path = KIT / STATUS_HEADER
    path.write_text(status_header_text())
    return path


def kit_files() -> tuple[Path, ...]:
    """The kit's headers (every ``learnest_*.h`` of ``ckit/``, ``learnest_status.h`` too),
    sorted by name."""
    return tuple(sorted(KIT.glob("learnest_*.h")))


def write_kit(out: Path) -> tuple[Path, ...]:
    """Copy the kit into ``out``; returns the paths."""
    paths = []
    for source in kit_files():
        paths.append(Path(out) / source.name)
        shutil.copyfile(source, paths[-1])
    return tuple(paths)
