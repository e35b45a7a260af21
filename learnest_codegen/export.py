"""Symbolic export: a system (and optionally a trained residual net) to a discrete CasADi model.

The hybrid continuous model ``f_hc = f_prior + Delta`` is built as one SX graph (the net through
l4casadi's naive path) and discretised by one RK4 step into the named Function
``F(x, u) -> x_next``. The same :class:`DiscreteModel` feeds the Python reference estimators and
the C code generators, so the model inside them is identical by construction.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import casadi as cs
import numpy as np

from .errors import ShapeError, UnknownNameError
from .integrators import rk4_step
from .systems import System

if TYPE_CHECKING:  # torch is not needed for nominal or true models
    from .learning.network import ResidualNet

MODEL_KINDS = ("nominal", "true", "knode")


@dataclass(frozen=True)
class DiscreteModel:
    """A discrete-time model ``x+ = F(x, u)``, ``y = h(x, u)`` with CasADi SX functions.

    Attributes
    ----------
    system : the system it models (names, sizes, noise defaults).
    kind : ``"nominal"`` (prior), ``"true"`` (true dynamics) or ``"knode"`` (prior + net).
    F : ``Function('F', [x (nx), u (nu)], [x_next (nx)])``.
    f_continuous : ``Function('f', [x, u], [xdot])`` that ``F`` discretises.
    h : ``Function('h', [x, u], [y (ny)])``.
    dt : sampling period [s].
    """

    system: System
    kind: str
    F: cs.Function
    f_continuous: cs.Function
    h: cs.Function
    dt: float

    @property
    def nx(self) -> int:
        return self.system.nx

    @property
    def nu(self) -> int:
        return self.system.nu

    @property
    def ny(self) -> int:
        return self.system.ny

    def step(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Evaluate ``F`` numerically on one state ``(nx,)`` and input ``(nu,)``."""
        x, u = np.asarray(x, dtype=float), np.asarray(u, dtype=float)
        if x.shape != (self.nx,) or u.shape != (self.nu,):
            raise ShapeError(f"{self.kind} model step: expected x ({self.nx},), u ({self.nu},), "
                             f"got {x.shape}, {u.shape}")
        return np.asarray(self.F(x, u)).ravel()

    def measure(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Evaluate ``h`` numerically."""
        return np.asarray(self.h(np.asarray(x, float), np.asarray(u, float))).ravel()


def discretise(system: System, kind: str, xdot_fn, dt: float | None = None) -> DiscreteModel:
    """Build a :class:`DiscreteModel` from ``xdot_fn(x_sx, u_sx) -> SX`` by one RK4 step."""
    if kind not in MODEL_KINDS:
        raise UnknownNameError(f"unknown model kind {kind!r}; choose from {MODEL_KINDS}")
    dt = system.dt if dt is None else dt
    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    xdot = xdot_fn(x, u)
    f = cs.Function("f", [x, u], [xdot], ["x", "u"], ["xdot"])
    F = cs.Function("F", [x, u], [rk4_step(f, x, u, dt)], ["x", "u"], ["x_next"])
    return DiscreteModel(system, kind, F, f, system.casadi_h(), dt)


def prior_model(system: System) -> DiscreteModel:
    """The nominal model: RK4 of the prior ``f_prior``."""
    return discretise(system, "nominal", lambda x, u: system.f(x, u, variant="prior"))


def true_model(system: System) -> DiscreteModel:
    """RK4 of the true dynamics (available in simulation only)."""
    return discretise(system, "true", lambda x, u: system.f(x, u, variant="true"))


def hybrid_model(system: System, net: "ResidualNet", box: tuple[np.ndarray, np.ndarray] | None = None
                 ) -> DiscreteModel:
    """The KNODE model: RK4 of ``f_prior + Delta_theta`` with the net as a CasADi graph.

    ``box = (low, high)`` clamps the net's inputs to its training range
    (:func:`learnest_codegen.learning.ranges.training_box`) inside the graph.
    """
    if (net.nx, net.nu) != (system.nx, system.nu):
        raise ShapeError(f"network sizes (nx={net.nx}, nu={net.nu}) do not match system "
                         f"{system.name!r} (nx={system.nx}, nu={system.nu})")
    return discretise(system, "knode", lambda x, u: system.f(x, u, variant="prior") + net.casadi(x, u, box))
