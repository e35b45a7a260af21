"""Compiling generated C into shared libraries with gcc.

A failed compile raises :class:`BuildError` with the full command line and the compiler's
stderr. A build whose inputs (command line and source contents) are unchanged, and whose
library is still the file that was built, is skipped: the ``.stamp`` file next to the library
records the inputs' hash and the library's size and SHA-256 (JSON). A library that was cut
short, altered or swapped for another build is rebuilt, never reused: the manifest written
after a build describes the file the build made (``runtime/manifest.py`` checks the stamp).
The compiler writes a temporary file that is renamed over the library, so a library that a
process has mapped is replaced, not rewritten under it.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from .errors import BuildError

# The one set of flags of every generated estimator: the package's libraries, the folders'
# build fragments and docs/guide/firmware.md use them alike (a firmware adds its target's flags).
# -O2 rather than -O3: measured on generated CasADi code, -O3 costs more compile time for no
# measurable run-time gain. -fno-math-errno lets libm calls inline; no -ffast-math, which would
# break bit-level parity with the reference implementations; -std=c99 and -ffp-contract=off
# keep compilers from fusing multiply-adds, so every build rounds every operation alike. The
# generated C is clean under these warnings (and -Werror, which the tests add). -Wno-psabi:
# GCC notes, on x86-64 without AVX, that the ABI of passing 32-byte vectors changed in GCC 4.6;
# the lane-parallel model copies (learnest_simd.h) pass them only between inlined routines, and
# the note cannot be silenced from the source (GCC ignores the diagnostic pragma for it). GCC,
# Clang and arm-none-eabi-gcc all accept the flag.
CFLAGS = ("-O2", "-std=c99", "-fno-math-errno", "-ffp-contract=off", "-Wall", "-Wextra", "-Wno-psabi",
          "-pedantic")
# What a shared library adds to CFLAGS.
SHARED_CFLAGS = ("-fPIC",)


@dataclass(frozen=True)
class BuildResult:
    """What a build did: the library path, the command, seconds spent, whether it was reused,
    and the library's size and SHA-256 (as recorded in its stamp)."""

    library: Path
    command: tuple[str, ...]
    seconds: float
    reused: bool
    library_bytes: int = 0
    library_sha256: str = ""


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


def stamp_path(library: Path) -> Path:
    """The build stamp beside ``library`` (``lib<prefix>.so.stamp``)."""
    library = Path(library)
    return library.with_suffix(library.suffix + ".stamp")


def build_shared(sources: Sequence[Path], library: Path, *, include_dirs: Sequence[Path] = (),
                 lib_dirs: Sequence[Path] = (), libs: Sequence[str] = (),
                 cflags: Sequence[str] = CFLAGS + SHARED_CFLAGS, force: bool = False) -> BuildResult:
    """Compile ``sources`` into the shared library ``library``; reuse it if nothing changed.

    Reused only when the stamp's inputs hash equals this build's and the library on disk still
    has the size and SHA-256 the stamp recorded when it was built; otherwise (or with
    ``force``) it is rebuilt.
    """
    library = Path(library)
    flags = [f"-I{d}" for d in include_dirs]
    flags += [f"-L{d}" for d in lib_dirs] + [f"-Wl,-rpath,{d}" for d in lib_dirs]
    flags += [f"-l{lib}" for lib in libs] + ["-lm"]
    head = [compiler(), *cflags, "-shared", *map(str, sources), "-o"]
    command = [*head, str(library), *flags]
    stamp = stamp_path(library)
    # the folder's own path is left out, so a folder built under a temporary name and renamed
    # into place (compilation.compile_estimators) still matches its stamp
    folder = str(library.parent)
    inputs = _inputs_hash([part.replace(folder, "<folder>") for part in command], sources)
    recorded = _read_stamp(stamp)
    if not force and recorded.get("inputs") == inputs and library.is_file():
        digest = library_digest(library)
        if digest == {k: recorded.get(k) for k in digest}:
            return BuildResult(library, tuple(command), 0.0, True, **digest)
    fd, tmp = tempfile.mkstemp(prefix=f".{library.name}.", suffix=".tmp", dir=library.parent)
    os.close(fd)
    os.unlink(tmp)  # a unique name; the linker makes the file with the usual permissions
    try:
        start = time.perf_counter()
        proc = subprocess.run([*head, tmp, *flags], capture_output=True, text=True)
        seconds = time.perf_counter() - start
        if proc.returncode != 0:
            raise BuildError(f"C compilation failed (exit {proc.returncode})\ncommand: "
                             f"{' '.join(command)}\nstderr:\n{proc.stderr.strip()}")
        digest = library_digest(Path(tmp))
        stamp.unlink(missing_ok=True)  # no stamp may vouch for a half-replaced library
        os.replace(tmp, library)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    _write_stamp(stamp, {"inputs": inputs, **digest})
    return BuildResult(library, tuple(command), seconds, False, **digest)


def library_digest(path: Path) -> dict:
    """``{"library_bytes", "library_sha256"}`` of a library file (as manifests record them)."""
    data = Path(path).read_bytes()
    return {"library_bytes": len(data), "library_sha256": hashlib.sha256(data).hexdigest()}


def _read_stamp(stamp: Path) -> dict:
    try:
        data = json.loads(stamp.read_text())
    except (OSError, ValueError):  # none, or an older plain-hash stamp: rebuild
        return {}
    return data if isinstance(data, dict) else {}


def _write_stamp(stamp: Path, content: dict) -> None:
    tmp = stamp.with_name(f".{stamp.name}.tmp")
    tmp.write_text(json.dumps(content, sort_keys=True))
    os.replace(tmp, stamp)


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
