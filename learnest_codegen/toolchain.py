"""Compiling generated C into shared libraries with gcc.

A failed compile raises :class:`BuildError` with the full command line and the compiler's
stderr. A build whose inputs (command line and source contents) are unchanged is skipped: the
hash of those inputs is kept in a ``.stamp`` file next to the library.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from .errors import BuildError

# The one set of flags of every generated estimator: the package's libraries, the folders'
# build fragments and docs/firmware.md use them alike (a firmware adds its target's flags).
# -O2 rather than -O3: measured on generated CasADi code, -O3 costs more compile time for no
# measurable run-time gain. -fno-math-errno lets libm calls inline; no -ffast-math, which would
# break bit-level parity with the reference implementations; -std=c99 and -ffp-contract=off
# keep compilers from fusing multiply-adds, so every build rounds every operation alike. The
# generated C is clean under these warnings (and -Werror, which the tests add).
CFLAGS = ("-O2", "-std=c99", "-fno-math-errno", "-ffp-contract=off", "-Wall", "-Wextra", "-pedantic")
# What a shared library adds to CFLAGS.
SHARED_CFLAGS = ("-fPIC",)


@dataclass(frozen=True)
class BuildResult:
    """What a build did: the library path, the command, seconds spent, and whether it was reused."""

    library: Path
    command: tuple[str, ...]
    seconds: float
    reused: bool


def casadi_dirs() -> tuple[Path, Path]:
    """``(include_dir, lib_dir)`` of the installed casadi wheel (Ipopt headers and libipopt.so)."""
    import casadi

    root = Path(casadi.__file__).resolve().parent
    return root / "include", root


def compiler() -> str:
    """The C compiler to use: ``$CC`` or gcc."""
    cc = os.environ.get("CC", "gcc")
    if shutil.which(cc) is None:
        raise BuildError(f"C compiler {cc!r} not found on PATH (set CC to choose another)")
    return cc


def build_shared(sources: Sequence[Path], library: Path, *, include_dirs: Sequence[Path] = (),
                 lib_dirs: Sequence[Path] = (), libs: Sequence[str] = (),
                 cflags: Sequence[str] = CFLAGS + SHARED_CFLAGS, force: bool = False) -> BuildResult:
    """Compile ``sources`` into the shared library ``library``; reuse it if nothing changed."""
    library = Path(library)
    command = [compiler(), *cflags, "-shared", *map(str, sources), "-o", str(library)]
    command += [f"-I{d}" for d in include_dirs]
    command += [f"-L{d}" for d in lib_dirs] + [f"-Wl,-rpath,{d}" for d in lib_dirs]
    command += [f"-l{lib}" for lib in libs] + ["-lm"]
    stamp = library.with_suffix(library.suffix + ".stamp")
    digest = _inputs_hash(command, sources)
    if not force and library.exists() and stamp.exists() and stamp.read_text() == digest:
        return BuildResult(library, tuple(command), 0.0, True)
    start = time.perf_counter()
    proc = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if proc.returncode != 0:
        raise BuildError(f"C compilation failed (exit {proc.returncode})\ncommand: {' '.join(command)}\n"
                         f"stderr:\n{proc.stderr.strip()}")
    stamp.write_text(digest)
    return BuildResult(library, tuple(command), seconds, False)


def _inputs_hash(command: Sequence[str], sources: Sequence[Path]) -> str:
    h = hashlib.sha256("\0".join(command).encode())
    for src in sources:
        h.update(Path(src).read_bytes())
    return h.hexdigest()


def file_hash(*paths: Path) -> str:
    """sha256 over the contents of ``paths``, in order."""
    h = hashlib.sha256()
    for p in paths:
        h.update(Path(p).read_bytes())
    return h.hexdigest()
