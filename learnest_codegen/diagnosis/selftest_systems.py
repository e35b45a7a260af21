"""Systems the self-test diagnoses besides the built-in ones, written as a user would write them.

``pendulum``: a torque-driven physical pendulum, ``J q'' = tau - mgl sin q``, with the inertia
``J`` [kg m^2] and the gravity torque ``mgl`` [N m] as separate parameters (as a user's system
file declares them), the angle measured by an encoder (std 2 mrad) and the motor torque known.
Its prior has both wrong by large factors (``J`` 0.05 against 0.1, ``mgl`` 1.0 against 1.6), and
the real joint has Coulomb friction (see :data:`PENDULUM_FRICTION`), which the prior leaves out:
the situation a diagnosis meets on a real pendulum. The excitation is a multisine torque around
the natural frequency (0.64 Hz with the true parameters), so that inertia and gravity leave
different signatures.
"""

from __future__ import annotations

import numpy as np

from ..systems import DiagnosisHints, KinematicChain, NoiseModel, Signal, System

PENDULUM_PRIOR = {"J": 0.05, "mgl": 1.0}  # [kg m^2], [N m]
PENDULUM_TRUE = {"J": 0.1, "mgl": 1.6}
PENDULUM_FRICTION = 0.2  # Coulomb friction of the real joint [N m]
FRICTION_SPEED = 0.01  # [rad/s]: the truth's friction is tanh(qdot / 0.01), close to a sign step


def _dynamics(ops, x, u, p):
    q, qdot = x
    return [qdot, (u[0] - p["mgl"] * ops.sin(q)) / p["J"]]


def _excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    freqs = np.array([0.25, 0.6, 1.1, 2.3]) * rng.uniform(0.9, 1.1, 4)  # [Hz]
    amps = np.array([0.9, 0.7, 0.5, 0.4])  # [N m]
    phases = rng.uniform(0, 2 * np.pi, 4)
    return np.sum(amps * np.sin(2 * np.pi * freqs * t[:, None] + phases), axis=1)[:, None]


def pendulum(friction: float = PENDULUM_FRICTION) -> System:
    """The pendulum with the prior's parameters; its truth adds ``friction`` N m of Coulomb friction."""
    def true_dynamics(ops, x, u, p):
        return _dynamics(ops, x, [u[0] - friction * ops.tanh(x[1] / FRICTION_SPEED)], p)

    return System(
        name="pendulum",
        states=(Signal("q", "rad"), Signal("qdot", "rad/s")),
        inputs=(Signal("tau", "N m"),),
        outputs=(Signal("q", "rad"),),
        params=PENDULUM_PRIOR, true_params=PENDULUM_TRUE,
        dynamics=_dynamics, true_dynamics=true_dynamics,
        measurement=lambda ops, x, u, p: [x[0]],
        noise=NoiseModel(measurement_std=(0.002,), state_std=(0.002, 0.02),
                         process_std=(1e-3, 5e-2), initial_std=(0.05, 0.2)),
        dt=0.01, duration=30.0, x0=(0.2, 0.0),
        excitation=_excitation,
        kinematic_chains=(KinematicChain("q", ("q", "qdot")),),
        diagnosis=DiagnosisHints(mass_params=("J",)),
    )


SMALL_FRICTION = 0.05  # [N m], a quarter of PENDULUM_FRICTION
SYSTEMS = {"pendulum": pendulum, "pendulum_small_friction": lambda: pendulum(SMALL_FRICTION)}
