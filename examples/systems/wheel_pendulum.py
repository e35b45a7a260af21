"""A pendulum balanced by a DC-motor-driven inertia wheel at its tip (a reaction-wheel pendulum).

States: the rod angle ``q`` [rad] from hanging down, its rate ``qdot`` [rad/s] and the wheel's
speed relative to the rod ``w`` [rad/s]. Input: the motor current ``i`` [A]. Measured: the rod
angle (an encoder) and the wheel speed (the motor's tachometer). With the motor torque
``tau = K_t i`` and the wheel bearing's friction ``tau_f = b_w w + t_c tanh(w / 0.5)``::

    qdot' = -k sin(q) - c qdot - (tau - tau_f) / J_p        (the reaction on the rod)
    w'    = (tau - tau_f) / J_w - qdot'                      (the wheel, relative to the rod)

The prior's torque constant is 20 % low (a datasheet value against the motor as wound) and it
knows no friction (``c = b_w = t_c = 0``); the truth has both. The residual therefore acts on
both rates, through the angle, the rates and the current.
"""

import numpy as np

from learnest_codegen import NoiseModel, Signal, System

J_P, J_W = 0.01, 0.001  # rod and wheel inertia [kg m^2]
K_T = 0.02  # torque constant [N m / A]


def dynamics(ops, x, u, p):
    q, qdot, w = x
    torque = p["K_t"] * u[0] - p["b_w"] * w - p["t_c"] * ops.tanh(2.0 * w)
    rod = -p["k"] * ops.sin(q) - p["c"] * qdot - torque / J_P
    return [qdot, rod, torque / J_W - rod]


def excitation(t, rng):
    """Two sines of random phase and frequency near the rod's resonance (4.5 rad/s), 1 A peak."""
    w1, w2 = rng.uniform(1.5, 2.5), rng.uniform(3.5, 5.5)
    p1, p2 = rng.uniform(0.0, 2.0 * np.pi, size=2)
    return (0.6 * np.sin(w1 * t + p1) + 0.4 * np.sin(w2 * t + p2))[:, None]


SYSTEM = System(
    name="wheel_pendulum",
    states=(Signal("q", "rad"), Signal("qdot", "rad/s"), Signal("w", "rad/s")),
    inputs=(Signal("i", "A"),),
    outputs=(Signal("q", "rad"), Signal("w", "rad/s")),
    params={"k": 20.0, "c": 0.0, "K_t": 0.8 * K_T, "b_w": 0.0, "t_c": 0.0},
    true_params={"k": 20.0, "c": 0.3, "K_t": K_T, "b_w": 2e-4, "t_c": 2e-4},
    dynamics=dynamics,
    measurement=lambda ops, x, u, p: [x[0], x[2]],
    noise=NoiseModel(measurement_std=(0.005, 0.05), state_std=(0.005, 0.02, 0.05),
                     process_std=(1e-3, 1e-2, 1e-2), initial_std=(0.1, 0.1, 0.1)),
    dt=0.01, duration=10.0, x0=(0.5, 0.0, 0.0),
    excitation=excitation,
    periodic_states=("q",),
)
