"""ctypes binding of a compiled MHE (``codegen/mhe.py``); torch-free.

:class:`CompiledMHE` has the interface of the Python reference
:class:`~learnest_codegen.estimators.mhe.MHE` (``reset``, ``step``, ``x``, ``window``, ``run``)
and checks ``manifest.json`` before loading the library. Each instance owns its workspace (a
numpy buffer handed to ``<prefix>_init``), so several estimators of one library run
independently. Rebuild into a new directory rather than over a library this process has
loaded: ``dlopen`` would hand back the old one.
"""

from __future__ import annotations

import ctypes
import os
import threading
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..errors import ModelMismatchError
from ..estimators import validation
from ..estimators.mhe import NO_COVARIANCE, arrival_weight_from_covariance
from ..estimators.mhe_problem import MHESettings
from .base import CompiledEstimator

_INT, _HANDLE = ctypes.c_int, ctypes.c_void_p
_LOCKS: dict[str, threading.Lock] = {}
_LOCKS_LOCK = threading.Lock()


def library_lock(library: Path) -> threading.Lock:
    """The process-wide lock of one library file (one per real path, made on first use)."""
    key = os.path.realpath(library)
    with _LOCKS_LOCK:
        return _LOCKS.setdefault(key, threading.Lock())


class CompiledMHE(CompiledEstimator):
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
    rejected, last_status, rejections : the innovation gate's report, as :class:`MHE`'s.
    """

    ESTIMATORS = ("mhe",)
    #: The Ipopt solver's C keeps its memories in one static pool per library (CasADi's
    #: checkout/release), so two handles of one library must not solve at the same time
    #: (two threads failed with NO_MEMORY in 1 of 4 runs): ``init``, ``reset``, ``step`` and
    #: ``run`` hold :func:`library_lock`. The embedded MHE keeps everything in its workspace.
    SERIALISE = True

    def __init__(self, directory: Path, *, expect: Mapping[str, Any] | None = None,
                 settings: MHESettings | None = None):
        super().__init__(directory, expect)
        m = self.manifest
        self.horizon = int(m["horizon"])
        self.settings = settings or MHESettings.from_json(m["settings"])
        if self.settings.horizon != self.horizon:
            raise ModelMismatchError(f"{self.where}: settings.horizon is {self.settings.horizon}, "
                                     f"the library was generated for {self.horizon}")
        self.settings.check(self.nx, self.ny, self.where)
        self._check_sizes()
        self._serial = library_lock(self.directory / m["library"]) if self.SERIALISE else nullcontext()
        self._memory = np.zeros(self._c["workspace_size"](), dtype=np.uint8)
        self._handle: int | None = None
        self._P: np.ndarray | None = None
        self.last_status = 0

    def signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        R, h = self.real_pointer, _HANDLE
        return {
            "workspace_size": (ctypes.c_size_t, []),
            "init": (_INT, [ctypes.c_void_p, ctypes.c_size_t, R, R, R, R, ctypes.POINTER(_HANDLE)]),
            "reset": (_INT, [h, R, R, R, R]),
            "step": (_INT, [h, R, R]),
            "run": (_INT, [h, _INT, R, R, R]),
            "get_state": (_INT, [h, R]),
            "get_window": (_INT, [h, R]),
            "samples": (_INT, [h]),
            "sizes": (None, [ctypes.POINTER(_INT)] * 4),
            "set_gate": (_INT, [h, self.c_real, _INT, self.c_real]),
            "get_rejected": (_INT, [h, np.ctypeslib.ndpointer(dtype=np.intc, flags="C_CONTIGUOUS")]),
            "rejections": (_INT, [h]),
        }

    @property
    def P(self):
        """Not available: an MHE has no state covariance (raises AttributeError)."""
        raise AttributeError(NO_COVARIANCE)

    @property
    def x(self) -> np.ndarray:
        x = np.empty(self.nx, dtype=self.dtype)
        self.check_status("x", self._c["get_state"](self._started("x"), x))
        return x.astype(float)

    @property
    def window(self) -> np.ndarray:
        X = np.empty((self.horizon + 1, self.nx), dtype=self.dtype)
        self.check_status("window", self._c["get_window"](self._started("window"), X))
        return X.astype(float)

    @property
    def arrival_weight(self) -> np.ndarray:
        """(nx, nx) the weight ``P`` of the arrival cost in use."""
        self._started("arrival_weight")
        return self._P.copy()

    def reset(self, x0: np.ndarray, P0: np.ndarray | None = None) -> None:
        """Start over from ``x0 (nx,)``; ``P0 (nx, nx)`` as in :meth:`MHE.reset`."""
        x0 = validation.vector(f"{type(self).__name__}.reset: x0", x0, self.nx)
        Q, R, P = self.settings.weights()
        if P0 is not None:
            P = arrival_weight_from_covariance(P0, self.nx)
        args = [self.real_array(a, exact=True) for a in (x0, Q, R, P)]
        if self._handle is None:
            handle = _HANDLE()
            with self._serial:
                code = self._c["init"](self._memory.ctypes.data, self._memory.nbytes, *args,
                                       ctypes.byref(handle))
            self.check_status("reset", code)
            self._handle = handle.value
            self._configure(self._handle)
        else:
            with self._serial:
                code = self._c["reset"](self._handle, *args)
            self.check_status("reset", code)
        gate = self.settings.gate
        self.check_status("reset", self._c["set_gate"](self._handle, gate.c_threshold(),
                                                       gate.recover_after, gate.inflation))
        self._P = P
        self.last_status = 0

    @property
    def rejected(self) -> np.ndarray:
        """(ny,) bool: the outputs the gate rejected in the last step."""
        mask = np.zeros(self.ny, dtype=np.intc)
        self.check_status("rejected", self._c["get_rejected"](self._started("rejected"), mask))
        return mask.astype(bool)

    @property
    def rejections(self) -> int:
        """Outputs rejected since :meth:`reset`."""
        return int(self._c["rejections"](self._started("rejections")))

    def _configure(self, handle: int) -> None:
        """Run-time options after the first init (the Ipopt MHE has none)."""

    def step(self, u: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Take sample ``y (ny,)`` with input ``u (nu,)``, as :meth:`MHE.step`; returns ``x (nx,)``."""
        handle = self._started("step")
        name = type(self).__name__
        u = self.real_array(validation.vector(f"{name}.step: u", u, self.nu))
        y = self.real_array(validation.vector(f"{name}.step: y", y, self.ny))
        with self._serial:
            code = self._c["step"](handle, u, y)
        self.last_status = self.check_status("step", code, self._sample())
        return self.x

    def run(self, U: np.ndarray, Y: np.ndarray, x0: np.ndarray,
            P0: np.ndarray | None = None) -> np.ndarray:
        """Estimate a whole run in C: ``U (T, nu)``, ``Y (T, ny)`` -> ``X_hat (T, nx)``.

        Same convention as :meth:`MHE.run` (sample 0 uses ``Y[0]`` only).
        """
        U, Y = validation.run_arrays(f"{type(self).__name__}.run", U, Y, self.nu, self.ny)
        self.reset(x0, P0)
        X_hat = np.empty((len(Y), self.nx), dtype=self.dtype)
        T = self.c_int(len(Y), "run_length", f"{type(self).__name__}.run: T")
        U, Y = self.real_array(U), self.real_array(Y)
        with self._serial:
            code = self._c["run"](self._handle, T, U, Y, X_hat)
        self.last_status = self.check_status("run", code, self._sample())
        return X_hat.astype(float)

    def _sample(self) -> str:
        return f", sample {self._c['samples'](self._handle)}"

    def _started(self, what: str) -> int:
        if self._handle is None:
            raise RuntimeError(f"{type(self).__name__}.{what}: call reset(x0) first")
        return self._handle

    def _check_sizes(self) -> None:
        sizes = [_INT() for _ in range(4)]
        self._c["sizes"](*(ctypes.byref(s) for s in sizes))
        got = tuple(s.value for s in sizes)
        self.check_real_size(self._c["real_size"]() if "real_size" in self._c else 8)  # Ipopt: double
        if got != (self.nx, self.nu, self.ny, self.horizon):
            raise ModelMismatchError(f"{self.where}: library sizes (nx, nu, ny, N) = {got}, manifest "
                                     f"says {(self.nx, self.nu, self.ny, self.horizon)}")
