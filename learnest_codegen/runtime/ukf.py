"""ctypes bindings of a compiled UKF folder (see ``codegen/ukf.py``), with :class:`UKF`'s interface.

Imports neither torch nor filterpy: a deployed estimator needs numpy and the library only.
"""

from __future__ import annotations

import ctypes
import weakref
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import ModelMismatchError, SolverError
from ..estimators.ukf import UKFSettings, as_matrix, as_vector, check_run_arrays
from .manifest import check_manifest, read_manifest

# The C return codes of <prefix>_api.h.
C_ERRORS = {1: "not initialised", 2: "NULL pointer or T < 0", 3: "non-finite input",
            4: "non-finite result (covariance not positive definite?)"}

_DOUBLES = np.ctypeslib.ndpointer(dtype=np.float64, flags="C_CONTIGUOUS")

# dlopen returns the same handle for the same file, so two CompiledUKF on one library share its
# static state; this maps each library to the instance that last called init, so the other
# one fails loudly instead of reading someone else's filter.
_OWNERS: dict[str, weakref.ref] = {}


class _Sizes:
    """The sizes in a manifest, as the attributes ``nx, nu, ny`` that a DiscreteModel has."""

    def __init__(self, manifest: Mapping[str, Any]):
        self.nx, self.nu, self.ny = (int(manifest[k]) for k in ("nx", "nu", "ny"))


class CompiledUKF:
    """A compiled UKF with the interface of :class:`learnest_codegen.estimators.ukf.UKF`.

    Parameters
    ----------
    directory : folder written by :func:`learnest_codegen.codegen.ukf.generate_ukf`.
    expect : manifest entries the caller requires, e.g. ``{"system": "cartpole", "nx": 4}``;
        any difference raises :class:`ModelMismatchError`.
    settings : :class:`UKFSettings` whose Q, R and P0 to use (default: those compiled with the
        library). Its alpha, beta and kappa must equal the compiled ones (they are constants in
        the C).

    The C filter keeps its state in static storage, so there is one filter per library and
    process: of several instances on one library only the last to call :meth:`reset` may step.
    """

    def __init__(self, directory, *, expect: Mapping[str, Any] | None = None,
                 settings: UKFSettings | None = None):
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise FileNotFoundError(f"compiled UKF folder {self.directory} does not exist")
        self.manifest = read_manifest(self.directory)
        where = f"CompiledUKF({self.directory})"
        check_manifest(self.manifest, {"estimator": "ukf", **(expect or {})}, where)
        self.sizes = _Sizes(self.manifest)
        self.settings = self._settings(settings, where)
        self._lib_path = str((self.directory / self.manifest["library"]).resolve())
        self._c = _load(self._lib_path, self.manifest["prefix"])
        self._check_library(where)
        self._ready = False

    def _settings(self, settings: UKFSettings | None, where: str) -> UKFSettings:
        compiled = UKFSettings(**self.manifest["settings"])
        if settings is None:
            return compiled
        check_manifest({k: getattr(settings, k) for k in ("alpha", "beta", "kappa")},
                       {k: getattr(compiled, k) for k in ("alpha", "beta", "kappa")},
                       f"{where} settings")
        settings.validate_for(self.sizes)
        return settings

    def _check_library(self, where: str) -> None:
        in_library = (self._c.nx(), self._c.nu(), self._c.ny(), self._c.dt())
        in_manifest = (self.sizes.nx, self.sizes.nu, self.sizes.ny, float(self.manifest["dt"]))
        if in_library != in_manifest:
            raise ModelMismatchError(f"{where}: library (nx, nu, ny, dt) = {in_library} differ from "
                                     f"the manifest's {in_manifest}")

    def reset(self, x0, P0=None) -> None:
        """Start from mean ``x0 (nx,)`` and covariance ``P0 (nx, nx)`` (default settings.P0())."""
        nx = self.sizes.nx
        x0 = np.ascontiguousarray(as_vector("CompiledUKF.reset x0", x0, nx))
        P0 = self.settings.P0() if P0 is None else P0
        P0 = np.ascontiguousarray(as_matrix("CompiledUKF.reset P0", P0, (nx, nx)))
        self._call("init", x0, P0, np.ascontiguousarray(self.settings.Q()),
                   np.ascontiguousarray(self.settings.R()))
        _OWNERS[self._lib_path] = weakref.ref(self)
        self._ready = True

    def step(self, u, y) -> np.ndarray:
        """Filter one sample (same convention as ``UKF.step``); returns ``x (nx,)``."""
        self._check_owner("step")
        u = np.ascontiguousarray(as_vector("CompiledUKF.step u", u, self.sizes.nu))
        y = np.ascontiguousarray(as_vector("CompiledUKF.step y", y, self.sizes.ny))
        self._call("step", u, y)
        return self.x

    @property
    def x(self) -> np.ndarray:
        """Current state estimate ``(nx,)``."""
        self._check_owner("x")
        x = np.empty(self.sizes.nx)
        self._c.get_state(x)
        return x

    @property
    def P(self) -> np.ndarray:
        """Current covariance ``(nx, nx)``."""
        self._check_owner("P")
        P = np.empty((self.sizes.nx, self.sizes.nx))
        self._c.get_covariance(P)
        return P

    def run(self, U, Y, x0, P0=None) -> np.ndarray:
        """Filter a whole run in C; same arguments, result and convention as ``UKF.run``."""
        U, Y = check_run_arrays("CompiledUKF.run", U, Y, self.sizes)
        self.reset(x0, P0)
        X_hat = np.full((len(Y), self.sizes.nx), np.nan)
        code = self._c.run(len(Y), np.ascontiguousarray(U), np.ascontiguousarray(Y), X_hat)
        if code:
            failed = int(np.flatnonzero(np.isnan(X_hat[:, 0]))[0])
            raise SolverError(f"CompiledUKF.run: C run failed at sample {failed} with code {code} "
                              f"({C_ERRORS.get(code, 'unknown')})")
        return X_hat

    def _call(self, name: str, *args) -> None:
        code = getattr(self._c, name)(*args)
        if code:
            raise SolverError(f"CompiledUKF.{name}: C {self.manifest['prefix']}_{name} returned "
                              f"{code} ({C_ERRORS.get(code, 'unknown')}); state left as before")

    def _check_owner(self, what: str) -> None:
        if not self._ready:
            raise RuntimeError(f"CompiledUKF.{what}: call reset(x0) first")
        owner = _OWNERS.get(self._lib_path)
        if owner is None or owner() is not self:
            raise RuntimeError(f"CompiledUKF.{what}: another CompiledUKF on {self._lib_path} has "
                               "reset the filter since (one filter per library); call reset again")


class _Library:
    """The library's functions without the prefix, each typed once."""

    def __init__(self, lib: ctypes.CDLL, prefix: str):
        signatures = {
            "nx": (ctypes.c_int, []), "nu": (ctypes.c_int, []), "ny": (ctypes.c_int, []),
            "dt": (ctypes.c_double, []),
            "init": (ctypes.c_int, [_DOUBLES] * 4),
            "step": (ctypes.c_int, [_DOUBLES] * 2),
            "get_state": (None, [_DOUBLES]),
            "get_covariance": (None, [_DOUBLES]),
            "run": (ctypes.c_int, [ctypes.c_int, _DOUBLES, _DOUBLES, _DOUBLES]),
        }
        for name, (restype, argtypes) in signatures.items():
            fn = getattr(lib, f"{prefix}_{name}")
            fn.restype, fn.argtypes = restype, argtypes
            setattr(self, name, fn)


def _load(path: str, prefix: str) -> _Library:
    if not Path(path).is_file():
        raise FileNotFoundError(f"compiled UKF library {path} does not exist; regenerate the folder")
    try:
        return _Library(ctypes.CDLL(path), prefix)
    except (OSError, AttributeError) as exc:  # not a library, or built with another prefix
        raise ModelMismatchError(f"cannot load UKF library {path} with prefix {prefix!r}: {exc}") from exc
