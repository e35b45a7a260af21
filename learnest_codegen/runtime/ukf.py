"""ctypes bindings of a compiled UKF folder (see ``codegen/ukf.py``), with :class:`UKF`'s interface.

Imports neither torch nor filterpy: a deployed estimator needs numpy and the library only.
Each :class:`CompiledUKF` owns its workspace (a numpy buffer of ``<prefix>_workspace_size()``
bytes handed to ``<prefix>_init``), so any number of filters on one library run independently.
"""

from __future__ import annotations

import ctypes
from typing import Any, Mapping

import numpy as np

from ..errors import ModelMismatchError
from ..estimators import validation
from ..estimators.ukf import UKFSettings
from .base import CompiledEstimator
from .manifest import check_manifest

_INT, _HANDLE = ctypes.c_int, ctypes.c_void_p


class _Sizes:
    """The sizes in a manifest, as the attributes ``nx, nu, ny`` that a DiscreteModel has."""

    def __init__(self, manifest: Mapping[str, Any]):
        self.nx, self.nu, self.ny = (int(manifest[k]) for k in ("nx", "nu", "ny"))


class CompiledUKF(CompiledEstimator):
    """A compiled UKF with the interface of :class:`learnest_codegen.estimators.ukf.UKF`.

    Parameters
    ----------
    directory : folder written by :func:`learnest_codegen.codegen.ukf.generate_ukf`.
    expect : manifest entries the caller requires, e.g. ``{"system": "cartpole", "nx": 4}``;
        any difference raises :class:`ModelMismatchError`.
    settings : :class:`UKFSettings` whose Q, R, P0 and gate to use (default: those compiled
        with the library). Its alpha, beta and kappa must equal the compiled ones (they are
        constants in the C).

    Attributes
    ----------
    rejected, last_status, rejections : as :class:`~learnest_codegen.estimators.ukf.UKF`.
    """

    ESTIMATORS = ("ukf",)

    def __init__(self, directory, *, expect: Mapping[str, Any] | None = None,
                 settings: UKFSettings | None = None):
        super().__init__(directory, expect)
        self.sizes = _Sizes(self.manifest)
        self.settings = self._settings(settings)
        self._check_library()
        self._memory = np.zeros(self._c["workspace_size"](), dtype=np.uint8)
        self._handle: int | None = None
        self.last_status = 0

    def signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        R, h = self.real_pointer, _HANDLE
        return {
            "nx": (_INT, []), "nu": (_INT, []), "ny": (_INT, []), "dt": (ctypes.c_double, []),
            "real_size": (_INT, []), "workspace_size": (ctypes.c_size_t, []),
            "init": (_INT, [ctypes.c_void_p, ctypes.c_size_t, R, R, R, R, ctypes.POINTER(_HANDLE)]),
            "reset": (_INT, [h, R, R, R, R]),
            "step": (_INT, [h, R, R]),
            "get_state": (_INT, [h, R]),
            "get_covariance": (_INT, [h, R]),
            "run": (_INT, [h, _INT, R, R, R]),
            "set_gate": (_INT, [h, self.c_real, _INT, self.c_real]),
            "get_rejected": (_INT, [h, np.ctypeslib.ndpointer(dtype=np.intc, flags="C_CONTIGUOUS")]),
            "rejections": (_INT, [h]),
        }

    def _settings(self, settings: UKFSettings | None) -> UKFSettings:
        compiled = UKFSettings(**self.manifest["settings"])
        if settings is None:
            return compiled
        check_manifest({k: getattr(compiled, k) for k in ("alpha", "beta", "kappa")},
                       {k: getattr(settings, k) for k in ("alpha", "beta", "kappa")},
                       f"{self.where} settings (sigma-point constants are compiled in)")
        settings.validate_for(self.sizes)
        return settings

    def _check_library(self) -> None:
        c = self._c
        in_library = (c["nx"](), c["nu"](), c["ny"](), c["dt"]())
        in_manifest = (self.sizes.nx, self.sizes.nu, self.sizes.ny, float(self.manifest["dt"]))
        self.check_real_size(c["real_size"]())
        if in_library != in_manifest:
            raise ModelMismatchError(f"{self.where}: library (nx, nu, ny, dt) = {in_library} differ from "
                                     f"the manifest's {in_manifest}")

    def reset(self, x0, P0=None) -> None:
        """Start from mean ``x0 (nx,)`` and covariance ``P0 (nx, nx)`` (default settings.P0())."""
        nx = self.sizes.nx
        x0 = validation.vector("CompiledUKF.reset x0", x0, nx)
        P0 = self.settings.P0() if P0 is None else P0
        P0 = validation.covariance("CompiledUKF.reset P0", P0, nx)
        args = [self.real_array(a, exact=True) for a in (x0, P0, self.settings.Q(), self.settings.R())]
        if self._handle is None:
            handle = _HANDLE()
            self.check_status("reset", self._c["init"](self._memory.ctypes.data, self._memory.nbytes,
                                                       *args, ctypes.byref(handle)))
            self._handle = handle.value
        else:
            self.check_status("reset", self._c["reset"](self._handle, *args), "; state left as before")
        gate = self.settings.gate
        self.check_status("reset", self._c["set_gate"](self._handle, gate.c_threshold(),
                                                       gate.recover_after, gate.inflation))
        self.last_status = 0

    @property
    def rejected(self) -> np.ndarray:
        """(ny,) bool: the outputs the gate rejected in the last step."""
        mask = np.zeros(self.sizes.ny, dtype=np.intc)
        self.check_status("rejected", self._c["get_rejected"](self._started("rejected"), mask))
        return mask.astype(bool)

    @property
    def rejections(self) -> int:
        """Outputs rejected since :meth:`reset`."""
        return int(self._c["rejections"](self._started("rejections")))

    def step(self, u, y) -> np.ndarray:
        """Filter one sample (same convention as ``UKF.step``); returns ``x (nx,)``."""
        handle = self._started("step")
        u = self.real_array(validation.vector("CompiledUKF.step u", u, self.sizes.nu))
        y = self.real_array(validation.vector("CompiledUKF.step y", y, self.sizes.ny))
        self.last_status = self.check_status("step", self._c["step"](handle, u, y),
                                             "; state left as before")
        return self.x

    @property
    def x(self) -> np.ndarray:
        """Current state estimate ``(nx,)``."""
        x = np.empty(self.sizes.nx, dtype=self.dtype)
        self.check_status("x", self._c["get_state"](self._started("x"), x))
        return x.astype(float)

    @property
    def P(self) -> np.ndarray:
        """Current covariance ``(nx, nx)``."""
        P = np.empty((self.sizes.nx, self.sizes.nx), dtype=self.dtype)
        self.check_status("P", self._c["get_covariance"](self._started("P"), P))
        return P.astype(float)

    def run(self, U, Y, x0, P0=None) -> np.ndarray:
        """Filter a whole run in C; same arguments, result and convention as ``UKF.run``."""
        U, Y = validation.run_arrays("CompiledUKF.run", U, Y, self.sizes.nu, self.sizes.ny)
        self.reset(x0, P0)
        X_hat = np.full((len(Y), self.sizes.nx), np.nan, dtype=self.dtype)
        T = self.c_int(len(Y), "run_length", "CompiledUKF.run: T")
        code = self._c["run"](self._handle, T, self.real_array(U), self.real_array(Y), X_hat)
        if code < 0:
            failed = int(np.flatnonzero(np.isnan(X_hat[:, 0]))[0])
            self.check_status("run", code, f", at sample {failed}")
        self.last_status = code
        return X_hat.astype(float)

    def _started(self, what: str) -> int:
        if self._handle is None:
            raise RuntimeError(f"CompiledUKF.{what}: call reset(x0) first")
        return self._handle
