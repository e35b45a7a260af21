"""What every ctypes estimator binding shares: the C kit's API, typed once, behind the
interface of the Python references.

A compiled estimator directory holds ``manifest.json`` and ``lib<prefix>.so``; the binding
checks the manifest against what the caller expects, loads the library, checks the
fingerprint compiled into it against the manifest's (a library swapped for another build is
refused before it runs), types each ``<prefix>_<name>`` symbol once from a signature table,
and turns a negative C status (``learnest_status.h``) into :class:`SolverError` naming the
call and the code. Each instance owns its workspace (a numpy buffer handed to
``<prefix>_init``), so any number of instances of one library run independently.

Threads: a C handle must not be used by two threads at once (``learnest_api.h``: one step
writes the whole estimator). Each instance holds a lock of its own around every call of its
handle (:func:`_locked`), so one instance called from several threads never runs two calls at
once: its steps are taken one after the other, in the order the threads get the lock (two
threads stepping one MHE handle without it crashed the process in 3 of 12 runs). Interleaving
two streams of samples on one estimator still makes no estimate of either: give each stream
its own instance. Torch-free.
"""

from __future__ import annotations

import ctypes
import functools
import os
import threading
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Callable, Mapping, TypeVar

import numpy as np

from ..errors import DataError, ModelMismatchError, SettingsError, ShapeError, SolverError
from ..estimators import validation
from .limits import check_option
from .manifest import check_manifest, read_manifest
from .status import STATUS_BY_CODE, status_name

C_DTYPES = {"float64": (np.float64, ctypes.c_double), "float32": (np.float32, ctypes.c_float)}
FLOAT32_MAX = float(np.finfo(np.float32).max)
INT, HANDLE, PTR = ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p
_LOCKS: dict[str, threading.Lock] = {}
_LOCKS_LOCK = threading.Lock()


_F = TypeVar("_F", bound=Callable[..., Any])


def _locked(method: _F) -> _F:
    """``method`` holding the instance's lock: no two calls of one handle overlap (see the
    module docstring)."""
    @functools.wraps(method)
    def call(self, *args, **kwargs):
        with self._lock:
            return method(self, *args, **kwargs)
    return call  # type: ignore[return-value]


def library_lock(library: Path) -> threading.Lock:
    """The process-wide lock of one library file (one per real path, made on first use)."""
    key = os.path.realpath(library)
    with _LOCKS_LOCK:
        return _LOCKS.setdefault(key, threading.Lock())


class CompiledEstimator:
    """Base of the ctypes bindings: ``directory``, ``manifest``, sizes, the typed library and
    the API every estimator shares (``reset``, ``step``, ``predict``, ``run``, ``set_noise``,
    ``x``, the gate's report).

    Subclasses set ``ESTIMATORS`` (manifest ``estimator`` values they load) and define
    ``_settings(settings)``, ``_covariances(P0) -> (P0, Q, R)`` and, for their own symbols,
    ``extra_signatures()``.

    One instance may be called from several threads: every call holds the instance's lock (the
    C handle itself is single-threaded; see the module docstring).

    Attributes
    ----------
    rejected, last_status, rejections : the innovation gate's report, as the references'.
    missing, input_rejected, input_rejections : the last step's missing outputs and replaced
        input components, and the components replaced since the reset (the input check).
    fingerprint : the build's identity, as compiled into the library.
    """

    #: Whether calls of two handles of one library must not overlap (the Ipopt MHE's static
    #: solver pool); then ``init``, ``reset``, ``step``, ``predict`` and ``run`` hold
    #: :func:`library_lock`.
    SERIALISE = False

    ESTIMATORS: tuple[str, ...] = ()
    #: Whether P0 and Q must be positive definite (the MHEs weigh by their inverses); R must be.
    DEFINITE = True

    def __init__(self, directory: Path, expect: Mapping[str, Any] | None, settings: Any = None):
        self._lock = threading.RLock()  # this instance's handle: one call at a time
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
        self.horizon = int(m["horizon"] or 0)
        precision = m["precision"]
        if precision not in C_DTYPES:
            raise ModelMismatchError(f"{self.where}: manifest precision {precision!r} is not one of "
                                     f"{list(C_DTYPES)}; recompile the estimator")
        self.precision = precision
        self.dtype, self.c_real = C_DTYPES[precision]
        self.real_pointer = np.ctypeslib.ndpointer(dtype=self.dtype, flags="C_CONTIGUOUS")
        library = self.directory / m["library"]
        self._lib = ctypes.CDLL(str(library))
        self._serial = library_lock(library) if self.SERIALISE else nullcontext()
        self._c = {}
        for name, (restype, argtypes) in {**self.signatures(), **self.extra_signatures()}.items():
            try:
                fn = getattr(self._lib, f"{m['prefix']}_{name}")
            except AttributeError as exc:
                raise ModelMismatchError(f"{self.where}: {library.name} has no symbol "
                                         f"{m['prefix']}_{name}; recompile the estimator") from exc
            fn.restype, fn.argtypes = restype, argtypes
            self._c[name] = fn
        self.fingerprint = self._c["fingerprint"]().decode()
        if self.fingerprint != m["fingerprint"]:
            raise ModelMismatchError(
                f"{library}: its fingerprint {self.fingerprint!r} is not the manifest's "
                f"{m['fingerprint']!r} (a library of another build); recompile the estimator")
        self._check_library()
        self.settings = self._settings(settings)
        self._memory = np.zeros(self._c["workspace_size"](), dtype=np.uint8)
        self._handle: int | None = None
        self.last_status = 0
        self._missing = np.zeros(self.ny, dtype=bool)

    def signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        """The C API every estimator shares (``learnest_api.h``)."""
        R, h = self.real_pointer, HANDLE
        return {
            "fingerprint": (ctypes.c_char_p, []), "real_size": (INT, []), "dt": (ctypes.c_double, []),
            "sizes": (None, [ctypes.POINTER(INT)] * 4), "workspace_size": (ctypes.c_size_t, []),
            "init": (INT, [PTR, ctypes.c_size_t, R, R, R, R, ctypes.POINTER(HANDLE)]),
            "reset": (INT, [h, R, R, R, R]),
            "step": (INT, [h, R, PTR, PTR]),
            "predict": (INT, [h, R]),
            "run": (INT, [h, INT, R, R, PTR, R]),
            "set_noise": (INT, [h, PTR, PTR]),
            "set_gate": (INT, [h, self.c_real, INT, self.c_real]),
            "get_rejected": (INT, [h, np.ctypeslib.ndpointer(dtype=np.intc, flags="C_CONTIGUOUS")]),
            "rejections": (INT, [h]), "samples": (INT, [h]), "get_state": (INT, [h, R]),
            "get_input_rejected": (INT, [h, np.ctypeslib.ndpointer(dtype=np.intc, flags="C_CONTIGUOUS")]),
            "input_rejections": (INT, [h]),
        }

    def extra_signatures(self) -> dict[str, tuple[Any, list[Any]]]:
        return {}

    def _settings(self, settings: Any) -> Any:
        raise NotImplementedError

    def _covariances(self, P0: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raise NotImplementedError

    def _configure(self) -> None:
        """Run-time options after the first init (the embedded MHE's solver options)."""

    def _check_library(self) -> None:
        sizes = [INT() for _ in range(4)]
        self._c["sizes"](*(ctypes.byref(s) for s in sizes))
        got = (*(s.value for s in sizes), self._c["dt"](), self._c["real_size"]())
        want = (self.nx, self.nu, self.ny, self.horizon, float(self.manifest["dt"]),
                np.dtype(self.dtype).itemsize)
        if got[-1] != want[-1]:
            built = {4: "float32", 8: "float64"}.get(got[-1], f"{got[-1]}-byte reals")
            raise ModelMismatchError(f"{self.where}: the library computes in {built}, the manifest "
                                     f"says precision {self.manifest['precision']!r} (edited?); "
                                     "recompile the estimator")
        if got != want:
            raise ModelMismatchError(f"{self.where}: library (nx, nu, ny, N, dt, real size) = {got}, "
                                     f"manifest says {want}; recompile the estimator")

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

    def check_status(self, call: str, code: int, detail: str = "") -> int:
        """Raise :class:`SolverError` for a negative status, naming the code, what it means and
        how to recover (``runtime/status.py``); return the code otherwise."""
        if code < 0:
            status = STATUS_BY_CODE.get(code)
            why = f": {status.meaning}; {status.recovery}" if status else "; the estimator is as before"
            raise SolverError(f"{type(self).__name__}.{call} ({self.directory.name}{detail}): "
                              f"C returned {code} ({status_name(code)}){why}")
        return code

    # -- the shared API --------------------------------------------------------------------

    @_locked
    def reset(self, x0: np.ndarray, P0: np.ndarray | None = None) -> None:
        """Start over from ``x0 (nx,)`` with covariance ``P0 (nx, nx)`` (default: the settings')
        and the settings' noise covariances and gate."""
        x0 = validation.vector(f"{type(self).__name__}.reset: x0", x0, self.nx)
        args = [self.real_array(a, exact=True) for a in (x0, *self._covariances(P0))]
        if self._handle is None:
            handle = HANDLE()
            with self._serial:
                code = self._c["init"](self._memory.ctypes.data, self._memory.nbytes, *args,
                                       ctypes.byref(handle))
            self.check_status("reset", code)
            self._handle = handle.value
            self._configure()
        else:
            with self._serial:
                code = self._c["reset"](self._handle, *args)
            self.check_status("reset", code)
        gate = self.settings.gate
        self.check_status("reset", self._c["set_gate"](self._handle, gate.c_threshold(),
                                                       gate.recover_after, gate.inflation))
        self.last_status = 0
        self._missing = np.zeros(self.ny, dtype=bool)

    @_locked
    def step(self, u: np.ndarray, y: np.ndarray, valid=None) -> np.ndarray:
        """One sample: ``u (nu,)`` the input applied since the previous sample, ``y (ny,)`` the
        measurement (NaN: a missing output), or ``valid (ny,)`` saying which outputs it holds
        (then a missing one may hold anything). The C call takes the validity as flags.
        A non-finite ``u`` goes to the C's input check (replaced, status bit 2).
        Returns the estimate ``x (nx,)``."""
        handle = self._started("step")
        name = type(self).__name__
        u = self.real_array(validation.input_vector(f"{name}.step: u", u, self.nu))
        y, mask = validation.measurements(f"{name}.step: y", y, valid, self.ny)
        if y.shape != (self.ny,):
            raise ShapeError(f"{name}.step: y: expected shape ({self.ny},), got {y.shape}")
        y, flags = self.real_array(y), None if mask is None else np.ascontiguousarray(mask, dtype=np.uint8)
        with self._serial:
            code = self._c["step"](handle, u, y.ctypes.data, None if flags is None else flags.ctypes.data)
        self.last_status = self.check_status("step", code, self._sample())
        self._missing = np.zeros(self.ny, dtype=bool) if mask is None else ~mask
        return self.x

    @_locked
    def predict(self, u: np.ndarray) -> np.ndarray:
        """A sample without measurement (every output missing); returns ``x (nx,)``."""
        handle = self._started("predict")
        u = self.real_array(validation.input_vector(f"{type(self).__name__}.predict: u", u, self.nu))
        with self._serial:
            code = self._c["predict"](handle, u)
        self.last_status = self.check_status("predict", code, self._sample())
        self._missing = np.ones(self.ny, dtype=bool)
        return self.x

    @_locked
    def run(self, U: np.ndarray, Y: np.ndarray, x0: np.ndarray, P0: np.ndarray | None = None,
            valid=None) -> np.ndarray:
        """Estimate a whole run in C: ``U (T, nu)``, ``Y (T, ny)`` (NaN: missing), ``valid (T, ny)``
        or None -> ``X_hat (T, nx)``; sample 0 is ``step(U[0], Y[0])``, sample ``k``
        ``step(U[k-1], Y[k])``."""
        name = type(self).__name__
        Y, mask = validation.measurements(f"{name}.run", Y, valid, self.ny)
        U, Y = validation.run_arrays(f"{name}.run", U, Y, self.nu, self.ny, missing=True)
        self.reset(x0, P0)
        X_hat = np.full((len(Y), self.nx), np.nan, dtype=self.dtype)
        flags = None if mask is None else np.ascontiguousarray(mask, dtype=np.uint8)
        T = self.c_int(len(Y), "run_length", f"{name}.run: T")
        U, Y = self.real_array(U), self.real_array(Y)
        with self._serial:
            code = self._c["run"](self._handle, T, U, Y, None if flags is None else flags.ctypes.data,
                                  X_hat)
        self.last_status = self.check_status("run", code, self._sample())
        self._missing = np.zeros(self.ny, dtype=bool) if mask is None or not len(mask) else ~mask[-1]
        return X_hat.astype(float)

    @_locked
    def set_noise(self, Q: np.ndarray | None = None, R: np.ndarray | None = None,
                  P_arrival: np.ndarray | None = None) -> None:
        """New process- and measurement-noise covariances (None keeps one) on the running
        estimator: its state, covariance or window stay. ``P_arrival``: the MHEs' arrival
        covariance (an estimator without an arrival cost refuses it)."""
        name = type(self).__name__
        if P_arrival is not None:
            raise SettingsError(f"{name}.set_noise: P_arrival is the MHEs' arrival covariance; "
                             f"this estimator has no arrival cost")
        Q = None if Q is None else self.real_array(
            validation.covariance(f"{name}.set_noise: Q", Q, self.nx, definite=self.DEFINITE,
                                  precision=self.precision), exact=True)
        R = None if R is None else self.real_array(
            validation.covariance(f"{name}.set_noise: R", R, self.ny, definite=True,
                                  precision=self.precision), exact=True)
        self.check_status("set_noise", self._c["set_noise"](
            self._started("set_noise"), None if Q is None else Q.ctypes.data,
            None if R is None else R.ctypes.data))

    def read(self, what: str, call: str, shape, dtype=None) -> np.ndarray:
        """What the C getter ``call`` writes into an array of ``shape`` (the real type unless
        ``dtype``), its status checked; ``what`` names it in errors. Hold the lock."""
        out = np.zeros(shape, dtype=self.dtype if dtype is None else dtype)
        self.check_status(what, self._c[call](self._started(what), out))
        return out

    @property
    @_locked
    def x(self) -> np.ndarray:
        """The current estimate ``(nx,)``."""
        return self.read("x", "get_state", self.nx).astype(float)

    @property
    @_locked
    def rejected(self) -> np.ndarray:
        """(ny,) bool: the outputs the gate rejected in the last step."""
        return self.read("rejected", "get_rejected", self.ny, np.intc).astype(bool)

    @property
    def missing(self) -> np.ndarray:
        """(ny,) bool: the outputs the last step had no sample of."""
        return self._missing.copy()

    @property
    @_locked
    def input_rejected(self) -> np.ndarray:
        """(nu,) bool: the input components the last step replaced by their held value."""
        return self.read("input_rejected", "get_input_rejected", self.nu, np.intc).astype(bool)

    @property
    @_locked
    def input_rejections(self) -> int:
        """Input components replaced since :meth:`reset`."""
        return int(self._c["input_rejections"](self._started("input_rejections")))

    @property
    @_locked
    def rejections(self) -> int:
        """Outputs rejected since :meth:`reset`."""
        return int(self._c["rejections"](self._started("rejections")))

    @property
    @_locked
    def samples(self) -> int:
        """Samples taken since :meth:`reset`."""
        return int(self._c["samples"](self._started("samples")))

    def _sample(self) -> str:
        return f", sample {self._c['samples'](self._handle)}"

    def _started(self, what: str) -> int:
        if self._handle is None:
            raise RuntimeError(f"{type(self).__name__}.{what}: call reset(x0) first")
        return self._handle
