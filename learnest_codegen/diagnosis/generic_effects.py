"""The generic effect kinds, derived from any system's structure.

Registered into :data:`~learnest_codegen.diagnosis.effects.KINDS` on import (the package imports
this module); see :mod:`~learnest_codegen.diagnosis.effects` for channels and terms.

The kinds and where they are placed:

===================  =========================================  =======================  ===============
kind                 term                                       channels                 physical range
===================  =========================================  =======================  ===============
mass                 ``dp = theta``  (mass / inertia params)    ``param:<p>``            ``p + theta > 0``
parameter            ``dp = theta``  (other prior params)       ``param:<p>``            sign of ``p`` kept
viscous_friction     ``-theta v``                               velocity states          ``theta >= 0``
coulomb_friction     ``-theta tanh(v / v_s)``                   velocity states          ``theta >= 0``
quadratic_drag       ``-theta v |v|``                           velocity states          ``theta >= 0``
actuator_gain        ``du = theta u``                           ``input:<u>``            ``theta > -1``
actuator_offset      ``du = theta``                             ``input:<u>``            any
bias                 ``ds' = theta``                            ``direct:<s>``           any
===================  =========================================  =======================  ===============

The actuator dynamics (dead zone, saturation, back-EMF, input delay, first-order lag) are in
:mod:`~learnest_codegen.diagnosis.actuator_effects`.

*Velocity states* are the residual states whose unit is a rate (``.../s`` but not ``.../s^2``),
or ``System.diagnosis.velocity_states`` when a system declares them. A velocity-dependent force
on velocity ``v`` is offered directly on ``v'`` and through every input whose prior path reaches
``v'`` with one sign (:func:`~learnest_codegen.diagnosis.effects.input_orientation`: a friction
"as a force on ``u``" must oppose the motion whatever the state); which one fits is for the data
to decide.
*Mass parameters* are those named like masses or inertias (``m``, ``m_*``, ``mass*``, ``I*``,
``J*``, ``inertia*``) or listed in ``System.diagnosis.mass_params``.

(:func:`~learnest_codegen.diagnosis.effects.velocity_states`,
:func:`~learnest_codegen.diagnosis.effects.mass_params`).
"""

from __future__ import annotations

from typing import Sequence

import casadi as cs

from ..systems import System
from ..systems.backends import CasadiOps
from .effects import Effect, LibraryContext, input_orientation, input_reach, mass_params, register_kind


def _index(system: System, name: str) -> int:
    return system.state_names.index(name)


def _unit(system: System, state: str) -> str:
    return next(s.unit for s in system.states if s.name == state)


def _input_unit(system: System, name: str) -> str:
    return next(s.unit for s in system.inputs if s.name == name)


def _velocity_kinds(system: System, ctx: LibraryContext, kind: str, shape, power: int, label: str):
    """One effect per velocity state and channel (direct, then each input reaching it).

    ``shape(ctx, v)`` gives ``g(ops, v)``; the term is ``-theta g(v)``. ``power`` is the power of
    ``v``'s unit in ``g`` (1 viscous, 0 Coulomb, 2 drag), which fixes the parameter's unit.
    """
    reach, sign = input_reach(system), input_orientation(system)
    out = []
    for v in ctx.velocity_states:
        target = ctx.targets.get(v, v)
        i, vu, tu = _index(system, v), _unit(system, v), _unit(system, target)
        per_v = {0: "", 1: f"/({vu})", 2: f"/({vu})^2"}[power]
        shaped = shape(ctx, v)
        text = kind.replace("_", " ")
        term = lambda ops, x, u, th, i=i, shaped=shaped: -th * shaped(ops, x[i])  # noqa: E731
        out.append(Effect(kind, target, f"direct:{target}", label, f"({tu})/s{per_v}", term,
                          f"{text} on {v}, acting on {target}' directly", v, lower=0.0))
        for name in reach[target]:
            s = sign[(target, name)]
            if s == 0:
                continue  # the input pushes this velocity either way: no friction acts through it
            flipped = lambda ops, x, u, th, i=i, shaped=shaped, s=s: -s * th * shaped(ops, x[i])  # noqa: E731
            out.append(Effect(kind, target, f"input:{name}", label, f"{_input_unit(system, name)}{per_v}",
                              flipped, f"{text} on {v} as a force on input {name}", v, lower=0.0))
    return out


@register_kind("viscous_friction")
def _viscous(system: System, ctx: LibraryContext) -> list:
    return _velocity_kinds(system, ctx, "viscous_friction", lambda c, v: lambda ops, s: s, 1, "c")


@register_kind("coulomb_friction")
def _coulomb(system: System, ctx: LibraryContext) -> list:
    def shape(c, v):
        vs = c.coulomb_scale[v]
        return lambda ops, s: ops.tanh(s / vs)
    return _velocity_kinds(system, ctx, "coulomb_friction", shape, 0, "F_c")


@register_kind("quadratic_drag")
def _drag(system: System, ctx: LibraryContext) -> list:
    return _velocity_kinds(system, ctx, "quadratic_drag", lambda c, v: lambda ops, s: s * ops.abs(s), 2,
                           "k")


def _primary_state(system: System, reach_of_input: str) -> str:
    """The residual state an input acts on first (for reporting an input-channel effect)."""
    reach = input_reach(system)
    for s in system.residual_state_names:
        if reach_of_input in reach[s]:
            return s
    return system.residual_state_names[0]


def _driving_inputs(system: System) -> list[tuple[int, str]]:
    """Inputs whose prior path reaches some residual state (a prior that ignores an input, like
    the quadrotor's triple integrator, cannot have a gain error on it)."""
    reach = input_reach(system)
    used = {n for s in system.residual_state_names for n in reach[s]}
    return [(j, n) for j, n in enumerate(system.input_names) if n in used]


@register_kind("actuator_gain")
def _gain(system: System, ctx: LibraryContext) -> list:
    return [Effect("actuator_gain", _primary_state(system, n), f"input:{n}", "gain", "1",
                   lambda ops, x, u, th, j=j: th * u[j], f"input {n} scaled by (1 + gain)",
                   lower=-1.0 + 1e-3)  # the actuator keeps its direction
            for j, n in _driving_inputs(system)]


@register_kind("actuator_offset")
def _offset(system: System, ctx: LibraryContext) -> list:
    return [Effect("actuator_offset", _primary_state(system, n), f"input:{n}", "offset",
                   _input_unit(system, n), lambda ops, x, u, th: th, f"input {n} shifted by offset")
            for _, n in _driving_inputs(system)]


@register_kind("bias")
def _bias(system: System, ctx: LibraryContext) -> list:
    return [Effect("bias", s, f"direct:{s}", "b", f"{_unit(system, s)}/s",
                   lambda ops, x, u, th: th, f"constant term on {s}'")
            for s in system.residual_state_names]


def _param_effects(system: System, kind: str, names: Sequence[str]) -> list:
    reach = _param_reach(system)
    out = []
    for p in names:
        if not reach.get(p):
            continue  # the prior does not depend on it: no signature to find
        value = float(system.params[p])
        # the parameter keeps its sign (a mass, an inertia, a length stay positive)
        lower, upper = (-value, float("inf")) if value > 0 else (float("-inf"), -value) if value < 0 \
            else (float("-inf"), float("inf"))
        out.append(Effect(kind, reach[p][0], f"param:{p}", f"d{p}", f"unit of {p}",
                          lambda ops, x, u, th: th, f"prior parameter {p} changed by d{p}",
                          lower=lower, upper=upper))
    return out


def _param_reach(system: System, points: int = 8) -> dict[str, list[str]]:
    """For each prior parameter, the residual states whose derivative depends on it.

    A structural dependence is not enough: the ground robot's mass ``m`` enters only through the
    drag, which the prior switches off with ``C_D = 0``. So the Jacobian is evaluated at the
    prior's parameter values on a few random points (seeded) and must be non-zero somewhere.
    """
    import numpy as np

    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    names = list(system.params)
    syms = cs.SX.sym("p", len(names))
    f = cs.vertcat(*system.dynamics(CasadiOps, [x[i] for i in range(system.nx)],
                                    [u[j] for j in range(system.nu)],
                                    {n: syms[k] for k, n in enumerate(names)}))
    jac = cs.Function("dfdp", [x, u, syms], [cs.jacobian(f, syms)])
    rng = np.random.default_rng(0)
    values = [system.params[n] for n in names]
    size = np.zeros((system.nx, len(names)))
    for _ in range(points):
        J = np.asarray(jac(rng.uniform(0.2, 1.0, system.nx), rng.uniform(0.2, 1.0, system.nu), values))
        size = np.maximum(size, np.nan_to_num(np.abs(J)))
    states = system.state_names
    return {n: [s for s in system.residual_state_names if size[states.index(s), k] > 0]
            for k, n in enumerate(names)}


@register_kind("mass")
def _mass(system: System, ctx: LibraryContext) -> list:
    return _param_effects(system, "mass", mass_params(system))


@register_kind("parameter")
def _parameter(system: System, ctx: LibraryContext) -> list:
    masses = set(mass_params(system))
    return _param_effects(system, "parameter", [p for p in system.params if p not in masses])
