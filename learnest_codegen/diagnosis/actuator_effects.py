"""Actuator dynamics: what a real drive does between the command and the force.

Registered into :data:`~learnest_codegen.diagnosis.effects.KINDS` on import, one candidate per
input that drives a residual state (and, for the back-EMF, per velocity it drives with one sign):

===============  ==================================================  ====================  =============
kind             what the model sees instead of the command ``u``     channel               range
===============  ==================================================  ====================  =============
dead_zone        ``u - clip(u, -theta, theta)``: nothing inside       ``input:<u>``         ``[0, max|u|]``
                 ``+-theta``, the rest shifted towards zero
saturation       ``clip(u, -L, L)``, ``L = (1 - theta) max|u|``       ``input:<u>``         ``[0, 0.9]``
back_emf         ``u - theta v |u|``: the drive fades with the speed  ``input:<u>``         ``theta >= 0``
                 ``v`` it produces (a motor's force-speed line)
input_delay      ``u(t - theta)``, whole and fractional samples       ``filter:<u>``        ``[0, 30 dt]``
actuator_lag     ``u`` through ``theta s' = u - s`` (first order)    ``filter:<u>``        ``[0, 100 dt]``
===============  ==================================================  ====================  =============

A dead zone, a saturation and a back-EMF are static maps of ``(x, u)``: they are input-channel
terms like a gain. A delay and a lag depend on the input's past, which a model Markov in
``(x, u)`` cannot hold, so they are ``filter:<u>`` effects (see
:mod:`~learnest_codegen.diagnosis.effects`): the command's time series is filtered before the
model sees it, exactly (the held command's delayed value is the linear interpolation of the
two samples it straddles; the lag is discretised exactly for a held input and averaged over the
step, as the RK4 step holds the input). A delay and a lag are equal to first order (``u - theta
u'``), so both are linearised also at a few ``starts`` (2-10 samples) where they differ.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import lfilter

from ..systems import System
from .effects import Effect, LibraryContext, input_orientation, input_reach, register_kind
from .generic_effects import _driving_inputs, _input_unit, _primary_state, _unit


def _clip(ops, u, level):
    """``clip(u, -level, level)`` with ``abs`` only (every backend has it)."""
    return 0.5 * (ops.abs(u + level) - ops.abs(u - level))


@register_kind("dead_zone")
def _dead_zone(system: System, ctx: LibraryContext) -> list:
    out = []
    for j, n in _driving_inputs(system):
        umax = ctx.input_max.get(n, 1.0)
        out.append(Effect("dead_zone", _primary_state(system, n), f"input:{n}", "width",
                          _input_unit(system, n), lambda ops, x, u, th, j=j: -_clip(ops, u[j], th),
                          f"input {n} has no effect within +-width and is shifted by it outside",
                          lower=0.0, upper=umax))
    return out


@register_kind("saturation")
def _saturation(system: System, ctx: LibraryContext) -> list:
    out = []
    for j, n in _driving_inputs(system):
        umax = ctx.input_max.get(n, 1.0)
        # the clip's edge just above the largest command: at cut 0 the term is then zero with zero
        # slope in u even where a torque-limited command sits exactly at its limit (at the edge
        # itself |u - L| has no slope, and every input-filter feature there would be halved)
        edge = umax * (1.0 + 1e-9)

        def term(ops, x, u, th, j=j, edge=edge):
            return _clip(ops, u[j], edge * (1.0 - th)) - u[j]

        out.append(Effect("saturation", _primary_state(system, n), f"input:{n}", "cut", "1", term,
                          f"input {n} saturates at (1 - cut) times its largest value ({umax:.4g})",
                          lower=0.0, upper=0.9, starts=(0.1, 0.25, 0.5),
                          derived=lambda th, umax=umax: {"level": umax * (1.0 - th)}))
    return out


@register_kind("back_emf")
def _back_emf(system: System, ctx: LibraryContext) -> list:
    reach, sign = input_reach(system), input_orientation(system)
    out = []
    for v in ctx.velocity_states:
        target = ctx.targets.get(v, v)
        i = system.state_names.index(v)
        for n in reach[target]:
            s = sign[(target, n)]
            if s == 0:
                continue
            j = system.input_names.index(n)
            out.append(Effect("back_emf", target, f"input:{n}", "k_e", f"1/({_unit(system, v)})",
                              lambda ops, x, u, th, i=i, j=j, s=s: -s * th * x[i] * ops.abs(u[j]),
                              f"the drive through {n} falls by k_e |{n}| per unit of {v} (back-EMF)",
                              v, lower=0.0))
    return out


def delay(u: np.ndarray, dt: float, theta: float) -> np.ndarray:
    """``u`` delayed by ``theta`` [s] >= 0: ``(1 - a) u[k - n] + a u[k - n - 1]`` with
    ``theta / dt = n + a``; samples before the start hold the first value."""
    steps = max(float(theta), 0.0) / dt
    n = int(math.floor(steps + 1e-9))
    a = min(max(steps - n, 0.0), 1.0)
    if n == 0 and a == 0.0:
        return np.array(u, dtype=float, copy=True)
    padded = np.concatenate([np.full(n + 1, u[0]), u])  # padded[k + 1] = u[k - n]
    T = len(u)
    now, earlier = padded[1:T + 1], padded[:T]
    return (1.0 - a) * now + a * earlier


def lag(u: np.ndarray, dt: float, theta: float) -> np.ndarray:
    """``u`` through the first-order lag ``theta s' = u - s`` (``s(0) = u[0]``, the input held over
    each step), averaged over each step [t_k, t_k+1]: what an RK4 step holding the input sees."""
    tau = max(float(theta), 0.0)
    if tau == 0.0:
        return np.array(u, dtype=float, copy=True)
    e = math.exp(-dt / tau)
    s = lfilter([0.0, 1.0 - e], [1.0, -e], u, zi=[u[0]])[0]  # s[k] at t_k
    return u + (s - u) * (tau / dt) * (1.0 - e)


@register_kind("input_delay")
def _input_delay(system: System, ctx: LibraryContext) -> list:
    dt = ctx.dt
    return [Effect("input_delay", _primary_state(system, n), f"filter:{n}", "delay", "s", None,
                   f"input {n} acts delay s late (whole and fractional samples)",
                   lower=0.0, upper=30 * dt, starts=(2 * dt, 5 * dt, 10 * dt), transform=delay)
            for _, n in _driving_inputs(system)]


@register_kind("actuator_lag")
def _actuator_lag(system: System, ctx: LibraryContext) -> list:
    dt = ctx.dt
    return [Effect("actuator_lag", _primary_state(system, n), f"filter:{n}", "tau", "s", None,
                   f"input {n} reaches the system through a first-order lag of time constant tau",
                   lower=0.0, upper=100 * dt, starts=(3 * dt, 10 * dt), transform=lag)
            for _, n in _driving_inputs(system)]
