"""Explicit Runge-Kutta steps written once for numpy, torch and CasADi values."""

from __future__ import annotations

from typing import Callable


def rk4_step(f: Callable, x, u, dt: float):
    """One classical RK4 step of ``xdot = f(x, u)`` with ``u`` held over the step."""
    k1 = f(x, u)
    k2 = f(x + (0.5 * dt) * k1, u)
    k3 = f(x + (0.5 * dt) * k2, u)
    k4 = f(x + dt * k3, u)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
