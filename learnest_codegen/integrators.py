"""Explicit Runge-Kutta steps written once for numpy, torch and CasADi values."""

from __future__ import annotations

from typing import Callable


def rk4_step(f: Callable, x, u, dt: float):
    """One classical RK4 step of ``xdot = f(x, u)`` with ``u`` held over the step."""
    return x + rk4_increment(f, x, u, dt)


def rk4_increment(f: Callable, x, u, dt: float):
    """:func:`rk4_step` less ``x``: the step's increment ``dt/6 (k1 + 2 k2 + 2 k3 + k4)``,
    without the rounding of adding it to ``x`` (training in float32 compares it with the
    observed increment)."""
    k1 = f(x, u)
    k2 = f(x + (0.5 * dt) * k1, u)
    k3 = f(x + (0.5 * dt) * k2, u)
    k4 = f(x + dt * k3, u)
    return (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def rk4_step_jacobian(f_jac: Callable, x, u, dt: float, eye):
    """One RK4 step and its Jacobian ``dx+/dx`` by the chain rule through the four stages.

    ``f_jac(x, u) -> (xdot, dxdot/dx)``; ``eye`` is the identity of the state's size. The step
    is :func:`rk4_step`'s expression; the Jacobian multiplies the stage Jacobians forward
    (``dk2/dx = J(x2) (I + dt/2 dk1/dx)``, ...), which keeps their sparsity where reverse or
    forward AD over the whole step does not.
    """
    k1, j1 = f_jac(x, u)
    k2, j2 = f_jac(x + (0.5 * dt) * k1, u)
    d2 = j2 @ (eye + (0.5 * dt) * j1)
    k3, j3 = f_jac(x + (0.5 * dt) * k2, u)
    d3 = j3 @ (eye + (0.5 * dt) * d2)
    k4, j4 = f_jac(x + dt * k3, u)
    d4 = j4 @ (eye + dt * d3)
    step = x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    return step, eye + (dt / 6.0) * (j1 + 2.0 * d2 + 2.0 * d3 + d4)
