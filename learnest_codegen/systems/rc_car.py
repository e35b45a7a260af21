"""RC car of the DART testbed (a Waveshare JetRacer Pro): a kinematic bicycle driven by raw commands.

State ``[x, y, v, psi]``: position of the Vicon reference point in the world frame [m], its speed
[m/s] and the car's heading [rad]. Inputs ``[throttle, steering]``: the raw commands the car
logs, throttle in ``[0, 1]`` and steering in ``[-1, 1]`` (positive turns left, counter-clockwise,
as the recordings show: corr(steering, yaw rate) = 0.96-0.98). With the steering angle
``delta`` and the slip angle of the reference point ``beta = atan(l_r tan(delta) / l)``::

    xdot = v cos(psi + beta),   ydot = v sin(psi + beta),
    vdot = a(throttle, v),      psidot = v cos(beta) tan(delta) / l.

Prior (:func:`dynamics`): the simplest first-principles map from commands to physics,
``a = a_max * throttle`` (motor stall acceleration times the command; no dead band, no back-EMF,
no friction, no drag) and ``delta = delta_max * steering`` (a linear servo). Finding what is
missing is the job of the diagnosis; the prior deliberately knows nothing of it.

Parameters of the prior, and where they come from:

* ``l = 0.1735 m`` wheelbase, measured wheel to wheel by the DART authors
  (``directly_measured_model_parameters`` in Lorenzo-Lyons/DART,
  ``DART_dynamic_models/dart_dynamic_models.py``; mass 1.580 kg, 0.847 kg on the front wheels).
* ``l_r = 0.115 m`` distance from the rear axle to the *Vicon reference point* (DART,
  ``lr_reference``, taped). The states are the Vicon point's position and speed, so the
  kinematic bicycle is written for that point, not for the centre of mass (0.093 m from the
  rear axle by the axle loads).
* ``delta_max = 0.36 rad`` (20.6 deg) steering angle at full command: DART's steering curve
  fitted on Vicon data gives +0.32 rad at ``steering = +1`` and -0.40 rad at ``-1``
  (mean 0.36); a least-squares fit of ``psidot`` from these recordings at low speed
  (0.3-1 m/s, where tyres barely slip) gives 0.38 rad. At higher speed the effective value
  falls (0.34 at 1-2 m/s, 0.27 at 2-3, 0.26 at 3-5 m/s): under-steer from tyre slip, which
  the prior leaves to the diagnosis.
* ``a_max = 16.05 m/s^2`` the motor's stall acceleration per unit throttle: DART's fitted
  motor force ``(a_m - b_m v)(throttle + c_m)`` with ``a_m = 25.36 N`` over the mass 1.58 kg.
  These recordings agree with DART's motor: the one clean standing start (throttle 0.29)
  accelerates at 1.5 m/s^2 over its first 0.3 s, and DART predicts
  16.05 (0.29 - 0.164) - rolling friction 0.9 = 1.1 m/s^2. A gain-only fit of the initial
  acceleration (v < 0.5 m/s, least squares through the origin) gives only 2.5-2.8 m/s^2 per
  unit throttle, because most starts use throttle 0.2-0.3, just above the dead band; such a
  gain describes no physical part and mis-predicts cruising, so the prior keeps the motor's
  stall gain. It omits the dead band ``c_m = -0.164``, so it over-predicts the acceleration by
  ``a_max * 0.164 = 2.6 m/s^2`` plus back-EMF and friction: on the recordings the prior's
  ``vdot`` is 4.7-7.8 m/s^2 too high on average, the largest part of the sim-to-real gap.

True dynamics (:func:`true_dynamics`, for simulation only; real runs have no truth): DART's own
fitted model of this car. Motor ``(a_m - b_m v) w(throttle) (throttle + c_m) / m`` with a smooth
switch ``w = (tanh(100 (throttle + c_m)) + 1) / 2`` (no force below the dead band),
``a_m = 25.36 N, b_m = 4.815 N s/m, c_m = -0.1638``; rolling friction and drag
``-(a_f tanh(b_f v) + c_f v + d_f v^2) / m`` with ``a_f = 1.266 N, b_f = 7.666 s/m,
c_f = 0.7393 N s/m, d_f = -0.1123 N s^2/m^2`` (valid over the 0-4 m/s DART drove); steering
``delta = w_s b_s tanh(a_s (s + c_s)) + (1 - w_s) d_s tanh(e_s (s + c_s))``,
``w_s = (tanh(30 (s + c_s)) + 1) / 2``, ``a_s = 1.393, b_s = 0.3658 rad, c_s = -0.0270,
d_s = 0.5148 rad, e_s = 1.023`` (an asymmetric, saturating servo). DART's first-order throttle
and steering lags (0.08 s) are not modelled: the recording reader shifts the commands instead.

Measurements ``[x, y, psi, v_enc]``: the Vicon position and yaw (100 Hz) and the wheel-encoder
speed (10 Hz, held). Noise stds: ``x, y`` 1 mm (the high-frequency residual in motion is
0.2-0.4 mm; stationary 0.01 mm; 1 mm leaves room for marker jitter and resampling), ``psi``
5 mrad (residual in motion 1.1-1.4 mrad; the Vicon body frame is also rotated by about 8 mrad
from the car's axis, DART's ``theta_correction``), ``v_enc`` 0.1 m/s (after the reader's
alignment the encoder differs from the Vicon speed by 0.03-0.19 m/s rms: 10 Hz hold, a
0.1-0.2 s lag and wheel slip; its scale is 1.00-1.05 times the Vicon speed).

Estimator tuning (``process_std`` per step of ``dt = 0.01 s``): 1 mm on ``x, y``; 0.02 m/s on
``v`` (an acceleration error of 2 m/s^2, the size of the prior's error on the real car) and
0.005 rad on ``psi`` (0.5 rad/s of yaw-rate error). ``initial_std`` ``(0.01 m, 0.01 m, 0.5 m/s,
0.05 rad)``. Full-state noise ``(1 mm, 1 mm, 0.02 m/s, 5 mrad)``.

Excitation (:func:`excitation`): free driving like the recordings. Commands are updated at
10 Hz and held, as on the car. Throttle ramps from 0 to a cruise level in 1 s, then moves
between 0.25 and 0.45 (the recordings' cruise range, 1-3 m/s with the true dynamics) as a sum
of two random-phase sines; steering is a sum of two random-phase sines with periods of 4-7 s
and 1.5-2.5 s and amplitudes 0.6 and 0.35, clipped to ``[-1, 1]``. The car starts at rest.
"""

from __future__ import annotations

import numpy as np

from .base import KinematicChain, NoiseModel, ResidualStructure, Signal, System
from .bicycle import bicycle_states, kinematic_bicycle

WHEELBASE = 0.1735  # [m] DART, measured
L_REF = 0.115  # [m] rear axle to the Vicon reference point, DART, measured
MASS = 1.580  # [kg] DART
DELTA_MAX = 0.36  # [rad] steering angle at full command (prior)
A_MAX = 25.35849952697754 / MASS  # [m/s^2] motor stall acceleration per unit throttle (prior)
COMMAND_RATE_HZ = 10.0  # the car's command and encoder rate

_GEOMETRY = {"l": WHEELBASE, "l_r": L_REF}
PRIOR_PARAMS = {**_GEOMETRY, "a_max": A_MAX, "delta_max": DELTA_MAX}
# DART's fitted model (model_parameters() in dart_dynamic_models.py), forces in N.
TRUE_PARAMS = {
    **_GEOMETRY, "m": MASS,
    "a_m": 25.35849952697754, "b_m": 4.815326690673828, "c_m": -0.16377617418766022,
    "a_f": 1.2659882307052612, "b_f": 7.666370391845703, "c_f": 0.7393041849136353,
    "d_f": -0.11231517791748047,
    "a_s": 1.392930030822754, "b_s": 0.36576229333877563, "c_s": 0.0029959678649902344 - 0.03,
    "d_s": 0.5147881507873535, "e_s": 1.0230425596237183,
}


def bicycle(ops, x, accel, delta, p):
    """Kinematic bicycle of the reference point ``l_r`` ahead of the rear axle, given ``vdot``."""
    return kinematic_bicycle(ops, x, accel, delta, p["l_r"], p["l"])


def dynamics(ops, x, u, p):
    """Prior: ``vdot = a_max throttle``, ``delta = delta_max steering``."""
    throttle, steering = u
    return bicycle(ops, x, p["a_max"] * throttle, p["delta_max"] * steering, p)


def steering_angle(ops, steering, p):
    """DART's asymmetric saturating steering curve [rad]."""
    s = steering + p["c_s"]
    w = 0.5 * (ops.tanh(30.0 * s) + 1.0)
    return w * p["b_s"] * ops.tanh(p["a_s"] * s) + (1.0 - w) * p["d_s"] * ops.tanh(p["e_s"] * s)


def longitudinal_acceleration(ops, throttle, v, p):
    """DART's motor (dead band, back-EMF) plus rolling friction and drag [m/s^2]."""
    on = 0.5 * (ops.tanh(100.0 * (throttle + p["c_m"])) + 1.0)
    motor = (p["a_m"] - p["b_m"] * v) * on * (throttle + p["c_m"])
    friction = -(p["a_f"] * ops.tanh(p["b_f"] * v) + p["c_f"] * v + p["d_f"] * v * v)
    return (motor + friction) / p["m"]


def true_dynamics(ops, x, u, p):
    """DART's fitted kinematic-bicycle model of the car (simulation only)."""
    throttle, steering = u
    return bicycle(ops, x, longitudinal_acceleration(ops, throttle, x[2], p),
                   steering_angle(ops, steering, p), p)


def measurement(ops, x, u, p):
    """Vicon ``x, y, psi`` and the encoder speed ``v``."""
    return [x[0], x[1], x[3], x[2]]


# -- excitation -----------------------------------------------------------------------------
THROTTLE_RANGE = (0.25, 0.45)
RAMP_S = 1.0
STEER_PERIODS_S = ((4.0, 7.0), (1.5, 2.5))
STEER_AMPLITUDES = (0.6, 0.35)


def excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Commands ``[throttle, steering]`` of shape ``(len(t), 2)``, held at 10 Hz."""
    held = np.floor(np.asarray(t) * COMMAND_RATE_HZ) / COMMAND_RATE_HZ  # zero-order hold
    mid, half = np.mean(THROTTLE_RANGE), 0.5 * np.diff(THROTTLE_RANGE)[0]
    w_th = 2 * np.pi / rng.uniform(3.0, 6.0, size=2)
    ph_th = rng.uniform(0, 2 * np.pi, size=2)
    throttle = mid + half * (0.6 * np.sin(w_th[0] * held + ph_th[0])
                             + 0.4 * np.sin(w_th[1] * held + ph_th[1]))
    throttle *= np.clip(held / RAMP_S, 0.0, 1.0)
    w_st = 2 * np.pi / np.array([rng.uniform(*r) for r in STEER_PERIODS_S])
    ph_st = rng.uniform(0, 2 * np.pi, size=2)
    steering = np.sin(np.outer(held, w_st) + ph_st) @ np.array(STEER_AMPLITUDES)
    return np.stack([throttle, np.clip(steering, -1.0, 1.0)], axis=1)


RC_CAR = System(
    name="rc_car",
    description="DART JetRacer RC car: kinematic bicycle on raw [throttle, steering]; prior "
                "a = a_max throttle (no dead band, friction or drag), delta = delta_max steering; "
                "true = DART's fitted motor, friction and steering curve; y = Vicon x, y, psi + "
                "encoder speed.",
    states=bicycle_states("Vicon reference point", "speed of the reference point",
                          "heading (Vicon yaw, unwrapped)"),
    inputs=(
        Signal("throttle", "1", "throttle command in [0, 1]"),
        Signal("steering", "1", "steering command in [-1, 1], positive turns left"),
    ),
    outputs=(
        Signal("x", "m", "Vicon x"),
        Signal("y", "m", "Vicon y"),
        Signal("psi", "rad", "Vicon yaw, unwrapped"),
        Signal("v_enc", "m/s", "wheel-encoder speed (10 Hz, held)"),
    ),
    params=PRIOR_PARAMS,
    true_params=TRUE_PARAMS,
    dynamics=dynamics,
    true_dynamics=true_dynamics,
    measurement=measurement,
    noise=NoiseModel(
        measurement_std=(1e-3, 1e-3, 5e-3, 0.1),
        state_std=(1e-3, 1e-3, 0.02, 5e-3),
        process_std=(1e-3, 1e-3, 0.02, 5e-3),
        initial_std=(0.01, 0.01, 0.5, 0.05),
    ),
    dt=0.01,
    duration=20.0,
    x0=(0.0, 0.0, 0.0, 0.0),
    excitation=excitation,
    kinematic_chains=(
        KinematicChain("x", ("x",)),
        KinematicChain("y", ("y",)),
        KinematicChain("psi", ("psi",)),
        KinematicChain("v_enc", ("v",)),
    ),
    periodic_states=("psi",),
    default_observer="ukf_rts",
    # invariant to where the car is and its heading
    residual=ResidualStructure(states=("v", "psi"), inputs=("v", "throttle", "steering")),
    planar_pose=("x", "y", "v", "psi"),
    # the commands' own ranges (the car's driver and the DART logs: throttle 0-1, steering +-1)
    input_limits=((0.0, 1.0), (-1.0, 1.0)),
)
