"""The figures the README and docs quote: where they are stored, with what conditions, and how a
page shows them.

Every figure lives in ``docs/figures/<name>.json``, written by one benchmark of
``scripts/bench.py`` (``python scripts/bench.py <name>``) and never by hand. A file holds::

    {"schema": 1, "name": ..., "command": "python scripts/bench.py <name> ...",
     "conditions": {"model": ..., "run": ..., "commit": ..., "date": ..., "machine": {...},
                    "versions": {...}, ...},
     "figures": {...}}

``conditions`` says what was measured (the model, the run) and how (the commit, the machine,
its load before and after, the package versions). A time is a raw figure or a ratio to a
reference measured in the same minutes, never a figure rescaled by an estimated machine speed.

A page shows a figure through a marked block, filled in by ``python scripts/render_docs.py``::

    <!-- figure: demo.table -->
    | method | MSE | ... |
    <!-- /figure -->

or inline, ``<!-- value: demo figures.knode_ukf.vs_nominal .0f -->276<!-- /value -->``. A block
``<bench>.<view>`` is the text returned by ``render_<view>(data)`` of ``scripts/bench_<bench>.py``;
an inline value is a path into the JSON and a format. ``tests/test_figures.py`` re-renders every
page and fails on any difference, so a quoted figure cannot drift from its JSON.
"""

from __future__ import annotations

import datetime
import importlib
import importlib.util
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
FIGURES = ROOT / "docs" / "figures"
SCHEMA = 1
#: The pages that quote figures: the README and every page under docs/.
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]

BLOCK = re.compile(r"(<!-- figure: (?P<name>[\w.]+) -->\n)(?P<body>.*?)(<!-- /figure -->)", re.S)
VALUE = re.compile(r"(<!-- value: (?P<bench>\w+) (?P<path>[\w.\[\]-]+) (?P<fmt>\S+) -->)(?P<body>.*?)"
                   r"(<!-- /value -->)")

def load_file(path, name: str):
    """The Python file ``path`` imported as module ``name`` (an example or a script outside any
    package); registered in ``sys.modules`` first, because dataclasses look their module up by name."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module



def _packages() -> dict[str, str]:
    import importlib.metadata as md
    out = {}
    for name in ("torch", "casadi", "l4casadi", "numpy", "scipy", "filterpy"):
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            pass
    return out


def _commit() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()
        # "+changes": the measured code differs from the commit; docs/ and README.md hold the
        # benchmarks' own outputs (figure JSONs, rendered pages), which do not change what is
        # measured
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".",
                                ":(exclude)docs", ":(exclude)README.md"], cwd=ROOT, capture_output=True,
                               text=True).stdout.strip()
        return head + ("+changes" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> dict:
    """The machine as a benchmark sees it now: CPU model, cores, the 1-minute load."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "load_1min": round(os.getloadavg()[0], 2),
            "python": platform.python_version(), "platform": platform.platform()}


def conditions(**what) -> dict:
    """The conditions of a measurement starting now: ``what`` (the model, the run, the settings)
    plus the commit, the date, the machine and the package versions. Call :func:`finish` on the
    result when the measurement ends, to record the load it ended with."""
    return {**what, "commit": _commit(), "date": datetime.datetime.now(datetime.timezone.utc)
            .strftime("%Y-%m-%d %H:%M UTC"), "machine": machine(), "versions": _packages()}


def finish(cond: dict) -> dict:
    cond["machine"]["load_1min_at_end"] = round(os.getloadavg()[0], 2)
    return cond


def write(name: str, figures: dict, cond: dict, command: str) -> Path:
    """Write ``docs/figures/<name>.json``."""
    FIGURES.mkdir(parents=True, exist_ok=True)
    path = FIGURES / f"{name}.json"
    data = {"schema": SCHEMA, "name": name, "command": command, "conditions": cond, "figures": figures}
    path.write_text(json.dumps(data, indent=1, sort_keys=False) + "\n")
    return path


def load(name: str) -> dict:
    path = FIGURES / f"{name}.json"
    if not path.exists():
        raise FileNotFoundError(f"{path.relative_to(ROOT)} does not exist: "
                                f"run python scripts/bench.py {name}")
    return json.loads(path.read_text())


def lookup(data: dict, path: str):
    """``figures.rows[KNODE-UKF].mse``: dotted keys; ``[x]`` picks a list item whose first
    string field equals ``x``, or an index."""
    node = data
    for part in re.findall(r"[^.\[\]]+|\[[^\]]+\]", path):
        if part.startswith("["):
            key = part[1:-1]
            if isinstance(node, list):
                node = node[int(key)] if key.lstrip("-").isdigit() else next(
                    item for item in node if key in [v for v in item.values() if isinstance(v, str)])
            else:
                node = node[key]
        else:
            node = node[part]
    return node


def bench_module(bench: str):
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        return importlib.import_module(f"bench_{bench}")
    finally:
        sys.path.pop(0)


def render_block(name: str) -> str:
    bench, view = name.split(".", 1)
    text = getattr(bench_module(bench), f"render_{view}")(load(bench))
    return text if text.endswith("\n") else text + "\n"


def render_page(text: str) -> str:
    """``text`` with every figure block and inline value filled from its JSON."""
    text = BLOCK.sub(lambda m: m.group(1) + render_block(m.group("name")) + m.group(4), text)
    return VALUE.sub(lambda m: m.group(1) + format(lookup(load(m.group("bench")), m.group("path")),
                                                   m.group("fmt")) + m.group(6), text)
