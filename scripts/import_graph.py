"""The package's import graph: check it flows one way, and draw it.

Every module of ``learnest_codegen`` belongs to a stage of the data flow (``STAGES``, most
specific prefix first); a module may import only from its own stage or earlier ones, and the
graph must have no cycles. Imports inside functions count as well (they are how heavy
dependencies stay lazy, not a way round the order); ``TYPE_CHECKING`` imports do not.

Usage::

    python scripts/import_graph.py                 # list violations and cycles (exit 1 if any)
    python scripts/import_graph.py --png graph.png # also draw the graph, stage by stage
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "learnest_codegen"

#: (module prefix, stage); the longest matching prefix decides. The order of the data flow.
STAGES = [
    ("errors", 0), ("outputs", 0), ("config", 0), ("integrators", 0),
    ("systems", 1),
    ("data", 2), ("simulation", 2), ("recordings", 2),
    ("observers", 3),
    ("learning", 4),
    ("export", 5), ("toolchain", 5),  # the compiler driver: codegen builds what it generates
    ("estimators", 6), ("runtime.manifest", 6), ("runtime.status", 6), ("runtime.limits", 6), ("codegen", 7),
    ("runtime", 8), ("compilation", 8),  # the registry of estimators: generate, reference, load
    ("evaluation", 9), ("plotting", 9), ("pipeline", 9),
    ("diagnosis", 10),
    ("experiments", 11),
    ("cli", 12),
    ("__init__", 13),  # the package's public API re-exports from every stage
]


def module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__" and len(parts) > 1:
        parts = parts[:-1]
    return ".".join(parts)


def stage(module: str) -> int:
    best = max((p for p, _ in STAGES if module == p or module.startswith(p + ".")), key=len, default=None)
    if best is None:
        raise KeyError(f"module {module!r} has no stage in scripts/import_graph.py STAGES")
    return dict(STAGES)[best]


def _resolve(importer: str, is_package: bool, node: ast.ImportFrom) -> list[str]:
    base = importer.split(".") if importer != "__init__" else []
    if not is_package:
        base = base[:-1]
    if node.level:
        base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
        prefix = ".".join(base + ([node.module] if node.module else []))
    elif node.module and node.module.startswith("learnest_codegen"):
        prefix = node.module.removeprefix("learnest_codegen").lstrip(".")
    else:
        return []
    if node.module is None or prefix == "":  # `from . import x` / `from .. import x`
        return [".".join(filter(None, [prefix, a.name])) for a in node.names]
    return [prefix]


def _type_checking_lines(tree: ast.AST) -> set[int]:
    lines = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                lines.update(range(child.lineno, (child.end_lineno or child.lineno) + 1))
    return lines


def graph() -> dict[str, set[str]]:
    """``{module: {imported modules of the package}}`` for every module of the package."""
    modules = {module_name(p): p for p in ROOT.rglob("*.py")}
    edges: dict[str, set[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text())
        skip = _type_checking_lines(tree)
        targets = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.lineno not in skip:
                for target in _resolve(name, path.name == "__init__.py", node):
                    while target and target not in modules:  # `from .x import f`: x is a module
                        target = target.rpartition(".")[0]
                    if target and target != name:
                        targets.add(target)
        edges[name] = targets
    return edges


def violations(edges: dict[str, set[str]]) -> list[str]:
    """Imports against the flow (a later stage imported by an earlier one)."""
    return sorted(f"{a} (stage {stage(a)}) imports {b} (stage {stage(b)})"
                  for a, targets in edges.items() for b in targets
                  if stage(b) > stage(a) and not b.startswith(a + "."))


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Every cycle found by depth-first search (each reported once, from its smallest member)."""
    found, seen = [], set()

    def visit(node, path, on_path):
        for nxt in sorted(edges.get(node, ())):
            if nxt in on_path:
                cycle = path[path.index(nxt):]
                key = tuple(sorted(cycle))
                if key not in seen:
                    seen.add(key)
                    found.append(cycle + [nxt])
            elif len(path) < 40:
                visit(nxt, path + [nxt], on_path | {nxt})

    for start in sorted(edges):
        visit(start, [start], {start})
    return found


def draw(edges: dict[str, set[str]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_stage: dict[int, list[str]] = {}
    for m in sorted(edges):
        by_stage.setdefault(stage(m), []).append(m)
    pos = {m: (i - (len(ms) - 1) / 2, -s) for s, ms in by_stage.items() for i, m in enumerate(ms)}
    fig, ax = plt.subplots(figsize=(22, 14))
    for a, targets in edges.items():
        for b in targets:
            (x0, y0), (x1, y1) = pos[a], pos[b]
            ax.annotate("", (x1, y1), (x0, y0), arrowprops={"arrowstyle": "->", "alpha": 0.25})
    for m, (x, y) in pos.items():
        ax.text(x, y, m, ha="center", va="center", fontsize=7,
                bbox={"boxstyle": "round", "fc": "white", "ec": "grey"})
    ax.set_axis_off()
    fig.savefig(path, dpi=110, bbox_inches="tight")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--png", type=Path, help="draw the graph to this file")
    args = parser.parse_args()
    edges = graph()
    bad, loops = violations(edges), cycles(edges)
    print(f"{len(edges)} modules, {sum(map(len, edges.values()))} imports")
    for line in bad:
        print("against the flow:", line)
    for loop in loops:
        print("cycle:", " -> ".join(loop))
    if args.png:
        draw(edges, args.png)
        print(f"wrote {args.png}")
    return 1 if bad or loops else 0


if __name__ == "__main__":
    sys.exit(main())
