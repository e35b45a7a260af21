"""The check a system gets when it is loaded: its equations evaluated in every backend.

A system's ``dynamics`` (both variants) and ``measurement`` are evaluated at a few probe points
near ``x0`` (inputs from its own excitation) with numpy (simulation), CasADi (code generation)
and torch (training); each must give one finite value per state (output), and the backends
must agree. A mistake that would otherwise pass ``simulate`` and ``learnest-compile`` and fail
minutes later in training with a long traceback (``np.sin`` for ``ops.sin``, a wrong number of
values, a branch on a state) is then one line naming the function and what was wrong.

The numpy and CasADi evaluations cost milliseconds and run at once. So does the torch one when
torch is already imported (training, the API in a session that uses it); otherwise it runs
when a system is first evaluated on torch tensors in the process, so that a command that
never trains does not pay for importing torch (about 2.4 s of CPU per command, measured on
``learnest simulate``). ``np.sin`` on a state is caught at once either way: CasADi warns when
a numpy function is applied to its symbols, and the check makes that warning an error.
"""

from __future__ import annotations

import sys
import warnings
from typing import Callable

import numpy as np

from ..errors import ShapeError, SystemFileError
from .backends import on_first_torch_use
from .base import System

#: numpy, torch and CasADi must agree to this (relative to the largest value, at least 1).
TOLERANCE = 1e-9
PROBES = 3
_HINT = ("write the equations with ops.* (ops.sin, ops.cos, ops.sqrt, ...) and arithmetic, not "
         "numpy, math or Python branches on a state")


_PENDING: list[tuple[System, str]] = []


def check_system(system: System, where: str) -> None:
    """Raise :class:`SystemFileError` (one line starting with ``where``) unless the system's
    equations evaluate to finite values of the right length that agree in every backend (torch
    now if it is imported, else at the first evaluation on torch tensors)."""
    if "torch" in sys.modules:
        _check(system, where, torch=True)
        return
    _check(system, where, torch=False)
    _PENDING.append((system, where))
    on_first_torch_use(_check_pending)


def _check_pending() -> None:
    while _PENDING:
        system, where = _PENDING.pop(0)
        _check(system, where, torch=True)


def _check(system: System, where: str, *, torch: bool) -> None:
    x, u = _probe(system, where)
    functions = [("prior", system.label("prior"), system.nx), ("true", system.label("true"), system.nx),
                 ("h", "measurement", system.ny)]
    backends = [("CasADi (code generation)", _casadi)] + ([("torch (training)", _torch)] if torch else [])
    for variant, label, n in functions:
        evaluate = _evaluator(system, variant)
        reference = _numpy(evaluate, x, u, n, where, label)
        for backend, run in backends:
            got = run(system, variant, x, u, f"{where}: {label} in {backend}")
            if got is None:
                continue
            scale = max(1.0, float(np.max(np.abs(reference))))
            diff = float(np.max(np.abs(got - reference)))
            if not diff <= TOLERANCE * scale:
                raise SystemFileError(f"{where}: {label} gives {got[0].tolist()} in {backend} but "
                                      f"{reference[0].tolist()} in numpy at x = {x[0].tolist()} "
                                      f"(difference {diff:.3g}); {_HINT}")


def _probe(system: System, where: str) -> tuple[np.ndarray, np.ndarray]:
    """``PROBES`` states near ``x0`` and inputs near the excitation's first samples."""
    rng = np.random.default_rng(0)
    x0 = np.asarray(system.x0, dtype=float)
    t = np.arange(PROBES) * system.dt
    try:
        u = np.asarray(system.excitation(t, np.random.default_rng(0)), dtype=float)
    except Exception as exc:  # a user function can fail in any way; say which one
        raise SystemFileError(f"{where}: excitation(t, rng) failed: {_text(exc)}") from exc
    if u.shape != (PROBES, system.nu):
        raise SystemFileError(f"{where}: excitation(t, rng) must return shape (len(t), {system.nu}) "
                              f"(one column per input), got {u.shape} for {PROBES} times")
    if not np.all(np.isfinite(u)):
        raise SystemFileError(f"{where}: excitation(t, rng) returned non-finite inputs {u.tolist()}")
    x = x0 + 0.01 * (1 + np.abs(x0)) * rng.standard_normal((PROBES, system.nx))
    u = u + 0.01 * (1 + np.abs(u)) * rng.standard_normal(u.shape)
    return x, u


def _evaluator(system: System, variant: str) -> Callable:
    if variant == "h":
        return system.h
    return lambda x, u: system.f(x, u, variant=variant)


def _numpy(evaluate: Callable, x: np.ndarray, u: np.ndarray, n: int, file: str,
           label: str) -> np.ndarray:
    where = f"{file}: {label}"
    try:
        with np.errstate(all="ignore"):
            value = evaluate(x, u)
    except ShapeError as exc:  # the count of values, already one clear line
        raise SystemFileError(f"{file}: {str(exc).split(': ', 1)[-1]}") from exc
    except KeyError as exc:
        raise SystemFileError(f"{where} reads the parameter {exc.args[0]!r}, which is not in "
                              f"{'true_params' if 'true' in label else 'params'}") from exc
    except Exception as exc:
        raise SystemFileError(f"{where} cannot be evaluated with numpy (simulation): {_text(exc)}; "
                              f"{_HINT}") from exc
    value = np.asarray(value)
    if value.shape != x.shape[:1] + (n,) or not np.issubdtype(value.dtype, np.number):
        raise SystemFileError(f"{where} returned shape {value.shape[1:]} per sample for a batch of "
                              f"{len(x)}, expected ({n},); each value must be a scalar of x and u")
    bad = ~np.isfinite(value)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise SystemFileError(f"{where}: value {j} is {value[i, j]} at x = {np.round(x[i], 4).tolist()}, "
                              f"u = {np.round(u[i], 4).tolist()} (a point near x0); it must be finite there")
    return value.astype(float)


def _torch(system: System, variant: str, x: np.ndarray, u: np.ndarray, where: str):
    try:
        import torch
    except ImportError:  # a deployment without training
        return None
    xt = torch.tensor(x, dtype=torch.float64, requires_grad=True)
    ut = torch.tensor(u, dtype=torch.float64, requires_grad=True)
    try:
        value = _evaluator(system, variant)(xt, ut)
    except Exception as exc:
        raise SystemFileError(f"{where} fails: {_text(exc)}; {_HINT}") from exc
    if not isinstance(value, torch.Tensor):
        raise SystemFileError(f"{where}: returned {type(value).__name__}, not a tensor; {_HINT}")
    if tuple(value.shape) != (len(x), value.shape[-1]):
        raise SystemFileError(f"{where}: returned shape {tuple(value.shape)} for a batch of {len(x)}")
    return value.detach().numpy()


def _casadi(system: System, variant: str, x: np.ndarray, u: np.ndarray, where: str):
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", FutureWarning)  # casadi: "a numpy function was called"
            fn = system.casadi_h() if variant == "h" else system.casadi_f(variant)
            value = np.asarray(fn.map(len(x))(x.T, u.T).full()).T
    except Exception as exc:
        raise SystemFileError(f"{where} fails: {_text(exc)}; {_HINT}") from exc
    return value


def _text(exc: BaseException) -> str:
    """An exception as one short line."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    if "numpy() on Tensor" in text:  # torch's words for np.sin(tensor) suggest the wrong fix
        text = "a numpy function was applied to the torch tensor of a state or input"
    if "a numpy function was called on a casadi value" in text:
        text = "a numpy function was applied to the CasADi symbol of a state or input"
    text = text if len(text) <= 160 else text[:157] + "..."
    return f"{type(exc).__name__}: {text}"

