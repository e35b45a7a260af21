"""Cartpole of the paper's eq. (13) in Florian's correct form (Barto et al.'s cartpole).

State ``[p, pdot, alpha, alphadot]`` with ``alpha`` measured from the upright; input the force
``F`` on the cart; measurement ``[p, alpha]``. The prior model believes the cart weighs 1.0 kg,
the true cart weighs 1.5 kg.
"""

from __future__ import annotations

import numpy as np

from .base import KinematicChain, NoiseModel, ResidualStructure, Signal, System


def dynamics(ops, x, u, p):
    """Continuous cartpole dynamics (Florian's correct form); ``l`` is the pole's half-length.

    The paper's eq. (13) as printed drops the ``1/(m_c + m_p)`` on the force term of
    ``alpha_dd`` (it adds a force to an acceleration); this is the form of its cited source,
    the Lagrangian of a cart and a uniform pole, which ``tests/test_systems.py`` checks.
    """
    _, pdot, alpha, alphadot = x
    (force,) = u
    mc, mp, l, g = p["m_c"], p["m_p"], p["l"], p["g"]
    sin_a, cos_a = ops.sin(alpha), ops.cos(alpha)
    total = mc + mp
    alpha_dd = (g * sin_a - cos_a * (force + mp * l * alphadot**2 * sin_a) / total) / (
        l * (4.0 / 3.0 - mp * cos_a**2 / total)
    )
    p_dd = (force + mp * l * (alphadot**2 * sin_a - alpha_dd * cos_a)) / total
    return [pdot, p_dd, alphadot, alpha_dd]


def measurement(ops, x, u, p):
    """``y = C x`` with ``C = [[1, 0, 0, 0], [0, 0, 1, 0]]``."""
    return [x[0], x[2]]


# Excitation: a multisine force of cosines with random signs and +-10 % frequency jitter per
# seed. A term A*cos(w t) adds A*sin(w t)/(M w) to the cart velocity (zero mean), whereas a sine
# with a random phase adds a constant velocity and the cart drifts away; so the cart stays
# within about a metre while every state keeps moving (informative for training) and the pole
# swings through large angles (eq. (13) is valid for any alpha).
_AMPLITUDES_N = np.array([4.0, 3.0, 2.0, 1.0])
_FREQUENCIES_HZ = np.array([0.4, 0.9, 1.7, 3.1])


def excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Force ``F(t)`` [N] of shape ``(len(t), 1)``."""
    signs = rng.choice([-1.0, 1.0], size=_AMPLITUDES_N.size)
    freqs = _FREQUENCIES_HZ * rng.uniform(0.9, 1.1, size=_FREQUENCIES_HZ.size)
    return (np.cos(2.0 * np.pi * np.outer(t, freqs)) @ (signs * _AMPLITUDES_N))[:, None]


CARTPOLE = System(
    name="cartpole",
    description="Cartpole, paper eq. (13); true cart mass 1.5 kg, prior 1.0 kg; y = [p, alpha].",
    states=(
        Signal("p", "m", "cart position"),
        Signal("pdot", "m/s", "cart velocity"),
        Signal("alpha", "rad", "pole angle from upright"),
        Signal("alphadot", "rad/s", "pole angular velocity"),
    ),
    inputs=(Signal("F", "N", "force on the cart"),),
    outputs=(Signal("p", "m", "cart position"), Signal("alpha", "rad", "pole angle")),
    params={"m_c": 1.0, "m_p": 0.1, "l": 0.5, "g": 9.81},
    true_params={"m_c": 1.5, "m_p": 0.1, "l": 0.5, "g": 9.81},
    dynamics=dynamics,
    measurement=measurement,
    noise=NoiseModel(
        measurement_std=(0.01, 0.01),
        state_std=(0.01, 0.01, 0.01, 0.01),
        process_std=(1e-4, 1e-3, 1e-4, 1e-3),
        initial_std=(0.05, 0.1, 0.05, 0.1),
    ),
    dt=0.002,
    duration=10.0,
    x0=(0.0, 0.0, 0.3, 0.0),
    excitation=excitation,
    periodic_states=("alpha",),
    # The cart's drive saturates well above the excitation's 10 N peak: a logged force beyond
    # it is a glitch, not a command (the estimators hold the last plausible one instead).
    input_limits=((-50.0, 50.0),),
    kinematic_chains=(KinematicChain("p", ("p", "pdot")), KinematicChain("alpha", ("alpha", "alphadot"))),
    residual=ResidualStructure(
        # Translation invariance: no force depends on where the cart is on the rail.
        inputs=("pdot", "alpha", "alphadot", "F"),
        # Unmodelled effects act on the cart, where the force acts (a heavier cart is the force
        # -Delta m_c * pdd): the net learns a force and the prior carries it to both accelerations.
        via=("F",),
        # ... and sees the prior's accelerations: given those, a mass error is nearly linear;
        # with gains on them, a mass error is a gain that barely varies.
        prior_features=("pdot", "alphadot"),
        prior_gains=True,
        # A level rail and a symmetric cart: pushed the other way, the cartpole does the mirror
        # image (true for any mass, friction or drag). Training adds the mirror image of every
        # pair; one run's excursions are lopsided, and the test run goes where the training run
        # did not.
        reflection=("p", "pdot", "alpha", "alphadot", "F"),
    ),
)
