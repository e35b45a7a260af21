"""Readers of real recordings in foreign formats, each turning a log into the project's :class:`Run`.

One module per format (``nanobench`` for Crazyflie flights, ``dart`` for the RC car). The data
itself never lives in the project: :func:`data_root` finds it in ``$LEARNEST_DATA`` or in
``../shared/data`` next to the project (or the current directory), and callers may always pass
an explicit path instead.
"""

from __future__ import annotations

import os
from pathlib import Path

ENV_VAR = "LEARNEST_DATA"


def data_root(path: str | Path | None = None) -> Path | None:
    """The folder holding real recordings, or ``None`` when none is found.

    Order: ``path`` when given (it must exist), ``$LEARNEST_DATA``, then ``../shared/data``
    relative to the current directory and to the project root.
    """
    if path is not None:
        path = Path(path)
        if not path.is_dir():
            raise FileNotFoundError(f"data folder {path} does not exist")
        return path
    candidates = []
    if os.environ.get(ENV_VAR):
        candidates.append(Path(os.environ[ENV_VAR]))
    project = Path(__file__).resolve().parents[2]
    candidates += [Path.cwd() / ".." / "shared" / "data", project / ".." / "shared" / "data"]
    for candidate in candidates:
        if candidate.is_dir():
            return candidate.resolve()
    return None
