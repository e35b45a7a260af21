"""Fuzz the C API of the generated estimators in child processes; counts what went wrong.

Each target (one compiled estimator folder) is driven through raw ctypes, not through the
checked Python bindings, by a seeded random plan of calls: init / reset / step (with validity
flags: all, some, none, or bytes that are not flags) / predict / run / set_noise / set_gate /
the getters (and set_options, set_arrival where the header has them), with values from a
simulated run mixed with
NaN, +-Inf, 1e300, 1e-310 denormals, huge negatives, and non-symmetric, indefinite, singular,
zero or overflowing covariances; NULL where the header says the call checks it; T <= 0; calls
before init, on a NULL handle, on a never-initialised workspace and on a handle whose workspace
a later failed init wiped. The plan is a pure function of (seed, target, chunk), so any event can
be replayed. Chunks of calls run in child processes (fork): a child killed by a signal is a
crash, a call that does not return within ``call_timeout_s`` is a hang (the child is killed).

Counted per target: calls, crashes, hangs, ``nonfinite_ok`` (a call returned a success code but
the state, covariance, window or run output it made holds NaN/Inf), ``changed_on_error`` (an
init/step/reset/predict that returned an error code changed the estimate, against the
header's "a failed call changes nothing": a failed init on the live workspace included),
``covariance_not_psd_ok`` (the Kalman filters: a success code with a covariance that is not symmetric positive
semi-definite; informational) and every status code seen per call.

The estimators are the package's estimator table (``compilation.ESTIMATORS``); what the fuzzer
must know of each one's C API (matrix order of init, getters, whether calls take a handle and how
success is coded) is :func:`api`, read from its entry; a header that no longer declares a symbol
of it is an error, not a silent skip.

Usage::

    python scripts/fuzz_c_api.py --calls 20000 --seed 0 --out fuzz.json
"""

from __future__ import annotations

import argparse
import ctypes
import json
import multiprocessing
import sys
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

SYSTEMS = ("cartpole", "ground_robot")
SPECIALS = {  # adversarial reals per C precision
    "float64": (np.nan, np.inf, -np.inf, 1e300, -1e300, 1e-310, -1e-310, 0.0, -0.0, 1.7e308, -1e150),
    "float32": (np.nan, np.inf, -np.inf, 3e38, -3e38, 1e-40, -1e-40, 0.0, -0.0, 1e30, -1e20),
}
RUN_LENGTHS = (-1000000, -1, 0, 1, 2, 7, 30)


@dataclass(frozen=True)
class Api:
    """What the fuzzer must know about one estimator's C API (see each ``<prefix>*.h``)."""

    handle: bool  # calls take a handle made by init on caller memory
    matrices: tuple[str, ...]  # the matrices init/reset take after x0, in order
    getters: tuple[str, ...]  # get_<what>(..., real* out), out sized by GETTER_SIZE
    options: bool = False  # set_options(h, mode, max_iter, tol)
    gate: bool = True  # set_gate(h, threshold, recover_after, inflation) (learnest_gate.h)
    ok_positive: bool = True  # codes > 0 are success (learnest_status.h); else only 0 is
    arrival: bool = False  # set_arrival(h, P0) (the MHEs)

    def symbols(self) -> tuple[str, ...]:
        return ("init", "step", "run", "predict", "set_noise",
                *(() if not self.handle else ("reset", "workspace_size")),
                *self.getters, *(("set_options",) if self.options else ()),
                *(("set_gate",) if self.gate else ()), *(("set_arrival",) if self.arrival else ()))


# every estimator takes covariances x0, P0, Q, R (the C kit's one convention)
_MHE_GETTERS = ("get_state", "get_window", "get_arrival")


def api(estimator: str) -> Api:
    """The C API of ``estimator``, from its entry in the estimator table: a Kalman filter's
    state and covariance getters, or an MHE's state, window and arrival (the embedded MHE's
    Gauss-Newton kit adds ``set_options``; the Ipopt MHE keeps Ipopt's own memory behind the
    handle). :func:`check_table` refuses a target whose headers disagree."""
    from learnest_codegen.compilation import estimator_kind

    kind = estimator_kind(estimator)
    if not kind.horizon:
        return Api(True, ("P0", "Q", "R"), ("get_state", "get_covariance"))
    return Api(True, ("P0", "Q", "R"), _MHE_GETTERS, options=kind.kit == "learnest_mhe_gn.h", arrival=True)


def table_estimators() -> tuple[str, ...]:
    """Every estimator of the table, the Ipopt MHE last (the slowest to fuzz)."""
    from learnest_codegen.compilation import ESTIMATORS

    return tuple(sorted(ESTIMATORS, key=lambda name: name == "mhe"))


@dataclass
class Target:
    """One compiled estimator to fuzz, with the nominal values its calls start from."""

    name: str
    estimator: str
    directory: Path
    prefix: str
    nx: int
    nu: int
    ny: int
    horizon: int
    precision: str
    x0: np.ndarray
    matrices: dict[str, np.ndarray]
    U: np.ndarray
    Y: np.ndarray
    library: str = ""  # the shared library's file name (the manifest's)

    @property
    def api(self) -> Api:
        return api(self.estimator)

    def size(self, what: str) -> int:
        """Number of reals of a matrix argument or a getter's output."""
        n = {"P0": self.nx, "Q": self.nx, "P": self.nx, "R": self.ny}
        if what in n:
            return n[what] ** 2
        return {"get_state": self.nx, "get_covariance": self.nx ** 2, "get_arrival": self.nx ** 2,
                "get_window": (self.horizon + 1) * self.nx}[what]


def build_targets(root: Path, systems=SYSTEMS, estimators=None,
                  precisions=("float64",), samples: int = 400) -> list[Target]:
    """Compile the nominal estimators of ``systems`` under ``root`` with the package."""
    from learnest_codegen import get_system
    from learnest_codegen.compilation import compile_estimators, estimator_dir, estimator_kind
    from learnest_codegen.estimators.mhe_problem import MHESettings
    from learnest_codegen.export import prior_model
    from learnest_codegen.runtime.manifest import read_manifest
    from learnest_codegen.simulation import simulate

    targets = []
    for system_name in systems:
        system = get_system(system_name)
        model = prior_model(system)
        run = simulate(system, seed=1, duration=samples * system.dt)
        for precision in precisions:
            chosen = tuple(e for e in estimators or table_estimators()
                           if precision in estimator_kind(e).precisions)
            compile_estimators(model, root, model_hash="nominal", estimators=chosen, precision=precision)
            for estimator in chosen:
                directory = estimator_dir(root, model, estimator, precision)
                m = read_manifest(directory)
                kind = estimator_kind(estimator)
                if not kind.horizon:
                    s = kind.settings(**m["settings"])
                    mats = {"P0": s.P0(), "Q": s.Q(), "R": s.R()}
                else:
                    Q, R, P0 = MHESettings.from_json(m["settings"]).covariances()
                    mats = {"P0": P0, "Q": Q, "R": R}
                targets.append(Target(
                    directory.name, estimator, directory, m["prefix"], m["nx"], m["nu"], m["ny"],
                    int(m["horizon"] or 0), m["precision"], np.asarray(system.x0, float),
                    {k: np.asarray(v, float) for k, v in mats.items()}, run.u, run.y, m["library"]))
    return targets


# ---- the plan: a pure function of the seed -------------------------------------------------

@dataclass
class Call:
    """One planned call; ``args`` maps an argument name to an array, ``None`` (NULL) or a choice."""

    name: str
    args: dict[str, Any] = field(default_factory=dict)
    kinds: dict[str, str] = field(default_factory=dict)  # how each array was made

    def describe(self) -> dict[str, Any]:
        out = {"call": self.name}
        for key, value in self.args.items():
            if isinstance(value, np.ndarray):
                out[key] = {"kind": self.kinds.get(key, "?"),
                            "values": value.tolist() if value.size <= 25 else f"array{value.shape}"}
            else:
                out[key] = "NULL" if value is None else value
        return out


class Planner:
    """Draws calls for one target from ``rng``; the nominal sample index advances with steps."""

    def __init__(self, target: Target, rng: np.random.Generator):
        self.t, self.rng, self.k = target, rng, 0
        self.specials = np.array(SPECIALS[target.precision])

    def _pick(self, table: dict[str, float]) -> str:
        names = list(table)
        p = np.array(list(table.values()))
        return names[self.rng.choice(len(names), p=p / p.sum())]

    def _null(self, p: float = 0.03) -> bool:
        return bool(self.rng.random() < p)

    def vector(self, nominal: np.ndarray) -> tuple[np.ndarray, str]:
        r, n = self.rng, nominal.size
        kind = self._pick({"nominal": 55, "special_entries": 15, "random_magnitude": 10,
                           "noisy": 12, "all_special": 8})
        v = nominal.astype(float).copy()
        if kind == "special_entries":
            idx = r.choice(n, size=r.integers(1, n + 1), replace=False)
            v[idx] = r.choice(self.specials, size=idx.size)
        elif kind == "random_magnitude":
            v = r.choice([-1.0, 1.0], size=n) * 10.0 ** r.uniform(-320, 300, size=n)
        elif kind == "noisy":
            v = v + r.normal(size=n) * 10.0 ** r.uniform(-3, 4)
        elif kind == "all_special":
            v = r.choice(self.specials, size=n)
        return v, kind

    def matrix(self, nominal: np.ndarray) -> tuple[np.ndarray, str]:
        r, n = self.rng, nominal.shape[0]
        kind = self._pick({"nominal": 50, "non_symmetric": 7, "indefinite": 7, "singular": 6,
                           "zero": 3, "negative_diagonal": 4, "special_entries": 8, "denormal": 4,
                           "huge": 4, "random_spd_any_scale": 7})
        M = nominal.astype(float).copy()
        if kind == "non_symmetric":
            M = M + np.triu(r.normal(size=(n, n)), 1) * np.abs(M).max()
        elif kind == "indefinite":
            e = r.normal(size=n)
            e /= np.linalg.norm(e)
            M = M - (1 + r.uniform()) * 2 * np.abs(np.linalg.eigvalsh(M)).max() * np.outer(e, e)
        elif kind == "singular":
            w, V = np.linalg.eigh((M + M.T) / 2)
            w[r.integers(n)] = 0.0
            M = (V * w) @ V.T
        elif kind == "zero":
            M = np.zeros((n, n))
        elif kind == "negative_diagonal":
            M = M.copy()
            M[np.diag_indices(n)] *= -1
        elif kind == "special_entries":
            idx = r.choice(n * n, size=r.integers(1, 4), replace=False)
            M.flat[idx] = r.choice(self.specials, size=idx.size)
        elif kind == "denormal":
            M = np.eye(n) * r.choice(self.specials[np.abs(self.specials) < 1e-30])
        elif kind == "huge":
            M = np.eye(n) * 10.0 ** r.uniform(30, 308)
        elif kind == "random_spd_any_scale":
            A = r.normal(size=(n, n))
            M = (A @ A.T + 1e-3 * np.eye(n)) * 10.0 ** r.uniform(-300, 300)
        return M, kind

    def flags(self, n: int) -> tuple[np.ndarray | None, str]:
        """Validity flags of a step: all valid (NULL), random 0/1, none, or non-flag bytes."""
        kind = self._pick({"null": 70, "random": 20, "none": 6, "not_flags": 4})
        if kind == "null":
            return None, kind
        if kind == "random":
            return self.rng.integers(0, 2, size=n).astype(np.uint8), kind
        if kind == "none":
            return np.zeros(n, dtype=np.uint8), kind
        return self.rng.integers(2, 256, size=n).astype(np.uint8), kind

    def _estimate_args(self, call: Call) -> None:
        """x0 and the matrices of init/reset."""
        self.k = 0
        if self.rng.random() < 0.5:  # a clean restart, so that steps reach the solvers often
            call.args["x0"], call.kinds["x0"] = self.t.x0.copy(), "nominal"
            for name in self.t.api.matrices:
                call.args[name], call.kinds[name] = self.t.matrices[name].copy(), "nominal"
            return
        call.args["x0"], call.kinds["x0"] = self.vector(self.t.x0)
        for name in self.t.api.matrices:
            call.args[name], call.kinds[name] = self.matrix(self.t.matrices[name])
        for name in ("x0", *self.t.api.matrices):
            if self._null(0.02):
                call.args[name] = None

    def _handle(self) -> str:
        return self._pick({"current": 88, "null": 4, "garbage": 3, "zeroed": 3, "stale": 2})

    def call(self) -> Call:
        t, r = self.t, self.rng
        api = t.api
        table = {"init": 5, "reset": 5 if api.handle else 0, "step": 58, "predict": 4, "run": 3,
                 "set_noise": 3, "set_options": 4 if api.options else 0,
                 "set_gate": 3 if api.gate else 0, "set_arrival": 2 if api.arrival else 0}
        table.update({g: 16 / len(api.getters) for g in api.getters})
        name = self._pick(table)
        call = Call(name)
        if api.handle and name != "init":
            call.args["handle"] = self._handle()
        if name == "init":
            self._estimate_args(call)
            if api.handle:
                call.args["memory"] = self._pick({"good": 85, "null": 4, "short_by_one": 4,
                                                  "zero_size": 3, "misaligned": 4})
                call.args["handle_out"] = "null" if self._null() else "given"
        elif name == "reset":
            self._estimate_args(call)
        elif name == "step":
            k = self.k % len(t.Y)
            u_nominal = t.U[k - 1] if k else np.zeros(t.nu)
            call.args["u"], call.kinds["u"] = self.vector(u_nominal)
            call.args["y"], call.kinds["y"] = self.vector(t.Y[k])
            call.args["valid"], call.kinds["valid"] = self.flags(t.ny)
            for key in ("u", "y"):
                if self._null(0.02):
                    call.args[key] = None
            self.k += 1
        elif name == "predict":
            k = self.k % len(t.Y)
            call.args["u"], call.kinds["u"] = self.vector(t.U[k - 1] if k else np.zeros(t.nu))
            if self._null(0.02):
                call.args["u"] = None
            self.k += 1
        elif name == "set_noise":
            for key in ("Q", "R"):
                call.args[key], call.kinds[key] = self.matrix(t.matrices[key])
                if self._null(0.2):
                    call.args[key] = None
        elif name == "set_arrival":
            call.args["P0"], call.kinds["P0"] = self.matrix(t.matrices["P0"])
            if self._null(0.05):
                call.args["P0"] = None
        elif name == "run":
            T = int(r.choice(RUN_LENGTHS))
            call.args["T"] = T
            rows = max(T, 1)
            start = int(r.integers(0, len(t.Y) - rows))
            call.args["U"] = t.U[start:start + rows].copy()
            call.args["Y"] = t.Y[start:start + rows].copy()
            if r.random() < 0.3:
                call.args["Y"].flat[r.integers(call.args["Y"].size)] = r.choice(self.specials)
                call.kinds["Y"] = "special_entry"
            if r.random() < 0.3:
                call.args["valid"] = r.integers(0, 2, size=(rows, t.ny)).astype(np.uint8)
                call.kinds["valid"] = "random_flags"
            for key in ("U", "Y", "Xhat"):
                if self._null(0.05):
                    call.args[key] = None
        elif name == "set_options":
            call.args["mode"] = int(r.choice([-1, 0, 1, 2, 1 << 30]))
            call.args["max_iter"] = int(r.choice([-5, 0, 1, 3, 20, 1000]))
            call.args["tol"] = float(r.choice([np.nan, np.inf, -1.0, 0.0, 1e-300, 1e-14, 1e-10, 1e-6,
                                               1e-3, 1e-2, 1e300]))
        elif name == "set_gate":  # a tiny threshold rejects everything: the recovery's path
            call.args["threshold"] = float(r.choice([np.nan, np.inf, -1.0, 0.0, 1e-300, 1e-3, 9.0,
                                                     50.8, 1e300]))
            call.args["recover_after"] = int(r.choice([-5, 0, 1, 3, 10, 1 << 30]))
            call.args["inflation"] = float(r.choice([np.nan, np.inf, -2.0, 1.0, 1.5, 2.0, 1e3, 1e300]))
        else:  # a getter; the older API's void getters cannot report a NULL, so none is passed
            call.args["out"] = None if (api.handle and self._null(0.05)) else "given"
        return call


def plan(target: Target, seed: int, chunk: int, calls: int) -> Iterator[Call]:
    """The calls of one chunk: a pure function of (seed, target name, chunk)."""
    rng = np.random.default_rng([seed, zlib.crc32(target.name.encode()), chunk])
    planner = Planner(target, rng)
    for _ in range(calls):
        yield planner.call()


# ---- the child: executes a plan through raw ctypes -------------------------------------------

class Executor:
    """Loads one library and runs planned calls on it, counting codes and contract breaks."""

    def __init__(self, target: Target, chunk: int = 0):
        self.t, self.chunk, api = target, chunk, target.api
        check_table(target)
        self.lib = ctypes.CDLL(str(target.directory / target.library))
        self.dtype = np.float32 if target.precision == "float32" else np.float64
        self.c_real = ctypes.c_float if target.precision == "float32" else ctypes.c_double
        self.fn = {s: getattr(self.lib, f"{target.prefix}_{s}") for s in api.symbols()}
        self.fn["samples"] = getattr(self.lib, f"{target.prefix}_samples", None)
        vp, i = ctypes.c_void_p, ctypes.c_int
        for f in self.fn.values():
            if f is not None:
                f.restype = i
        if api.handle:
            self.fn["workspace_size"].restype = ctypes.c_size_t
            self.fn["init"].argtypes = [vp, ctypes.c_size_t] + [vp] * (2 + len(api.matrices))
            self.fn["reset"].argtypes = [vp] * (2 + len(api.matrices))
            self.fn["step"].argtypes = [vp] * 4
            self.fn["predict"].argtypes = [vp] * 2
            self.fn["set_noise"].argtypes = [vp] * 3
            self.fn["run"].argtypes = [vp, i, vp, vp, vp, vp]
            if api.arrival:
                self.fn["set_arrival"].argtypes = [vp] * 2
            for g in api.getters:
                self.fn[g].argtypes = [vp, vp]
            if api.options:
                self.fn["set_options"].argtypes = [vp, i, i, self.c_real]
            if api.gate:
                self.fn["set_gate"].argtypes = [vp, self.c_real, i, self.c_real]
            self.workspace = int(self.fn["workspace_size"]())
            self.memory = np.zeros(self.workspace + 64, dtype=np.uint8)
            self.garbage = np.random.default_rng(1).integers(0, 256, self.workspace + 64, dtype=np.uint8)
            self.zeroed = np.zeros(self.workspace + 64, dtype=np.uint8)
        else:
            self.fn["init"].argtypes = [vp] * (1 + len(api.matrices))
            self.fn["step"].argtypes = [vp, vp]
            self.fn["run"].argtypes = [i, vp, vp, vp]
            for g in api.getters:
                self.fn[g].restype, self.fn[g].argtypes = None, [vp]
        self.handle: int | None = None  # the current handle (None: NULL)
        self.stale: int | None = None  # the last handle an init returned
        self.codes: dict[str, Counter] = {}
        self.counts = Counter()
        self.events: list[dict[str, Any]] = []

    # -- helpers
    def _arr(self, a):
        if a is None:
            return None, None
        if isinstance(a, np.ndarray) and a.dtype == np.uint8:  # validity flags
            return a, a.ctypes.data
        with np.errstate(over="ignore", invalid="ignore"):
            arr = np.ascontiguousarray(a, dtype=self.dtype)
        return arr, arr.ctypes.data

    def _h(self, choice: str):
        if choice == "current":
            return self.handle
        if choice == "stale":
            return self.stale
        if choice == "garbage":
            return self.garbage.ctypes.data + 16
        if choice == "zeroed":
            return self.zeroed.ctypes.data + 16
        return None

    def _ok(self, code: int) -> bool:
        return code == 0 or (code > 0 and self.t.api.ok_positive)

    def _read(self, getter: str) -> np.ndarray | None:
        """A getter's output on the current handle, or None if it reports an error."""
        out = np.full(self.t.size(getter), np.nan, dtype=self.dtype)
        if self.t.api.handle:
            if self.handle is None or self.fn[getter](self.handle, out.ctypes.data) != 0:
                return None
        else:
            if self.fn["samples"]() < 0:
                return None
            self.fn[getter](out.ctypes.data)
        return out

    def snapshot(self) -> bytes | None:
        parts = [self._read(g) for g in self.t.api.getters]
        return None if any(p is None for p in parts) else b"".join(p.tobytes() for p in parts)

    def _event(self, kind: str, call: Call, index: int) -> None:
        self.counts[kind] += 1
        if len(self.events) < 20:
            self.events.append({"kind": kind, "chunk": self.chunk, "index": index, **call.describe()})

    def _check_outputs(self, call: Call, index: int, extra: np.ndarray | None = None) -> None:
        parts = [self._read(g) for g in self.t.api.getters]
        if extra is not None:
            parts.append(extra)
        if any(p is not None and not np.all(np.isfinite(p)) for p in parts):
            self._event("nonfinite_ok", call, index)
        covariance = parts[1] if self.t.api.getters[1:2] == ("get_covariance",) else None
        if covariance is not None and np.all(np.isfinite(covariance)):
            if not _symmetric_psd(covariance.astype(float).reshape(self.t.nx, self.t.nx)):
                self._event("covariance_not_psd_ok", call, index)

    # -- one call
    def execute(self, call: Call, index: int) -> None:
        t, a = self.t, call.args
        # a failed run keeps the samples before the failing one (headers), so only these two
        before = (self.snapshot() if call.name in ("step", "reset", "predict")
                  or (call.name == "init" and a.get("memory") in ("good", "misaligned")) else None)
        keep = []  # arrays alive until the call returns
        extra = None

        def ptr(key):
            arr, p = self._arr(a.get(key))
            keep.append(arr)
            return p

        mats = [ptr(m) for m in t.api.matrices]
        if call.name == "init":
            if t.api.handle:
                mem = {"good": self.memory.ctypes.data, "misaligned": self.memory.ctypes.data + 3,
                       "null": None, "short_by_one": self.memory.ctypes.data,
                       "zero_size": self.memory.ctypes.data}[a["memory"]]
                size = {"short_by_one": self.workspace - 1, "zero_size": 0}.get(a["memory"], self.workspace)
                out = ctypes.c_void_p(12345)
                code = self.fn["init"](mem, size, ptr("x0"), *mats,
                                       None if a["handle_out"] == "null" else ctypes.byref(out))
                if a["handle_out"] != "null":
                    if self._ok(code) and a["memory"] in ("good", "misaligned"):
                        self.handle = self.stale = out.value
                    elif self._ok(code):
                        self._event("accepted_bad_memory", call, index)
                    elif out.value is not None:
                        self._event("handle_not_null_on_error", call, index)
            else:
                code = self.fn["init"](ptr("x0"), *mats)
        elif call.name == "reset":
            code = self.fn["reset"](self._h(a["handle"]), ptr("x0"), *mats)
        elif call.name == "step":
            code = self.fn["step"](self._h(a["handle"]), ptr("u"), ptr("y"), ptr("valid"))
        elif call.name == "predict":
            code = self.fn["predict"](self._h(a["handle"]), ptr("u"))
        elif call.name == "set_noise":
            code = self.fn["set_noise"](self._h(a["handle"]), ptr("Q"), ptr("R"))
        elif call.name == "set_arrival":
            code = self.fn["set_arrival"](self._h(a["handle"]), ptr("P0"))
        elif call.name == "run":
            T = a["T"]
            X = None if a.get("Xhat", "") is None else np.full((max(T, 1), t.nx), np.nan, self.dtype)
            keep.append(X)
            args = [T, ptr("U"), ptr("Y"), ptr("valid"), None if X is None else X.ctypes.data]
            code = self.fn["run"](*([self._h(a["handle"])] if t.api.handle else []), *args)
            extra = X if X is not None and T > 0 else None
        elif call.name == "set_options":
            code = self.fn["set_options"](self._h(a["handle"]), a["mode"], a["max_iter"], a["tol"])
        elif call.name == "set_gate":
            code = self.fn["set_gate"](self._h(a["handle"]), a["threshold"], a["recover_after"],
                                       a["inflation"])
        else:
            out = np.full(t.size(call.name), np.nan, dtype=self.dtype)
            if t.api.handle:
                code = self.fn[call.name](self._h(a["handle"]), None if a["out"] is None else out.ctypes.data)
                ok = self._ok(code) and a["out"] is not None
            else:
                self.fn[call.name](out.ctypes.data)
                code, ok = "void", self.fn["samples"]() >= 0  # before init it copies zeros
            if ok and not np.all(np.isfinite(out)):
                self._event("nonfinite_ok", call, index)
        self.codes.setdefault(call.name, Counter())[str(code)] += 1
        self.counts["calls"] += 1
        if call.name in ("init", "reset", "step", "predict", "run") and self._ok(code):
            if call.name == "init" and t.api.handle and a["memory"] not in ("good", "misaligned"):
                return
            self._check_outputs(call, index, extra)
        if before is not None and not self._ok(code) and not self._targets_other(call):
            if self.snapshot() != before:
                self._event("changed_on_error", call, index)

    def _targets_other(self, call: Call) -> bool:
        """True when the call was made on some handle other than the current one."""
        return self.t.api.handle and call.args.get("handle") != "current"

    def result(self) -> dict[str, Any]:
        return {"counts": dict(self.counts), "events": self.events,
                "codes": {k: dict(v) for k, v in self.codes.items()}}


def _symmetric_psd(P: np.ndarray) -> bool:
    """Symmetric to 1e-6 and no eigenvalue below -1e-9, both relative to max |P_ij|."""
    P = P / max(np.abs(P).max(), 1e-300)  # scaled first: P + P' must not overflow
    return bool(np.abs(P - P.T).max() <= 1e-6 and np.linalg.eigvalsh((P + P.T) / 2).min() >= -1e-9)


def check_table(target: Target) -> None:
    """Raise if the target's headers no longer declare a symbol its :func:`api` names."""
    header = "\n".join(p.read_text() for p in sorted(target.directory.glob("*.h")))
    missing = [s for s in target.api.symbols() if f"{target.prefix}_{s}(" not in header]
    if missing:
        raise RuntimeError(f"fuzz api({target.estimator!r}) is out of date: the headers of "
                           f"{target.directory} declare no {missing}")


def _child(target: Target, seed: int, chunk: int, calls: int, progress, conn) -> None:
    executor = Executor(target, chunk)
    for index, call in enumerate(plan(target, seed, chunk, calls)):
        progress.value = index
        executor.execute(call, index)
    conn.send(executor.result())
    conn.close()


# ---- the parent: chunks in child processes, crashes and hangs --------------------------------

def fuzz_target(target: Target, calls: int, seed: int = 0, chunk_calls: int = 500,
                call_timeout_s: float = 20.0) -> dict[str, Any]:
    """Fuzz one target with ``calls`` planned calls in chunks of ``chunk_calls`` per child."""
    ctx = multiprocessing.get_context("fork")
    total = {"target": target.name, "estimator": target.estimator, "precision": target.precision,
             "seed": seed, "calls": 0, "crashes": 0, "hangs": 0, "nonfinite_ok": 0,
             "changed_on_error": 0, "covariance_not_psd_ok": 0, "handle_not_null_on_error": 0,
             "accepted_bad_memory": 0,
             "codes": {}, "events": [], "seconds": 0.0}
    start = time.perf_counter()
    n_chunks = -(-calls // chunk_calls)
    for chunk in range(n_chunks):
        n = min(chunk_calls, calls - chunk * chunk_calls)
        progress = ctx.Value("q", -1, lock=False)
        receive, send = ctx.Pipe(duplex=False)
        child = ctx.Process(target=_child, args=(target, seed, chunk, n, progress, send), daemon=True)
        child.start()
        send.close()
        outcome, last, since = None, -1, time.monotonic()
        while outcome is None:
            if receive.poll(0.02):
                try:
                    outcome = ("done", receive.recv())
                except EOFError:
                    outcome = ("died", None)
                break
            if not child.is_alive() and not receive.poll(0):
                outcome = ("died", None)
                break
            index = progress.value
            if index != last:
                last, since = index, time.monotonic()
            elif time.monotonic() - since > call_timeout_s:
                child.kill()
                outcome = ("hang", None)
        child.join()
        receive.close()
        if outcome[0] == "died" and child.exitcode >= 0:  # a Python error, not a signal
            raise RuntimeError(f"fuzz child of {target.name} failed (exit code {child.exitcode}) "
                               f"at chunk {chunk}, call {progress.value}")
        if outcome[0] == "done":
            _merge(total, outcome[1])
        else:
            kind = "crashes" if outcome[0] == "died" else "hangs"
            total[kind] += 1
            total["calls"] += max(progress.value, 0) + 1
            index = max(progress.value, 0)
            call = next(c for i, c in enumerate(plan(target, seed, chunk, n)) if i == index)
            total["events"].append({"kind": kind, "chunk": chunk, "index": index,
                                    "exitcode": child.exitcode, **call.describe()})
    total["seconds"] = round(time.perf_counter() - start, 2)
    return total


def _merge(total: dict[str, Any], part: dict[str, Any]) -> None:
    for key, value in part["counts"].items():
        total[key] = total.get(key, 0) + value
    for call, codes in part["codes"].items():
        into = total["codes"].setdefault(call, {})
        for code, n in codes.items():
            into[code] = into.get(code, 0) + n
    room = max(0, 40 - len(total["events"]))
    total["events"].extend(part["events"][:room])


def fuzz(targets: list[Target], calls: int | dict[str, int], seed: int = 0, report=None,
         **kwargs) -> dict[str, Any]:
    """Fuzz every target; ``calls`` may be a number per estimator name; ``report(result)`` is
    called after each target."""
    results = []
    for target in targets:
        check_table(target)
        n = calls[target.estimator] if isinstance(calls, dict) else calls
        results.append(fuzz_target(target, n, seed, **kwargs))
        if report:
            report(results[-1])
    keys = ("calls", "crashes", "hangs", "nonfinite_ok", "changed_on_error")
    return {"seed": seed, "targets": results,
            "totals": {k: sum(r[k] for r in results) for k in keys}}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("fuzz_c_api.json"))
    parser.add_argument("--build-dir", type=Path, default=Path("build_fuzz"))
    parser.add_argument("--systems", nargs="+", default=list(SYSTEMS), choices=SYSTEMS)
    parser.add_argument("--estimators", nargs="+", default=list(table_estimators()),
                        choices=table_estimators())
    parser.add_argument("--precisions", nargs="+", default=["float64", "float32"],
                        choices=["float64", "float32"])
    parser.add_argument("--calls", type=int, default=20000, help="planned calls per target")
    parser.add_argument("--ipopt-calls", type=int, default=None,
                        help="planned calls per Ipopt MHE target (default: --calls / 10)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--chunk", type=int, default=2000, help="calls per child process")
    parser.add_argument("--call-timeout", type=float, default=20.0, help="[s] a longer call is a hang")
    args = parser.parse_args(argv)
    targets = build_targets(args.build_dir, args.systems, args.estimators, args.precisions)
    calls = {e: args.calls for e in table_estimators()}
    calls["mhe"] = args.ipopt_calls if args.ipopt_calls is not None else max(1, args.calls // 10)
    result = fuzz(targets, calls, args.seed, report=_print, chunk_calls=args.chunk,
                  call_timeout_s=args.call_timeout)
    args.out.write_text(json.dumps(result, indent=1))
    return result


def _print(r: dict[str, Any]) -> None:
    print(f"{r['target']:32s} calls {r['calls']:8d} crashes {r['crashes']} hangs {r['hangs']} "
          f"nonfinite_ok {r['nonfinite_ok']} changed_on_error {r['changed_on_error']} "
          f"cov_not_psd_ok {r['covariance_not_psd_ok']} ({r['seconds']} s)", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
