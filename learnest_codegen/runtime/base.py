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

from ..errors import ModelMismatchError, SolverError
from .manifest import check_manifest, read_manifest
from .status import status_name

C_DTYPES = {"float64": (np.float64, ctypes.c_double), "float32": (np.float32, ctypes.c_float)}


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
        self.dtype, self.c_real = C_DTYPES[m.get("precision", "float64")]
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

    def real_array(self, a) -> np.ndarray:
        """``a`` as a C-contiguous array of the library's real type."""
        return np.ascontiguousarray(a, dtype=self.dtype)

    def check_status(self, call: str, code: int, detail: str = "") -> int:
        """Raise :class:`SolverError` for a negative status; return the code otherwise."""
        if code < 0:
            raise SolverError(f"{type(self).__name__}.{call} ({self.directory.name}{detail}): "
                              f"C returned {code} ({status_name(code)})")
        return code
