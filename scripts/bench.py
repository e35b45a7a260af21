"""The benchmark command: regenerates every figure the README and docs quote.

    python scripts/bench.py list                 # the benchmarks, their figures and rough cost
    python scripts/bench.py demo callgrind       # run these, write docs/figures/<name>.json
    python scripts/bench.py all                  # every benchmark, in the order of the list
    python scripts/bench.py table1 --jobs 2      # a benchmark's own options follow the names

A benchmark is a module ``scripts/bench_<name>.py`` that defines ``MINUTES`` (its rough cost on
2 idle cores), ``measure(args) -> (figures, conditions)`` and the ``render_<view>(data)``
functions its pages use; ``add_arguments(parser)`` adds its own options. After the runs, every
page is re-rendered from the JSON (``scripts/render_docs.py``). Run benchmarks that time
anything on an idle machine: each JSON records the load before and after.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import figures

SCRIPTS = Path(__file__).resolve().parent


def benches() -> dict[str, object]:
    """Every benchmark module (those that define ``MINUTES`` and ``measure``), in the order of
    their ``ORDER``."""
    found = {}
    for path in sorted(SCRIPTS.glob("bench_*.py")):
        module = figures.bench_module(path.stem.removeprefix("bench_"))
        if hasattr(module, "MINUTES") and hasattr(module, "measure"):
            found[path.stem.removeprefix("bench_")] = module
    return dict(sorted(found.items(), key=lambda kv: (getattr(kv[1], "ORDER", 50), kv[0])))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    table = benches()
    if not argv or argv[0] in ("list", "-h", "--help"):
        print(__doc__.strip().splitlines()[0] + "\n")
        for name, module in table.items():
            doc = (module.__doc__ or "").strip().splitlines()[0]
            print(f"  {name:<18} ~{module.MINUTES:>4} min  {doc}")
        return 0
    split = next((i for i, a in enumerate(argv) if a.startswith("-")), len(argv))
    names, rest = argv[:split], argv[split:]  # the benchmarks, then their options
    names = list(table) if names == ["all"] else names
    unknown = [n for n in names if n not in table]
    if unknown:
        print(f"unknown benchmark {unknown[0]!r}; choose from {', '.join(table)} or all", file=sys.stderr)
        return 2
    parsed, left = {}, None
    for name in names:  # every option must belong to a named benchmark, before hours of work
        parser = argparse.ArgumentParser(prog=f"bench.py {name}")
        if hasattr(table[name], "add_arguments"):
            table[name].add_arguments(parser)
        parsed[name], extra = parser.parse_known_args(rest)
        left = set(extra) if left is None else left & set(extra)
    stray = [a for a in rest if a in (left or ()) and a.startswith("-")]
    if stray:
        print(f"{stray[0]}: not an option of {', '.join(names)} (python scripts/bench.py {names[0]} --help)",
              file=sys.stderr)
        return 2
    for name in names:
        module, args = table[name], parsed[name]
        print(f"==> {name} (about {module.MINUTES} min)", flush=True)
        start = time.perf_counter()
        figs, cond = module.measure(args)
        cond = figures.finish(cond)
        cond["wall_seconds"] = round(time.perf_counter() - start, 1)
        command = "python scripts/bench.py " + " ".join(shlex.quote(a) for a in [name, *rest])
        path = figures.write(name, figs, cond, command)
        print(f"    wrote {path.relative_to(figures.ROOT)} in {cond['wall_seconds']:.0f} s", flush=True)
    import render_docs
    render_docs.main([])
    return 0


if __name__ == "__main__":
    sys.exit(main())
