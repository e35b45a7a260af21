"""The kinematic bicycle that the ground robot and the RC car share: its states and its motion.

State ``[x, y, v, psi]``: the world position of a point on the car's axis [m], that point's
speed [m/s] and the heading [rad]. With the front steering angle ``delta`` and the point
``l_r`` ahead of the rear axle on a wheelbase ``l``, its slip angle is
``beta = atan(l_r tan(delta) / l)`` and::

    xdot = v cos(psi + beta),   ydot = v sin(psi + beta),
    vdot = accel,               psidot = v cos(beta) tan(delta) / l.

How ``accel`` and ``delta`` follow from a vehicle's inputs is that vehicle's own model.
"""

from __future__ import annotations

from .base import Signal


def bicycle_states(point: str = "position", speed: str = "speed",
                   heading: str = "heading") -> tuple[Signal, ...]:
    """The states ``[x, y, v, psi]``, described for the ``point`` whose position they are."""
    return (Signal("x", "m", f"{point}, world x"), Signal("y", "m", f"{point}, world y"),
            Signal("v", "m/s", speed), Signal("psi", "rad", heading))


def kinematic_bicycle(ops, x, accel, delta, l_r, wheelbase) -> list:
    """``xdot`` of the point ``l_r`` ahead of the rear axle, given its ``vdot = accel`` and the
    steering angle ``delta`` [rad] (``wheelbase`` [m])."""
    _, _, v, psi = x
    beta = ops.arctan(l_r * ops.tan(delta) / wheelbase)
    return [v * ops.cos(psi + beta), v * ops.sin(psi + beta), accel,
            v * ops.cos(beta) * ops.tan(delta) / wheelbase]
