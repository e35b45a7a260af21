"""Where results are written: never over an input, never over earlier results unasked, whole or
not at all.

:func:`claim_output` is called before any work starts, so a refused ``--out`` costs nothing;
:func:`atomic_file` and :func:`atomic_dir` write under a temporary name beside the target and
rename it into place only when the writing succeeded, so an interrupted command (Ctrl-C, a full
disk) leaves the old file or nothing, never half a file.
"""

from __future__ import annotations

import os
import shutil
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from .errors import OutputError


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def claim_output(out: str | os.PathLike, *, inputs: tuple = (), force: bool = False,
                 kind: str = "file") -> Path:
    """Check that ``out`` may be written, before any work is done; returns it as a Path.

    Parameters
    ----------
    out : the file (``kind="file"``) or folder (``kind="dir"``) to be written.
    inputs : paths the command reads (``None`` entries are ignored). ``out`` may be none of them,
        nor a folder holding one of them (``--force`` does not lift this).
    force : allow replacing an existing regular file or a non-empty folder. A device, FIFO or
        socket, or a symbolic link, is never replaced: renaming over it would destroy the node
        or the link (as root, ``/dev/null`` would become a regular file).

    Raises
    ------
    OutputError : with one line saying which path, why, and what to do.
    """
    out = Path(out)
    for source in (Path(p) for p in inputs if p is not None):
        if _same(out, source) or (kind == "dir" and out.is_dir() and _inside(source, out)):
            raise OutputError(f"refusing to write {out}: it {'is' if _same(out, source) else 'holds'} "
                              f"the input {source}; choose another --out")
    special = _special(out)
    if special:
        raise OutputError(f"refusing to write {out}: it is {special}, not a regular file or folder "
                          "(--force replaces only those); give another --out (or the link's target)")
    if kind == "file" and out.is_dir():
        raise OutputError(f"{out} is a folder; --out needs a file name")
    if kind == "dir" and out.exists() and not out.is_dir():
        raise OutputError(f"{out} is a file; --out needs a folder")
    occupied = out.is_file() if kind == "file" else (out.is_dir() and any(out.iterdir()))
    if occupied and not force:
        raise OutputError(f"{out} exists{' and is not empty' if kind == 'dir' else ''}; "
                          "pass --force to replace it")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot create the folder of {out}: {exc.strerror or exc}") from exc
    if not os.access(out.parent, os.W_OK):
        raise OutputError(f"cannot write {out}: folder {out.parent} is not writable")
    return out


def _special(path: Path) -> str:
    """What ``path`` is when it exists and is neither a regular file nor a folder:
    ``"a character device"``, ``"a FIFO"``, ``"a symbolic link to ..."``; else ``""``.

    A link is refused too: renaming over it replaces the link, not what it points to (as root,
    ``--out /dev/stdout`` would turn the system's link into a regular file)."""
    try:
        mode = os.lstat(path).st_mode
    except OSError:  # absent
        return ""
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return ""
    if stat.S_ISLNK(mode):
        return f"a symbolic link to {os.readlink(path)}"
    for test, name in ((stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
                       (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "a special file"


def _inside(path: Path, folder: Path) -> bool:
    try:
        path.resolve().relative_to(folder.resolve())
        return True
    except ValueError:
        return False


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path``.

    On an exception the temporary file is removed and ``path`` is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 would make every result private
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


@contextmanager
def atomic_dir(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; on success it replaces ``path`` whole.

    An existing ``path`` is renamed aside first and removed only after the new folder is in
    place (callers check ``--force`` with :func:`claim_output` beforehand).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # "-" after the name, never ".": CasADi refuses to generate "<name>.c" into a folder whose
    # path contains "<name>.c", which ".<name>.c8x2...tmp" would (once in 37 random names)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}-", suffix=".tmp", dir=path.parent))
    os.chmod(tmp, 0o777 & ~_umask())
    try:
        yield tmp
        old = None
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}-", suffix=".old", dir=path.parent))
            os.replace(path, old / "previous")
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
