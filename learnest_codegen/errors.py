"""One error hierarchy for the package.

Every error subclasses :class:`LearnestError` and the builtin it naturally is, so callers can
catch either ``LearnestError`` or e.g. ``ValueError``. Messages say where, what was expected and
what was got.
"""

from __future__ import annotations


class LearnestError(Exception):
    """Base class of every error raised on purpose by learnest_codegen."""


class ShapeError(LearnestError, ValueError):
    """An array has the wrong shape for the system or estimator it is given to."""


class SettingsError(LearnestError, ValueError):
    """An option is outside its documented range (``runtime/limits.py``) or of the wrong type."""


class DataError(LearnestError, ValueError):
    """A run (CSV) is malformed: missing columns, non-monotonic time, non-finite values."""


class UnknownNameError(LearnestError, KeyError):
    """A name (system, estimator, activation, ...) is not in its registry."""

    def __str__(self) -> str:  # KeyError would otherwise quote the message
        return str(self.args[0]) if self.args else ""


class SystemFileError(LearnestError, ImportError):
    """A user system file cannot be loaded or does not define a system."""


class ModelMismatchError(LearnestError, ValueError):
    """A trained model or compiled library does not belong to the system or settings in use."""


class BuildError(LearnestError, RuntimeError):
    """The C compiler failed; the message carries the command line and the compiler's stderr."""


class OutputError(LearnestError, OSError):
    """An output path cannot be written as asked: it is an input, it exists (without
    ``--force``), or its folder cannot be made."""


class SolverError(LearnestError, RuntimeError):
    """A numerical solver (Ipopt, a Cholesky factorisation) failed at run time."""


def check_shape(name: str, array, expected: tuple[int, ...]) -> None:
    """Raise :class:`ShapeError` unless ``array.shape == expected``."""
    shape = tuple(getattr(array, "shape", ()))
    if shape != tuple(expected):
        raise ShapeError(f"{name}: expected shape {tuple(expected)}, got {shape}")
