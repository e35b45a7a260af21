"""Effects of particular built-in systems, registered into the library of their system.

The generic kinds of :mod:`~learnest_codegen.diagnosis.effects` are derived from any system's
structure; the terms here need to know what a system's states and inputs mean (the quadrotor's
commanded thrust, its battery voltage). A user's system file adds its own through
``System.diagnosis.effects`` instead.
"""

from __future__ import annotations

from typing import Mapping

from ..systems import System
from .effects import DERIVED, Effect, LibraryContext, register_system_effects


def _quadrotor_effects(system: System, ctx: LibraryContext) -> list:
    """The quadrotor's prior (a triple integrator, ``adot = 0``) has no thrust path at all, so the
    generic input effects do not apply. Per axis ``i`` (acting on ``a_i'``):

    * ``thrust``: ``theta T_i`` - the commanded thrust the prior ignores [m/s^3 per unit throttle];
    * ``battery_thrust_loss``: ``theta T_i (vbat - V_NOM)`` - thrust per command falls as the
      battery drains (``V_NOM = 3.5 V``) [m/s^3 per unit throttle per V];
    * ``motor_lag``: ``-theta a_i`` - the acceleration relaxing towards the command with the
      motors' time constant, ``theta = 1 / tau`` [1/s];
    * ``thrust_response`` (all axes, three parameters, one group): the motors' first-order
      response to the commanded thrust, with the rotor drag in the force balance,
      ``a' = (k_T (vbat / V_NOM) T - g e3 - k_D v - a) / tau``, written linearly as
      ``(k_T/tau) (vbat / V_NOM) T - (1/tau) (a + g e3) - (k_D/tau) v``: a shared thrust gain over
      time constant [m/s^3 per unit throttle], a shared rate ``1/tau`` [1/s] and drag over time
      constant [1/s^2]. In flight the terms nearly cancel (``k_T T ~ a + g e3 + k_D v``), so only
      together do they explain the jerk; the diagnosis also reports ``tau``, ``k_T`` and ``k_D``.
      The drag is part of the group because without it the thrust balance is off by ``k_D v``,
      which on a 1 m/s flight is several times the jerk itself, and the two-parameter fit then
      lands on the degenerate direction ``k_T/tau ~ k_T (1/tau)`` (seen on the simulated
      quadrotor: ``k/tau = -35``, ``1/tau = -3``). The drag's own ``-k_D a`` is absorbed in
      ``1/tau`` (``1/tau + k_D``, 0.35 of 20 1/s in the simulation).

    Every parameter is >= 0: a thrust gain, a time constant and a drag are positive, and thrust
    per command rises with the battery voltage.
    """
    try:
        from ..systems.quadrotor import GRAVITY, V_NOM
    except ImportError:  # the system file may be a user's copy; the constants are the same
        GRAVITY, V_NOM = 9.81, 3.5
    out = []
    names = system.state_names
    axes = [(f"a{a}", f"T{a}") for a in ("x", "y", "z")]
    if not all(s in names for s, _ in axes) or not all(t in system.input_names for _, t in axes) \
            or "vbat" not in system.input_names:
        return out
    jb = system.input_names.index("vbat")
    for s, t in axes:
        i, j = names.index(s), system.input_names.index(t)
        out += [
            Effect("thrust", s, f"direct:{s}", "k", "(m/s^2)/s", lambda ops, x, u, th, j=j: th * u[j],
                   f"commanded thrust {t} on {s}'", t, lower=0.0),
            Effect("battery_thrust_loss", s, f"direct:{s}", "k_V", "(m/s^2)/s/V",
                   lambda ops, x, u, th, j=j: th * u[j] * (u[jb] - V_NOM),
                   f"thrust {t} scaled by the battery voltage's deviation from {V_NOM} V", "vbat", lower=0.0),
            Effect("motor_lag", s, f"direct:{s}", "1/tau", "1/s", lambda ops, x, u, th, i=i: -th * x[i],
                   f"{s} relaxes with the motors' time constant", lower=0.0),
        ]
    acc = [names.index(s) for s, _ in axes]
    thr = [system.input_names.index(t) for _, t in axes]
    target = "direct:" + ",".join(s for s, _ in axes)
    out += [
        Effect("thrust_response", "az", target, "k/tau", "(m/s^2)/s",
               lambda ops, x, u, th: [th * u[j] * u[jb] / V_NOM for j in thr],
               "thrust response: gain over time constant on the commanded thrust (vbat / V_NOM) T",
               "T", group="thrust_response", lower=0.0),
        Effect("thrust_response", "az", target, "1/tau", "1/s",
               lambda ops, x, u, th: [-th * x[i] - (th * GRAVITY if k == 2 else 0.0)
                                      for k, i in enumerate(acc)],
               "thrust response: the acceleration (plus gravity) relaxing at rate 1/tau",
               "a", group="thrust_response", lower=0.0),
        Effect("thrust_response", "az", target, "k_D/tau", "1/s^2",
               lambda ops, x, u, th: [-th * x[i - 3] for i in acc],
               "thrust response: rotor drag k_D v in the thrust balance, over tau",
               "v", group="thrust_response", lower=0.0),
    ]
    return out


register_system_effects("quadrotor", _quadrotor_effects)


def _thrust_response_physical(p: Mapping[str, float]) -> dict:
    """``tau``, ``k_T``, ``k_D`` from the fitted ``c = k_T/tau``, ``b = 1/tau + k_D``, ``d = k_D/tau``.

    The rate column also carries the drag's ``-k_D a`` (see :func:`_quadrotor_effects`), so
    ``tau`` solves ``d tau^2 - b tau + 1 = 0`` (the root near ``1/b``); with no drag ``tau = 1/b``.
    """
    import math

    b, c, d = p["1/tau"], p["k/tau"], p["k_D/tau"]
    if b <= 0:
        return {}
    disc = b * b - 4 * d
    tau = 1.0 / b if abs(d) < 1e-12 * b * b or disc < 0 else (b - math.sqrt(disc)) / (2 * d)
    return {"tau": tau, "k_T": c * tau, "k_D": d * tau}


DERIVED["thrust_response"] = _thrust_response_physical
