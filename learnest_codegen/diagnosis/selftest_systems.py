"""Systems the self-test diagnoses besides the built-in ones, written as a user would write them.

``pendulum_swingup``, ``cart``, ``rc_car_damped`` and ``pendulum_rig`` follow at the end: a
torque-limited swing-up (the situation of a real pendulum), a cart with sharp Coulomb friction,
the DART car with a known rolling drag (for actuator dynamics on held commands), and the twin of
a lab pendulum whose torque may be applied a few milliseconds late.

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


def multisine(t: np.ndarray, rng: np.random.Generator, freqs, amps) -> np.ndarray:
    """``(T, 1)``: a sum of sines of amplitudes ``amps`` at the frequencies ``freqs`` [Hz], each
    frequency scaled by a draw in [0.9, 1.1] and each phase drawn, per run."""
    freqs = np.asarray(freqs, float) * rng.uniform(0.9, 1.1, len(freqs))
    phases = rng.uniform(0, 2 * np.pi, len(freqs))
    return np.sum(np.asarray(amps, float) * np.sin(2 * np.pi * freqs * t[:, None] + phases), axis=1)[:, None]


def _excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return multisine(t, rng, (0.25, 0.6, 1.1, 2.3), (0.9, 0.7, 0.5, 0.4))  # [Hz], [N m]


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


# -- a torque-limited swing-up (the real pendulum's situation) ------------------------------------
SWINGUP_TRUE = {"J": 0.2, "mgl": 1.6}  # [kg m^2], [N m]
SWINGUP_PRIOR = {"J": 0.07, "mgl": 0.5}  # both about 3x too small, as a user's first guess was
SWINGUP_FRICTION = 0.2  # Coulomb friction of the real joint [N m]
SWINGUP_TORQUE = 0.8  # the motor's torque limit [N m], half the gravity torque: it must pump


def _pumping(system: System, truth: dict, limit: float, dither: float, delay: float = 0.0):
    """The excitation of an energy-pumping swing-up, closed on the true pendulum (parameters
    ``truth``) with its torque applied ``delay`` [s] late (:func:`late_step`):

    ``tau = clip(k (E_ref - E) qdot + d(t), +-limit)`` with ``E = J qdot^2 / 2 + mgl (1 - cos q)``:
    the torque pushes along the motion while the energy is below its target and brakes above it;
    the target moves every 3 s between 50 % and 95 % of the energy at the top, ``k`` is drawn per
    run (10-20) and ``d`` is a three-tone multisine of ``dither`` N m per tone. The loop is
    simulated at the simulation's own accuracy, so replaying the torque open loop flies the same
    swing-up."""
    def excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        dt = float(t[1] - t[0])
        k = rng.uniform(10.0, 20.0)
        top = 2.0 * truth["mgl"]
        targets = rng.uniform(0.5, 0.95, size=int(t[-1] / 3.0) + 2) * top
        freqs, phases = np.array([0.3, 0.8, 1.7]) * rng.uniform(0.9, 1.1, 3), rng.uniform(0, 2 * np.pi, 3)
        d = dither * np.sum(np.sin(2 * np.pi * freqs * t[:, None] + phases), axis=1)
        x, u = np.array(system.x0, dtype=float), np.zeros((len(t), 1))
        for i in range(len(t)):
            energy = 0.5 * truth["J"] * x[1] ** 2 + truth["mgl"] * (1.0 - np.cos(x[0]))
            u[i, 0] = np.clip(k * (targets[int(t[i] / 3.0)] - energy) * x[1] + d[i], -limit, limit)
            if i < len(t) - 1:
                x = late_step(system, x, u[max(i - 1, 0)], u[i], dt, delay, t[i])
        return u

    return excitation


def _swingup(system: System):
    """The swing-up of a motor limited to 0.8 N m (:func:`_pumping`, a 0.05 N m dither): the
    torque saturates in the pumping phases and correlates with ``sign(qdot)`` by about
    +0.5-0.65, so a gain on the torque and a Coulomb friction nearly alias."""
    return _pumping(system, SWINGUP_TRUE, SWINGUP_TORQUE, 0.05)


def swingup_pendulum() -> System:
    """A pendulum swung up by a torque-limited motor (:func:`_swingup`); its prior has ``J`` and
    ``mgl`` about 3x too small and no friction, the truth has :data:`SWINGUP_FRICTION`."""
    import dataclasses

    def true_dynamics(ops, x, u, p):
        return _dynamics(ops, x, [u[0] - SWINGUP_FRICTION * ops.tanh(x[1] / FRICTION_SPEED)], p)

    base = dataclasses.replace(pendulum(), name="pendulum_swingup", params=SWINGUP_PRIOR,
                               true_params=SWINGUP_TRUE, true_dynamics=true_dynamics, duration=12.0,
                               x0=(0.1, 0.0))
    return dataclasses.replace(base, excitation=_swingup(base))


# -- a cart on a track with Coulomb friction ------------------------------------------------------
CART_FRICTION = 1.0  # [N], a sharp Coulomb friction: tanh(pdot / 1 mm/s)


def _cart_dynamics(ops, x, u, p):
    return [x[1], u[0] / p["m"]]


def _cart_excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return multisine(t, rng, (0.2, 0.5, 1.1, 2.3), (3.0, 2.1, 1.5, 0.9))  # [Hz], [N]


def cart() -> System:
    """A 1 kg cart pushed by a force [N] along a track, position measured (1 mm); the prior is
    ``m pdot' = F``, the truth adds :data:`CART_FRICTION` of sharp Coulomb friction."""
    def true_dynamics(ops, x, u, p):
        return _cart_dynamics(ops, x, [u[0] - CART_FRICTION * ops.tanh(x[1] / 1e-3)], p)

    return System(
        name="cart", states=(Signal("p", "m"), Signal("pdot", "m/s")), inputs=(Signal("F", "N"),),
        outputs=(Signal("p", "m"),), params={"m": 1.0}, true_params={"m": 1.0},
        dynamics=_cart_dynamics, true_dynamics=true_dynamics, measurement=lambda ops, x, u, p: [x[0]],
        noise=NoiseModel(measurement_std=(1e-3,), state_std=(1e-3, 0.01), process_std=(1e-4, 1e-2),
                         initial_std=(0.01, 0.1)),
        dt=0.01, duration=20.0, x0=(0.0, 0.0), excitation=_cart_excitation,
        kinematic_chains=(KinematicChain("p", ("p", "pdot")),))


# -- the DART car with a known rolling drag, for actuator dynamics on held commands ---------------
def _car_dynamics(ops, x, u, p):
    from ..systems.rc_car import bicycle

    throttle, steering = u
    return bicycle(ops, x, p["a_max"] * throttle - p["c_v"] * x[2], p["delta_max"] * steering, p)


def rc_car_damped() -> System:
    """The ``rc_car`` whose prior (and truth) has a rolling drag ``c_v v`` (2 1/s): it cruises
    at 2-4 m/s on its 10 Hz held commands instead of speeding up for ever, so the actuator
    dynamics of its throttle and steering (delay, lag, back-EMF) can be injected alone."""
    import dataclasses

    from ..systems.rc_car import RC_CAR

    params = {**RC_CAR.params, "c_v": 2.0}
    return dataclasses.replace(RC_CAR, name="rc_car_damped", params=params, true_params=params,
                               dynamics=_car_dynamics, true_dynamics=_car_dynamics)


# -- the twin of a torque-limited lab pendulum, its torque applied late ---------------------------
RIG_TRUE = {"J": 0.187, "mgl": 3.60}  # [kg m^2], [N m]: a plain regression on the rig's swing-ups
RIG_PRIOR = PENDULUM_PRIOR  # a user's first guess: both 3.6-3.7x too small, in nearly the same ratio
RIG_FRICTION = 0.195  # Coulomb friction [N m]; no viscous friction
RIG_TORQUE = 1.5  # the motor's torque limit [N m], 0.42 of the gravity torque: it must pump
RIG_DT = 0.006  # [s]
RIG_ENCODER = 5e-4  # angle noise [rad]: about a 4096-count encoder's quantisation (1.53 mrad / sqrt 12)


def late_step(system: System, x: np.ndarray, before, now, dt: float, delay: float, t: float = 0.0):
    """One sample of the true pendulum whose command ``now`` takes effect ``delay`` [s] late: the
    previous command ``before`` acts for the first ``delay`` of the step (``0 <= delay < dt``)."""
    from ..simulation import integrate_interval

    if delay > 0:
        x = integrate_interval(system, "true", x, before, delay, t)
    return integrate_interval(system, "true", x, now, dt - delay, t + delay)


def _rig_swingup(system: System, delay: float):
    """The rig's swing-up (:func:`_pumping`): torque limited to 1.5 N m and applied ``delay`` late,
    a 0.1 N m dither; the torque sits at its limit through most of the pumping."""
    return _pumping(system, RIG_TRUE, RIG_TORQUE, 0.1, delay)


def pendulum_rig(delay: float = 0.0, encoder: float = RIG_ENCODER) -> System:
    """The twin of a torque-limited lab pendulum (:data:`RIG_TRUE`, :data:`RIG_FRICTION`, torque
    limit :data:`RIG_TORQUE`, sampled every :data:`RIG_DT`, angle noise ``encoder`` [rad]), swung
    up with its torque applied ``delay`` [s] late (:func:`_rig_swingup`). The prior is
    :data:`RIG_PRIOR`, without friction; runs of 15 s from 0.1 rad. A delay is not a function of
    ``(x, u)``: the self-test integrates the truth with :func:`late_step`."""
    import dataclasses

    def true_dynamics(ops, x, u, p):
        return _dynamics(ops, x, [u[0] - RIG_FRICTION * ops.tanh(x[1] / FRICTION_SPEED)], p)

    base = dataclasses.replace(pendulum(), name="pendulum_rig", params=RIG_PRIOR, true_params=RIG_TRUE,
                               true_dynamics=true_dynamics, dt=RIG_DT, duration=15.0, x0=(0.1, 0.0),
                               noise=dataclasses.replace(pendulum().noise, measurement_std=(encoder,)))
    return dataclasses.replace(base, excitation=_rig_swingup(base, delay))


SYSTEMS.update({"pendulum_swingup": swingup_pendulum, "cart": cart, "rc_car_damped": rc_car_damped,
                "pendulum_rig": pendulum_rig})


# -- an inertia-wheel pendulum driven by a DC motor, as a new user writes it ------------------------
WHEEL_PRIOR = {"J_p": 0.02, "mgl": 0.3, "J_w": 5e-4, "k_m": 0.05, "b_m": 1e-3}
WHEEL_GAIN = -0.2  # the motor's torque per volt is 20 % below the datasheet's
WHEEL_BEARING = 0.004  # Coulomb friction of the wheel's bearing [N m], tanh(w / 0.5 rad/s)
WHEEL_PIVOT = 0.002  # viscous damping at the pendulum's pivot [N m s]


def _wheel_dynamics(ops, x, u, p):
    """``tau = k_m V - b_m w`` (a DC motor with its back-EMF), the pendulum taking the reaction,
    ``w`` the wheel's speed relative to it: ``J_p q'' = -mgl sin q - tau``, ``w' = tau / J_w - q''``."""
    q, qdot, phi, w = x
    tau = p["k_m"] * u[0] - p["b_m"] * w
    qddot = (-p["mgl"] * ops.sin(q) - tau) / p["J_p"]
    return [qdot, qddot, w, tau / p["J_w"] - qddot]


def _wheel_truth(ops, x, u, p):
    q, qdot, phi, w = x
    tau = (1 + WHEEL_GAIN) * p["k_m"] * u[0] - p["b_m"] * w - WHEEL_BEARING * ops.tanh(w / 0.5)
    qddot = (-p["mgl"] * ops.sin(q) - WHEEL_PIVOT * qdot - tau) / p["J_p"]
    return [qdot, qddot, w, tau / p["J_w"] - qddot]


def _wheel_excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return multisine(t, rng, (0.15, 0.55, 0.9, 1.7), (2.5, 2.0, 1.5, 0.8))  # [Hz], [V]


def inertia_wheel() -> System:
    """A pendulum swung by the reaction of a motor-driven wheel, both angles measured by encoders
    (1 mrad), the voltage known. Its truth has the motor 20 % weaker, Coulomb friction in the
    wheel's bearing and viscous damping at the pivot, none of which the prior has."""
    return System(
        name="inertia_wheel",
        states=(Signal("q", "rad"), Signal("qdot", "rad/s"), Signal("phi", "rad"), Signal("w", "rad/s")),
        inputs=(Signal("V", "V"),), outputs=(Signal("q", "rad"), Signal("phi", "rad")),
        params=WHEEL_PRIOR, true_params=WHEEL_PRIOR, dynamics=_wheel_dynamics, true_dynamics=_wheel_truth,
        measurement=lambda ops, x, u, p: [x[0], x[2]],
        noise=NoiseModel(measurement_std=(1e-3, 1e-3), state_std=(1e-3, 0.02, 1e-3, 0.5),
                         process_std=(1e-3, 0.1, 1e-3, 2.0), initial_std=(0.05, 0.2, 0.05, 2.0)),
        dt=0.005, duration=20.0, x0=(0.3, 0.0, 0.0, 0.0), excitation=_wheel_excitation,
        kinematic_chains=(KinematicChain("q", ("q", "qdot")), KinematicChain("phi", ("phi", "w"))),
        diagnosis=DiagnosisHints(mass_params=("J_p", "J_w")))


SYSTEMS["inertia_wheel"] = inertia_wheel
