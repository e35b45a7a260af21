"""A library of named unmodelled effects, built from a :class:`System` description.

An *effect* is a physically meaningful term that a first-principles prior commonly leaves out,
with one parameter (value and unit) and a *channel* through which it enters the dynamics:

* ``input:<u>`` - a perturbation of input ``u`` (a generalised force), mapped through the prior's
  own input path. A friction force on a cart enters where the motor force does, so it changes
  every derivative the force changes (in the cartpole both ``pdot'`` and ``alphadot'``, through
  the mass matrix) with a single parameter.
* ``param:<p>`` - a change of a prior parameter (``m_c + dm``): "scaling of the prior's own
  terms" for masses and inertias, exact and nonlinear in the parameter.
* ``direct:<s>`` - a term added to the derivative of state ``s`` only (a bias, or a damping of a
  velocity that no input drives); ``direct:<s1>,<s2>,...`` - a list of terms, one per state, with
  one shared parameter (a thrust gain common to all three axes).
* ``filter:<u>`` - a causal filter of input ``u``'s time series before the model sees it (an
  input delay, a first-order actuator lag): ``Effect.transform(u (T,), dt, theta) -> (T,)``. The
  model stays Markov in ``(x, u)``; the estimators of a corrected prior are fed the filtered
  input (a pre-filter a firmware can run too).

Every parameter has its physical range (``Effect.lower``, ``Effect.upper``): friction, drag and
damping coefficients are >= 0, time constants and delays >= 0, a gain keeps the actuator's
direction (``1 + gain > 0``); the fits enforce it (bounded least squares), so no effect is ever
selected with a non-physical sign. An effect that is nonlinear in its parameter (a delay, a
saturation level) may name ``starts``: values at which the selection also linearises it.

An effect with several parameters is a *group* of one-parameter columns (``Effect.group``) that
the selection enters and reports together, e.g. the quadrotor's ``thrust_response``
``(k T - a) / tau`` = ``(k/tau) T - (1/tau) a``: each column alone explains nothing when the two
nearly cancel (hover: ``k T ~ a + g``), their difference is the signature.

The corrected dynamics are ``f(x, u + sum du, p + sum dp) + sum direct``, written once against the
``ops`` backend (:func:`corrected_dynamics`), so a corrected prior runs in numpy, torch and CasADi
like any system, and an effect's regression feature is an exact CasADi derivative.

The kinds themselves live by family: the generic ones, derived from any system's structure
(friction, drag, actuator, bias, one per prior parameter), in
:mod:`~learnest_codegen.diagnosis.generic_effects`; those of particular built-in systems in
:mod:`~learnest_codegen.diagnosis.system_effects`. This module holds what they share: the
:class:`Effect`, the structure of the prior they are derived from, the registry and
:func:`library`, and the corrected dynamics.

Systems may add their own kinds: :func:`register_system_effects` (built-in systems) or
``System(..., diagnosis=DiagnosisHints(effects=fn))`` in a user's system file, with
``fn(system, context) -> list[Effect]``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import casadi as cs

from ..errors import UnknownNameError
from ..systems import System

# term(ops, x: list, u: list, theta) -> value added to the channel's target
Term = Callable[..., object]


@dataclass(frozen=True)
class Effect:
    """One candidate effect with a single parameter.

    Attributes
    ----------
    kind : a key of :data:`KINDS` or a system-specific kind.
    state : the state whose derivative it primarily acts on.
    channel : ``"input:<u>"``, ``"param:<p>"`` or ``"direct:<s>"``.
    param : name of its parameter (``"c"``, ``"k"``, ``"gain"``, ``"dm_c"`` ...).
    unit : unit of the parameter.
    term : ``term(ops, x, u, theta)``, the value added to the channel's target.
    description : one line for reports.
    lower, upper : the parameter's physical range (``-inf, inf``: any sign).
    starts : parameter values besides 0 at which the selection linearises the effect.
    transform : for a ``filter:<u>`` channel, ``transform(u (T,), dt, theta) -> (T,)``.
    derived : ``fn(theta) -> {name: value}``, physical quantities to report beside ``theta``.
    """

    kind: str
    state: str
    channel: str
    param: str
    unit: str
    term: Term | None = field(compare=False, repr=False)
    description: str = ""
    variable: str = ""  # the state it depends on, when not ``state`` (drag on vx acting on ax')
    group: str = ""  # effects of one group are selected together (one multi-parameter effect)
    lower: float = -math.inf
    upper: float = math.inf
    starts: tuple[float, ...] = ()
    transform: Callable | None = field(default=None, compare=False, repr=False)
    derived: Callable | None = field(default=None, compare=False, repr=False)

    @property
    def is_filter(self) -> bool:
        return self.channel.startswith("filter:")

    def physical(self, theta: float, tol: float = 1e-9) -> bool:
        """Whether ``theta`` lies in the parameter's physical range (to ``tol`` of its scale)."""
        slack = tol * max(1.0, abs(theta))
        return self.lower - slack <= theta <= self.upper + slack

    @property
    def name(self) -> str:
        """A unique, readable key, e.g. ``viscous_friction(pdot via F)``, ``quadratic_drag(vx on ax)``."""
        how, target = self.channel.split(":", 1)
        via = {"input": f" via {target}", "param": f" via {target}", "filter": f" via {target}",
               "direct": ""}[how]
        on = f"{self.variable} on " if self.variable and self.variable != self.state else ""
        return f"{self.kind}({on}{self.state}{via})"

    def to_json(self) -> dict:
        return {"kind": self.kind, "state": self.state, "channel": self.channel, "param": self.param,
                "unit": self.unit, "name": self.name, "description": self.description,
                "range": [_finite(self.lower), _finite(self.upper)]}


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


@dataclass(frozen=True)
class LibraryContext:
    """What the library builders need to know beyond the system.

    Attributes
    ----------
    velocity_states : states that friction and drag depend on.
    targets : per velocity state, the state whose derivative the force changes: itself when it
        is a residual state, else the residual state ending its kinematic chain (a quadrotor's
        drag on ``vx`` changes ``ax'`` when the model carries the acceleration as a state).
    coulomb_scale : per velocity state, the smoothing speed ``v_s`` of ``tanh(v / v_s)``
        (units of the state); :func:`default_context` takes 2 % of a typical speed.
    input_max : per input, the largest ``|u|`` over the data (the saturation kind's scale).
    dt : the sample period [s] (the delay and lag kinds' scale).
    """

    velocity_states: tuple[str, ...]
    coulomb_scale: Mapping[str, float]
    targets: Mapping[str, str] = field(default_factory=dict)
    input_max: Mapping[str, float] = field(default_factory=dict)
    dt: float = 0.01


KindBuilder = Callable[[System, LibraryContext], list]
KINDS: dict[str, KindBuilder] = {}
# physical parameters derived from a multi-parameter effect's fitted ones: group -> fn(params) -> dict
DERIVED: dict[str, Callable[[Mapping[str, float]], dict]] = {}
_SYSTEM_EFFECTS: dict[str, KindBuilder] = {}


def register_kind(name: str):
    """Decorator: register ``fn(system, context) -> list[Effect]`` as the generic kind ``name``."""
    def register(fn: KindBuilder) -> KindBuilder:
        KINDS[name] = fn
        return fn
    return register


def register_system_effects(system_name: str, builder: KindBuilder) -> KindBuilder:
    """Add system-specific effects to the library of ``system_name`` (e.g. a battery thrust loss)."""
    _SYSTEM_EFFECTS[system_name] = builder
    return builder


# -- structure of the prior ------------------------------------------------------------------------
_RATE = re.compile(r"/\s*s$|/\s*sec$|per\s*s$")
_MASS = re.compile(r"^(m|mass.*|m_.*|inertia.*|i|i_.*|j|j_.*|i[xyz]{1,2}|j[xyz]{1,2})$", re.IGNORECASE)


def velocity_states(system: System) -> dict[str, str]:
    """Velocity states (unit a rate, ``m/s``, ``rad/s``; or ``System.diagnosis.velocity_states``) that a
    residual can act on, each mapped to the state whose derivative a force on it changes: itself
    if it is a residual state, else the residual state that ends its kinematic chain."""
    residual = system.residual_state_names
    chain_end = {n: c.states[-1] for c in system.kinematic_chains for n in c.states
                 if c.states[-1] in residual}
    declared = system.diagnosis.velocity_states
    units = {s.name: s.unit.strip() for s in system.states}
    names = declared if declared is not None else [n for n in system.state_names if _RATE.search(units[n])]
    out = {}
    for n in names:
        if n in residual:
            out[n] = n
        elif n in chain_end:
            out[n] = chain_end[n]
    return out


def mass_params(system: System) -> tuple[str, ...]:
    """Prior parameters that are masses or inertias (by name, or ``System.diagnosis.mass_params``)."""
    declared = system.diagnosis.mass_params
    if declared is not None:
        return tuple(declared)
    return tuple(p for p in system.params if _MASS.match(p))


def input_reach(system: System) -> dict[str, tuple[str, ...]]:
    """For each state, the inputs whose prior path structurally reaches its derivative."""
    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    f = system.f(x, u)
    return {s: tuple(n for j, n in enumerate(system.input_names) if cs.depends_on(f[i], u[j]))
            for i, s in enumerate(system.state_names)}


def input_orientation(system: System, points: int = 64) -> dict[tuple[str, str], int]:
    """``(state, input) -> +1 / -1 / 0``: the sign of ``d state' / d input`` under the prior, when it
    is the same at random points (seeded; states and inputs over +-3) and not zero, else 0.

    A friction acting "as a force on input u" opposes the motion only if ``u`` pushes that
    velocity forward; with ``-1`` the term's sign is flipped, with ``0`` (a cart force's effect on
    a pole's angular acceleration changes sign with the angle) no such effect is offered.
    """
    import numpy as np

    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    jac = cs.Function("dfdu", [x, u], [cs.jacobian(system.f(x, u), u)])
    rng = np.random.default_rng(0)
    signs = np.array([np.sign(np.asarray(jac(rng.uniform(-3, 3, system.nx), rng.uniform(-3, 3, system.nu))))
                      for _ in range(points)])
    out = {}
    for i, s in enumerate(system.state_names):
        for j, n in enumerate(system.input_names):
            col = signs[:, i, j]
            out[(s, n)] = int(col[0]) if np.all(col == col[0]) else 0
    return out


def default_context(system: System, speed_scale: Mapping[str, float] | None = None,
                    input_max: Mapping[str, float] | None = None) -> LibraryContext:
    """Context from the system; ``speed_scale`` (typical |v| per velocity state, e.g. the RMS
    over the data) sets the Coulomb smoothing ``v_s = 0.02 * scale`` (default scale 1);
    ``input_max`` the largest ``|u|`` per input (default 1)."""
    vel = velocity_states(system)
    scale = {v: 0.02 * float((speed_scale or {}).get(v, 1.0)) or 0.02 for v in vel}
    umax = {n: float((input_max or {}).get(n, 1.0)) or 1.0 for n in system.input_names}
    return LibraryContext(tuple(vel), scale, vel, umax, float(system.dt))


# Order matters only for ties: of two candidates with the same signature on the data the first
# is kept and the other reported as its alias (e.g. the ground robot's drag coefficient C_D
# aliases quadratic drag on v), so the physical kinds come before raw parameters.
KIND_ORDER = ("viscous_friction", "coulomb_friction", "quadratic_drag", "actuator_gain",
              "actuator_offset", "dead_zone", "saturation", "back_emf", "input_delay", "actuator_lag",
              "bias", "mass", "parameter")


def library(system: System, context: LibraryContext | None = None,
            kinds: Sequence[str] | None = None) -> list[Effect]:
    """All candidate effects of ``system``: the generic kinds, then the system's own.

    Parameters
    ----------
    system : the system whose prior the effects modify.
    context : velocity states and Coulomb smoothing (default: :func:`default_context`).
    kinds : restrict to these kinds (default: all, including system-specific ones).
    """
    context = context or default_context(system)
    unknown = [k for k in (kinds or ()) if k not in KINDS and k not in _system_kinds(system, context)]
    if unknown:
        raise UnknownNameError(f"unknown effect kinds {unknown}; choose from {list(KIND_ORDER)} "
                               f"or the system's own")
    effects = [e for k in KIND_ORDER for e in KINDS[k](system, context)]
    effects += _system_effects(system, context)
    if kinds:
        effects = [e for e in effects if e.kind in kinds]
    seen, unique = set(), []
    for e in effects:
        if e.name not in seen:
            seen.add(e.name)
            unique.append(e)
    return unique


def _system_effects(system: System, context: LibraryContext) -> list[Effect]:
    out = []
    if system.name in _SYSTEM_EFFECTS:
        out += list(_SYSTEM_EFFECTS[system.name](system, context))
    user = system.diagnosis.effects
    if callable(user):
        out += list(user(system, context))
    return out


def _system_kinds(system: System, context: LibraryContext) -> set[str]:
    return {e.kind for e in _system_effects(system, context)}


def corrected_dynamics(system: System, effects: Sequence[Effect], thetas: Sequence) -> Callable:
    """The prior plus ``effects`` with parameters ``thetas``, as a backend-generic dynamics fn.

    ``thetas`` may be floats (a corrected model) or CasADi symbols (regression features). Returns
    ``fn(ops, x, u, p) -> list`` suitable for ``System.dynamics``.
    """
    if len(effects) != len(thetas):
        raise ValueError(f"corrected_dynamics: {len(effects)} effects but {len(thetas)} parameters")
    states, inputs, prior = system.state_names, system.input_names, system.dynamics
    effects, thetas = list(effects), list(thetas)

    def dynamics(ops, x, u, p):
        u2, p2, extra = list(u), dict(p), [0.0] * len(states)
        for effect, theta in zip(effects, thetas):
            how, target = effect.channel.split(":", 1)
            if how == "filter":  # acts on the input's time series, before the model (filter_inputs)
                continue
            value = effect.term(ops, x, u, theta)
            if how == "input":
                j = inputs.index(target)
                u2[j] = u2[j] + value
            elif how == "param":
                p2[target] = p2[target] + value
            elif "," in target:
                for name, v in zip(target.split(","), value):
                    i = states.index(name)
                    extra[i] = extra[i] + v
            else:
                i = states.index(target)
                extra[i] = extra[i] + value
        return [a + b for a, b in zip(prior(ops, x, u2, p2), extra)]

    return dynamics


def filter_inputs(system: System, effects: Sequence[Effect], thetas: Sequence[float], u, dt: float):
    """``u (T, nu)`` through the ``filter:<u>`` effects (in library order), as the corrected prior
    sees it; the other effects are ignored. A copy; ``u`` itself when there is no filter."""
    import numpy as np

    pairs = [(e, float(t)) for e, t in zip(effects, thetas) if e.is_filter]
    if not pairs:
        return u
    out = np.array(u, dtype=float, copy=True)
    for e, theta in pairs:
        j = system.input_names.index(e.channel.split(":", 1)[1])
        out[:, j] = e.transform(out[:, j], dt, theta)
    return out


def corrected_system(system: System, effects: Sequence[Effect], thetas: Sequence[float]) -> System:
    """``system`` whose prior includes ``effects`` with parameters ``thetas`` (floats).

    The true dynamics (for simulation) are unchanged. ``filter:<u>`` effects are not part of
    the dynamics: feed the corrected system :func:`filter_inputs` of the commands.
    """
    import dataclasses

    dynamics = corrected_dynamics(system, effects, [float(t) for t in thetas])
    true = system.true_dynamics or system.dynamics
    return dataclasses.replace(system, dynamics=dynamics, true_dynamics=true)


def describe_library(effects: Sequence[Effect]) -> str:
    """A plain-text listing (for ``learnest diagnose --list-effects``)."""
    rows = [("effect", "kind", "acts on", "channel", "parameter [unit]", "range")]
    rows += [(e.name, e.kind, f"{e.state}'", e.channel, f"{e.param} [{e.unit}]", _range(e)) for e in effects]
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def _range(e: Effect) -> str:
    if math.isinf(e.lower) and math.isinf(e.upper):
        return "any"
    if math.isinf(e.upper):
        return f">= {e.lower:g}"
    if math.isinf(e.lower):
        return f"<= {e.upper:g}"
    return f"[{e.lower:g}, {e.upper:g}]"
