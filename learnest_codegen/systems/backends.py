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


class NumpyOps:
    """Backend over numpy arrays of shape ``(..., n)``."""

    name = "numpy"
    pi = math.pi
    sin, cos, tan = staticmethod(np.sin), staticmethod(np.cos), staticmethod(np.tan)
    arctan, arctan2 = staticmethod(np.arctan), staticmethod(np.arctan2)
    sqrt, exp, tanh = staticmethod(np.sqrt), staticmethod(np.exp), staticmethod(np.tanh)
    abs = staticmethod(np.abs)

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
        self.sin, self.cos, self.tan = torch.sin, torch.cos, torch.tan
        self.arctan, self.arctan2 = torch.atan, torch.atan2
        self.sqrt, self.exp, self.tanh = torch.sqrt, torch.exp, torch.tanh
        self.abs = torch.abs

    def unpack(self, v, n: int) -> list:
        if v.shape[-1] != n:
            raise ShapeError(f"expected last dimension {n}, got shape {tuple(v.shape)}")
        return list(v.unbind(-1))  # one operation (and one in the backward pass), not n

    def stack(self, parts: Sequence) -> Any:
        torch = self._torch
        ref = next(p for p in parts if isinstance(p, torch.Tensor))
        parts = [p if isinstance(p, torch.Tensor) else torch.full_like(ref, float(p)) for p in parts]
        return torch.stack(torch.broadcast_tensors(*parts), dim=-1)


class CasadiOps:
    """Backend over CasADi SX/MX column vectors ``(n, 1)``."""

    name = "casadi"
    pi = math.pi
    sin, cos, tan = staticmethod(cs.sin), staticmethod(cs.cos), staticmethod(cs.tan)
    arctan, arctan2 = staticmethod(cs.atan), staticmethod(cs.atan2)
    sqrt, exp, tanh = staticmethod(cs.sqrt), staticmethod(cs.exp), staticmethod(cs.tanh)
    abs = staticmethod(cs.fabs)

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
