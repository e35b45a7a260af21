"""ctypes binding of a compiled MHE (``codegen/mhe.py``); torch-free.

:class:`CompiledMHE` has the interface of the Python reference
:class:`~learnest_codegen.estimators.mhe.MHE` (``reset``, ``step``, ``x``, ``window``, ``run``)
and checks ``manifest.json`` before loading the library.

The C estimator keeps its state in static arrays and a process loads a library path only
once, so every :class:`CompiledMHE` on the same directory drives the same C state. The last
one to :meth:`~CompiledMHE.reset` owns it; the others raise instead of silently reading or
moving someone else's window. For the same reason, rebuild into a new directory rather than
over a library this process has loaded: ``dlopen`` would hand back the old one.
"""

from __future__ import annotations

import ctypes
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import ModelMismatchError, SolverError
from ..estimators.mhe import NO_COVARIANCE, arrival_weight_from_covariance, check_run_arrays, check_vector
from ..estimators.mhe_problem import MHESettings
from .manifest import check_manifest, read_manifest

_DOUBLES = ctypes.POINTER(ctypes.c_double)
_INT = ctypes.c_int
_SIGNATURES = {  # symbol suffix: (restype, argtypes)
    "init": (_INT, [_DOUBLES] * 4),
    "step": (_INT, [_DOUBLES, _DOUBLES]),
    "get_state": (None, [_DOUBLES]),
    "get_window": (None, [_DOUBLES]),
    "run": (_INT, [_INT, _DOUBLES, _DOUBLES, _DOUBLES]),
    "samples": (_INT, []),
    "sizes": (None, [ctypes.POINTER(_INT)] * 4),
    "status_name": (ctypes.c_char_p, [_INT]),
}
_OWNERS: dict[str, object] = {}  # library path -> token of the instance that last reset it


class CompiledMHE:
    """A compiled MHE loaded from its directory.

    Parameters
    ----------
    directory : folder written by :func:`~learnest_codegen.codegen.mhe.generate_mhe`.
    expect : manifest entries the library must have, e.g. ``{"system": "cartpole",
        "model_kind": "knode", "model_hash": h}``; any difference raises
        :class:`ModelMismatchError`.
    settings : weights to use (its horizon must be the library's); default: the settings
        recorded in the manifest.

    Attributes
    ----------
    x : (nx,) current estimate; window : (N+1, nx) current window solution, oldest first.
    """

    def __init__(self, directory: Path, *, expect: Mapping[str, Any] | None = None,
                 settings: MHESettings | None = None):
        self.directory = Path(directory)
        self.manifest = read_manifest(self.directory)
        where = f"CompiledMHE({self.directory})"
        check_manifest(self.manifest, {"estimator": "mhe", **(expect or {})}, where)
        m = self.manifest
        self.nx, self.nu, self.ny, self.horizon = m["nx"], m["nu"], m["ny"], m["horizon"]
        self.settings = settings or MHESettings.from_json(m["settings"])
        if self.settings.horizon != self.horizon:
            raise ModelMismatchError(f"{where}: settings.horizon is {self.settings.horizon}, "
                                     f"the library was generated for {self.horizon}")
        self.settings.check(self.nx, self.ny, where)
        self._c = _load(self.directory / m["library"], m["prefix"], where)
        self._check_sizes(where)
        self._x = np.zeros(self.nx)
        self._window = np.zeros((self.horizon + 1, self.nx))
        self._P: np.ndarray | None = None
        self._key, self._token = str((self.directory / m["library"]).resolve()), object()

    @property
    def P(self):
        """Not available: an MHE has no state covariance (raises AttributeError)."""
        raise AttributeError(NO_COVARIANCE)

    @property
    def x(self) -> np.ndarray:
        self._owned("x")
        self._c["get_state"](_ptr(self._x))
        return self._x.copy()

    @property
    def window(self) -> np.ndarray:
        self._owned("window")
        self._c["get_window"](_ptr(self._window))
        return self._window.copy()

    @property
    def arrival_weight(self) -> np.ndarray:
        """(nx, nx) the weight ``P`` of the arrival cost in use."""
        self._owned("arrival_weight")
        return self._P.copy()

    def reset(self, x0: np.ndarray, P0: np.ndarray | None = None) -> None:
        """Start over from ``x0 (nx,)``; ``P0 (nx, nx)`` as in :meth:`MHE.reset`."""
        x0 = check_vector("CompiledMHE.reset: x0", x0, self.nx)
        Q, R, P = self.settings.weights()
        if P0 is not None:
            P = arrival_weight_from_covariance(P0, self.nx)
        self._check("init", self._c["init"](*(_ptr(np.ascontiguousarray(a)) for a in (x0, Q, R, P))))
        _OWNERS[self._key], self._P = self._token, P

    def step(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Take sample ``y (ny,)`` with input ``u (nu,)``, as :meth:`MHE.step`; returns ``x (nx,)``."""
        self._owned("step")
        u = check_vector("CompiledMHE.step: u", u, self.nu)
        y = check_vector("CompiledMHE.step: y", y, self.ny)
        self._check("step", self._c["step"](_ptr(u), _ptr(y)))
        return self.x

    def run(self, U: np.ndarray, Y: np.ndarray, x0: np.ndarray,
            P0: np.ndarray | None = None) -> np.ndarray:
        """Estimate a whole run in C: ``U (T, nu)``, ``Y (T, ny)`` -> ``X_hat (T, nx)``.

        Same convention as :meth:`MHE.run` (sample 0 uses ``Y[0]`` only).
        """
        U, Y = check_run_arrays(U, Y, self.nu, self.ny, "CompiledMHE.run")
        self.reset(x0, P0)
        U, Y = np.ascontiguousarray(U), np.ascontiguousarray(Y)
        X_hat = np.empty((len(Y), self.nx))
        self._check("run", self._c["run"](len(Y), _ptr(U), _ptr(Y), _ptr(X_hat)))
        return X_hat

    def _check(self, call: str, code: int) -> None:
        if code != 0:
            name = self._c["status_name"](code).decode()
            raise SolverError(f"CompiledMHE.{call} ({self.directory.name}, sample "
                              f"{self._c['samples']()}): C returned {code} ({name})")

    def _owned(self, what: str) -> None:
        if _OWNERS.get(self._key) is not self._token:
            raise RuntimeError(f"CompiledMHE.{what}: call reset() first (another CompiledMHE "
                               f"on {self.directory} may have reset the shared C state)")

    def _check_sizes(self, where: str) -> None:
        sizes = [_INT() for _ in range(4)]
        self._c["sizes"](*(ctypes.byref(s) for s in sizes))
        got = tuple(s.value for s in sizes)
        if got != (self.nx, self.nu, self.ny, self.horizon):
            raise ModelMismatchError(f"{where}: library sizes (nx, nu, ny, N) = {got}, manifest "
                                     f"says {(self.nx, self.nu, self.ny, self.horizon)}")


def _load(library: Path, prefix: str, where: str) -> dict[str, Any]:
    """Load ``library`` and type each ``<prefix>_<name>`` symbol once."""
    if not library.is_file():
        raise FileNotFoundError(f"{where}: library {library} not found (rebuild the estimator)")
    lib = ctypes.CDLL(str(library))
    functions = {}
    for name, (restype, argtypes) in _SIGNATURES.items():
        try:
            fn = getattr(lib, f"{prefix}_{name}")
        except AttributeError as exc:
            raise ModelMismatchError(f"{where}: {library.name} has no symbol {prefix}_{name}") from exc
        fn.restype, fn.argtypes = restype, argtypes
        functions[name] = fn
    return functions


def _ptr(a: np.ndarray):
    return a.ctypes.data_as(_DOUBLES)

