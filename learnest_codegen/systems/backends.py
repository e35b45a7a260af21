"""Array backends that let a system's equations be written once.

A system writes its dynamics against a small ``ops`` namespace (``ops.sin``, ``ops.stack``...).
The same function then evaluates on numpy arrays, torch tensors (batched, differentiable) and
CasADi symbols, which is how the numpy, torch and CasADi forms of a model stay identical.

Conventions: numpy/torch vectors carry the component on the last axis (``(..., n)``); CasADi
vectors are columns ``(n, 1)``.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import casadi as cs
import numpy as np

from ..errors import ShapeError

#: The functions every backend offers, by numpy's names.
FUNCTIONS = ("sin", "cos", "tan", "arctan", "arctan2", "sqrt", "exp", "tanh", "abs")


def _functions(lib, **other_names: str) -> dict[str, Callable]:
    """:data:`FUNCTIONS` taken from the module ``lib``, by ``other_names`` where it spells one
    differently (``arctan="atan"``)."""
    return {name: getattr(lib, other_names.get(name, name)) for name in FUNCTIONS}


class _Backend:
    """A backend class: its :data:`FUNCTIONS` come from the module ``lib`` of its definition
    (``class NumpyOps(_Backend, lib=np)``)."""

    pi = math.pi

    def __init_subclass__(cls, lib=None, **other_names: str) -> None:
        super().__init_subclass__()
        for name, fn in _functions(lib, **other_names).items():
            setattr(cls, name, staticmethod(fn))


class NumpyOps(_Backend, lib=np):
    """Backend over numpy arrays of shape ``(..., n)``."""

    name = "numpy"

    @staticmethod
    def unpack(v, n: int) -> list:
        if v.shape[-1] != n:
            raise ShapeError(f"expected last dimension {n}, got shape {v.shape}")
        return [v[..., i] for i in range(n)]

    @staticmethod
    def stack(parts: Sequence) -> Any:
        return np.stack(np.broadcast_arrays(*parts), axis=-1)


class TorchOps:
    """Backend over torch tensors of shape ``(..., n)``; differentiable."""

    name = "torch"
    pi = math.pi

    def __init__(self) -> None:
        import torch  # imported lazily: the runtime layer must work without torch

        self._torch = torch
        vars(self).update(_functions(torch, arctan="atan", arctan2="atan2"))

    def unpack(self, v, n: int) -> list:
        if v.shape[-1] != n:
            raise ShapeError(f"expected last dimension {n}, got shape {tuple(v.shape)}")
        return list(v.unbind(-1))  # one operation (and one in the backward pass), not n

    def stack(self, parts: Sequence) -> Any:
        torch = self._torch
        ref = next(p for p in parts if isinstance(p, torch.Tensor))
        parts = [p if isinstance(p, torch.Tensor) else torch.full_like(ref, float(p)) for p in parts]
        return torch.stack(torch.broadcast_tensors(*parts), dim=-1)


class CasadiOps(_Backend, lib=cs, arctan="atan", arctan2="atan2", abs="fabs"):
    """Backend over CasADi SX/MX column vectors ``(n, 1)``."""

    name = "casadi"

    @staticmethod
    def unpack(v, n: int) -> list:
        if v.shape != (n, 1):
            raise ShapeError(f"expected a CasADi column of shape ({n}, 1), got {v.shape}")
        return [v[i] for i in range(n)]

    @staticmethod
    def stack(parts: Sequence) -> Any:
        return cs.vertcat(*parts)


_TORCH_OPS: TorchOps | None = None
_FIRST_TORCH_HOOKS: list[Callable[[], None]] = []


def on_first_torch_use(hook: Callable[[], None]) -> None:
    """Call ``hook()`` when a system is first evaluated on torch tensors in this process (the
    deferred torch part of the load check, :mod:`.check`); now if that already happened."""
    if _TORCH_OPS is not None:
        hook()
    elif hook not in _FIRST_TORCH_HOOKS:
        _FIRST_TORCH_HOOKS.append(hook)


def ops_for(value) -> Any:
    """Return the backend that matches the type of ``value``."""
    global _TORCH_OPS
    if isinstance(value, (cs.SX, cs.MX, cs.DM)):
        return CasadiOps
    if isinstance(value, np.ndarray):
        return NumpyOps
    if type(value).__module__.startswith("torch"):
        if _TORCH_OPS is None:
            _TORCH_OPS = TorchOps()
            while _FIRST_TORCH_HOOKS:
                _FIRST_TORCH_HOOKS.pop(0)()
        return _TORCH_OPS
    raise TypeError(f"no backend for values of type {type(value).__name__}")
