"""What every ctypes estimator binding shares: the manifest check, typed symbols, status codes.

A compiled estimator directory holds ``manifest.json`` and ``lib<prefix>.so``; the binding
checks the manifest against what the caller expects, loads the library, types each
``<prefix>_<name>`` symbol once from a signature table, and turns a negative C status
(``learnest_status.h``) into :class:`SolverError` naming the call and the code. Torch-free.
"""

from __future__ import annotations

import ctypes
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import DataError, ModelMismatchError, SettingsError, SolverError
from .limits import check_option
from .manifest import check_manifest, read_manifest
from .status import status_name

C_DTYPES = {"float64": (np.float64, ctypes.c_double), "float32": (np.float32, ctypes.c_float)}
FLOAT32_MAX = float(np.finfo(np.float32).max)


class CompiledEstimator:
    """Base of the ctypes bindings: ``directory``, ``manifest``, sizes and the typed library.

    Subclasses set ``ESTIMATORS`` (manifest ``estimator`` values they load) and
    ``signatures(real_pointer, real)`` -> ``{name: (restype, argtypes)}``.
    """

    ESTIMATORS: tuple[str, ...] = ()

    def __init__(self, directory: Path, expect: Mapping[str, Any] | None):
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise FileNotFoundError(f"compiled estimator folder {self.directory} does not exist")
        self.manifest = read_manifest(self.directory)
        self.where = f"{type(self).__name__}({self.directory})"
        if self.manifest.get("estimator") not in self.ESTIMATORS:
            raise ModelMismatchError(f"{self.where}: compiled estimator does not match: estimator: "
                                     f"library has {self.manifest.get('estimator')!r}, expected "
                                     f"one of {list(self.ESTIMATORS)}")
        check_manifest(self.manifest, expect, self.where)
        m = self.manifest
        self.nx, self.nu, self.ny = int(m["nx"]), int(m["nu"]), int(m["ny"])
        precision = m.get("precision", "float64")
        if precision not in C_DTYPES:
            raise ModelMismatchError(f"{self.where}: manifest precision {precision!r} is not one of "
                                     f"{list(C_DTYPES)}; recompile the estimator")
        self.dtype, self.c_real = C_DTYPES[precision]
        self.real_pointer = np.ctypeslib.ndpointer(dtype=self.dtype, flags="C_CONTIGUOUS")
        library = self.directory / m["library"]
        if not library.is_file():
            raise FileNotFoundError(f"{self.where}: library {library} does not exist (rebuild the estimator)")
        self._lib = ctypes.CDLL(str(library))
        self._c = {}
        for name, (restype, argtypes) in self.signatures().items():
            try:
                fn = getattr(self._lib, f"{m['prefix']}_{name}")
            except AttributeError as exc:
                raise ModelMismatchError(f"{self.where}: {library.name} has no symbol "
                                         f"{m['prefix']}_{name}") from exc
            fn.restype, fn.argtypes = restype, argtypes
            self._c[name] = fn

    def signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        raise NotImplementedError

    def real_array(self, a, *, exact: bool = False) -> np.ndarray:
        """``a`` as a C-contiguous array of the library's real type.

        In a float32 library a finite value beyond float32's range (``|v| > 3.4e38``) would
        become infinite, and the C would refuse the whole call (NONFINITE_INPUT) where the
        float64 build takes the sample and its innovation gate rejects it. Such a value of a
        measurement or an input saturates to the largest float32 instead, which the gate
        rejects the same way. With ``exact`` (the initial state and the weights, which are
        settings, not samples) it raises :class:`SettingsError`. Complex values raise
        :class:`DataError` (numpy would drop the imaginary part).
        """
        a = np.asarray(a)
        if np.iscomplexobj(a):
            raise DataError(f"{self.where}: complex values are not real numbers (got {a.dtype})")
        if self.dtype != np.float32:
            return np.ascontiguousarray(a, dtype=self.dtype)
        wide = np.asarray(a, dtype=np.float64)
        big = np.isfinite(wide) & (np.abs(wide) > FLOAT32_MAX)
        if big.any():
            if exact:
                raise SettingsError(f"{self.where}: {wide[big][0]:g} is beyond the range of this "
                                    f"float32 library (|v| <= {FLOAT32_MAX:.4g})")
            wide = np.where(big, np.copysign(FLOAT32_MAX, wide), wide)
        return np.ascontiguousarray(wide, dtype=np.float32)

    def c_int(self, value: int, limit: str, where: str) -> int:
        """``value`` for a C ``int`` argument, checked against ``runtime/limits.py``'s range
        (ctypes would wrap 2**32 + 10 to 10 without a word)."""
        return check_option(limit, value, where)

    def check_real_size(self, real_size: int) -> None:
        """Raise :class:`ModelMismatchError` unless the library's reals are the manifest's."""
        if real_size != np.dtype(self.dtype).itemsize:
            built = {4: "float32", 8: "float64"}.get(real_size, f"{real_size}-byte")
            raise ModelMismatchError(f"{self.where}: the library computes in {built}, the manifest "
                                     f"says precision {self.manifest.get('precision', 'float64')!r} "
                                     "(edited?); recompile the estimator")

    def check_status(self, call: str, code: int, detail: str = "") -> int:
        """Raise :class:`SolverError` for a negative status; return the code otherwise."""
        if code < 0:
            raise SolverError(f"{type(self).__name__}.{call} ({self.directory.name}{detail}): "
                              f"C returned {code} ({status_name(code)})")
        return code
