"""Quadrotor translational states, the paper's section V-C (Crazyflie 2.1 with Vicon).

State ``[px, py, pz, vx, vy, vz, ax, ay, az]`` (world-frame position [m], velocity [m/s] and
acceleration [m/s^2], z up); measurements ``[px, py, pz, ax, ay, az]``: motion-capture position
and the world-frame acceleration from the onboard accelerometer,
``a_world = R(q) (9.81 acc_g) - [0, 0, 9.81]`` (the accelerometer measures the specific force,
thrust plus drag over mass, in the body frame, in g).

Prior (the paper's): ``f_prior(x) = A x``, a triple integrator per axis, ``pdot = v``,
``vdot = a``, ``adot = 0``. It ignores the inputs.

Inputs ``[Tx, Ty, Tz, vbat]``: the collective thrust command as a world-frame vector in units
of full throttle (the mean motor PWM over 65535 along the body z axis ``R(q) e3``) and the
battery voltage [V]. Nothing in the prior uses them; they are there for the learned residual,
which acts on ``adot`` (``residual_state_names`` are the chains' last states ``ax, ay, az``).
The residual never sees the position (``residual.inputs``): no force on the vehicle depends on
where it is in the room, and a net that sees ``p`` keys on where the training flight went.
:data:`QUADROTOR` gives it velocity, acceleration, thrust and battery voltage;
:data:`QUADROTOR_STATE` (``"quadrotor_state"``, the paper's setting) velocity and acceleration
only. A residual of ``(v, a)`` alone can only learn what the acceleration of *this* trajectory
does next (on a circle of angular rate ``w``: ``adot = -w^2 v``), which does not carry over to
other speeds or shapes; with the thrust and the battery voltage it can learn the physics below.
:mod:`learnest_codegen.experiments.quadrotor` measures both. :data:`QUADROTOR_LINEAR` and
:data:`QUADROTOR_THRUST_LINEAR` are grey-box priors whose acceleration rows are fitted to
flights, the latter of the true model's form below (``docs/reports/flights.md``).

Pre-training observer (``default_observer``): ``linear_rts``, the exact Kalman filter and RTS
smoother of the prior ``A x`` with white jerk on each axis (intensity by maximum likelihood)
that uses both outputs. The per-chain ``rts`` observer sees position only and gets the
acceleration from its second differences; on the real flights the KNODE-UKF trained on
``linear_rts`` observations improves more on the UKF (thrust features: +21 % against +16 %).

True system (simulation only). Thrust acceleration ``f`` follows the command through a
first-order motor lag ``tau``, its gain falls with the battery voltage, and rotor drag ``k_D v``
opposes the velocity::

    a = f - g e3 - k_D v,       fdot = (k_T (vbat / V_NOM) T - f) / tau
    =>  adot = (k_T (vbat / V_NOM) T - g e3 - k_D v - a) / tau - k_D a.

Parameters: ``k_T = 11.4 m/s^2`` per unit throttle at ``V_NOM = 3.5 V`` (hover at 0.86 of full
throttle, what the NanoBench Crazyflies with markers fly at), ``tau = 0.05 s`` (a Crazyflie
brushed-motor time constant), ``k_D = 0.35 1/s`` (rotor drag of a 30 g quadrotor: 0.35 m/s^2
at 1 m/s, in line with identified Crazyflie drag). The prior has none of this: ``adot = 0``.

Noise (per sample, ``dt = 0.01 s``, the NanoBench logs' 100 Hz): Vicon position 1 mm; world
acceleration 0.25 m/s^2 horizontally and 0.12 m/s^2 vertically. The latter are the total error
of the accelerometer-derived acceleration against a 0.3 s Savitzky-Golay second derivative of
Vicon position on the real flights: a slowly varying part (attitude misalignment, bias: 0.1-0.2
m/s^2) and motor vibration (0.06-0.12 m/s^2). Full-state training noise ``[1 mm, 0.01 m/s,
0.05 m/s^2]``. Estimator tuning (``process_std`` per RK4 step): 1e-4 m on position and 1e-3
m/s on velocity (kinematics, exact up to the RK4 step) and 0.02 m/s^2 on acceleration: a white
jerk of 2 m/s^3 rms, the size of the jerk of a 1 m/s figure-eight. ``initial_std`` ``(1 cm,
0.2 m/s, 0.5 m/s^2)``; estimators start from the first measurements, not from ``x0``.

Excitation (:func:`excitation`): a feed-forward that flies a circle or a figure-eight of radius
1 m at 1 m altitude (chosen per seed with equal odds), at 0.5-1.0 m/s, with a 0.1 m altitude
wobble; the path parameter ramps up from hover over 3 s with a quintic smoothstep so the
reference starts at rest with zero acceleration and jerk at ``x0``. The commanded thrust is the
exact inverse of the true model along the reference, ``T = (f_ref + tau fdot_ref) / (k_T vbat /
V_NOM)`` with ``f_ref = a_ref + g e3 + k_D v_ref``, so the truth flies the reference (the
low-level controller knows its own vehicle; the estimator's prior does not). The battery sags
linearly from 3.5-3.7 V by 0.01 V/s, as in the real flights.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .base import KinematicChain, NoiseModel, ResidualStructure, Signal, System

GRAVITY = 9.81  # [m/s^2]
V_NOM = 3.5  # battery voltage at which k_T is given [V]
K_T, TAU_MOTOR, K_DRAG = 11.4, 0.05, 0.35  # [m/s^2 per unit throttle], [s], [1/s]
AXES = ("x", "y", "z")

_TRUE = {"k_T": K_T, "tau": TAU_MOTOR, "k_D": K_DRAG, "g": GRAVITY, "v_nom": V_NOM}
#: The inputs' real ranges: each thrust component is the unit body axis times the mean motor
#: PWM over 65535 (0-1), so within [-1, 1]; the battery is one LiPo cell, 4.2 V full (the
#: NanoBench flights log 2.0-4.19 V), read by the power monitor below 4.5 V.
INPUT_LIMITS = ((-1.0, 1.0),) * 3 + ((0.0, 4.5),)


def dynamics(ops, x, u, p):
    """Triple integrator per axis: ``pdot = v``, ``vdot = a``, ``adot = 0`` (the paper's A x)."""
    return [*x[3:9], 0.0 * x[6], 0.0 * x[7], 0.0 * x[8]]


def true_dynamics(ops, x, u, p):
    """Triple integrator whose ``adot`` has motor lag, battery-dependent thrust and rotor drag."""
    v, a = x[3:6], x[6:9]
    thrust, vbat = u[0:3], u[3]
    gain = p["k_T"] * vbat / p["v_nom"]
    gravity = (0.0, 0.0, p["g"])
    adot = [(gain * thrust[i] - gravity[i] - p["k_D"] * v[i] - a[i]) / p["tau"] - p["k_D"] * a[i]
            for i in range(3)]
    return [*v, *a, *adot]


def measurement(ops, x, u, p):
    """Motion-capture position and world-frame acceleration: ``[p, a]``."""
    return [*x[0:3], *x[6:9]]


# -- excitation -----------------------------------------------------------------------------
RADIUS_M, ALTITUDE_M, WOBBLE_M = 1.0, 1.0, 0.1
SPEED_RANGE = (0.5, 1.0)  # [m/s] along the path's x swing at full speed
RAMP_S = 3.0
VBAT_RANGE, VBAT_SAG = (3.5, 3.7), 0.01  # [V], [V/s]
X0 = (0.0, 0.0, ALTITUDE_M, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)

# Reference shapes as sums of r sin(k theta + phi) per axis (offsets separate), so every
# derivative in theta is exact: d^n/dtheta^n sin(k theta + phi) = k^n sin(k theta + phi + n pi/2).
SHAPES = {
    "circle": {"x": [(RADIUS_M, 1, 0.0)], "y": [(RADIUS_M, 1, -0.5 * np.pi)],
               "z": [(WOBBLE_M, 2, 0.0)]},
    "figure8": {"x": [(RADIUS_M, 1, 0.0)], "y": [(0.5 * RADIUS_M, 2, 0.0)],
                "z": [(WOBBLE_M, 1, 0.0)]},
}


def _phase(t: np.ndarray, rate: float) -> np.ndarray:
    """``theta`` and its first three time derivatives, ``(4, T)``: a quintic smoothstep ramp."""
    s = np.clip(t / RAMP_S, 0.0, 1.0)
    ramp = [10 * s**3 - 15 * s**4 + 6 * s**5,  # theta' / rate
            (30 * s**2 - 60 * s**3 + 30 * s**4) / RAMP_S,
            (60 * s - 180 * s**2 + 120 * s**3) / RAMP_S**2]
    integral = np.where(t < RAMP_S, RAMP_S * (2.5 * s**4 - 3 * s**5 + s**6), t - 0.5 * RAMP_S)
    return rate * np.stack([integral, *ramp])


def reference(shape: str, rate: float, t: np.ndarray) -> np.ndarray:
    """Reference position, velocity, acceleration and jerk, ``(4, T, 3)``, of a named shape.

    The path starts at ``x0``'s position (theta = 0) and is flown at ``rate`` [rad/s] of the
    path parameter after the ramp.
    """
    th = _phase(t, rate)
    out = np.zeros((4, t.size, 3))
    out[0] = X0[:3]
    for axis, terms in enumerate(SHAPES[shape][a] for a in AXES):
        for r, k, phi in terms:
            d = [k**n * r * np.sin(k * th[0] + phi + n * np.pi / 2) for n in range(4)]  # d^n/dtheta^n
            out[0, :, axis] += d[0] - r * np.sin(phi)
            out[1, :, axis] += d[1] * th[1]
            out[2, :, axis] += d[2] * th[1] ** 2 + d[1] * th[2]
            out[3, :, axis] += d[3] * th[1] ** 3 + 3 * d[2] * th[1] * th[2] + d[1] * th[3]
    return out


def excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Inputs ``[Tx, Ty, Tz, vbat]`` of shape ``(len(t), 4)`` that fly the seeded reference."""
    shape = str(rng.choice(sorted(SHAPES)))
    rate = rng.uniform(*SPEED_RANGE) / RADIUS_M * rng.choice([-1.0, 1.0])  # [rad/s]
    vbat = rng.uniform(*VBAT_RANGE) - VBAT_SAG * t
    _, v, a, j = reference(shape, rate, t)
    e3 = np.array([0.0, 0.0, GRAVITY])
    f_ref, fdot_ref = a + e3 + K_DRAG * v, j + K_DRAG * a
    thrust = (f_ref + TAU_MOTOR * fdot_ref) / (K_T * vbat / V_NOM)[:, None]
    return np.hstack([thrust, vbat[:, None]])


QUADROTOR = System(
    name="quadrotor",
    description="Quadrotor translational states (paper sec. V-C): triple-integrator prior "
                "A x; y = [Vicon p, world accel]; true: motor lag, battery-dependent thrust, "
                "rotor drag.",
    states=(
        *(Signal(f"p{a}", "m", f"position, world {a}") for a in AXES),
        *(Signal(f"v{a}", "m/s", f"velocity, world {a}") for a in AXES),
        *(Signal(f"a{a}", "m/s^2", f"acceleration, world {a}") for a in AXES),
    ),
    inputs=(
        *(Signal(f"T{a}", "1", f"thrust command along world {a} (fraction of full throttle)")
          for a in AXES),
        Signal("vbat", "V", "battery voltage"),
    ),
    outputs=(
        *(Signal(f"p{a}", "m", f"motion-capture position, world {a}") for a in AXES),
        *(Signal(f"a{a}", "m/s^2", f"accelerometer acceleration, world {a}") for a in AXES),
    ),
    params={},
    true_params=_TRUE,
    dynamics=dynamics,
    true_dynamics=true_dynamics,
    measurement=measurement,
    noise=NoiseModel(
        measurement_std=(1e-3, 1e-3, 1e-3, 0.25, 0.25, 0.12),
        state_std=(1e-3,) * 3 + (0.01,) * 3 + (0.05,) * 3,
        process_std=(1e-4,) * 3 + (1e-3,) * 3 + (0.02,) * 3,
        initial_std=(0.01,) * 3 + (0.2,) * 3 + (0.5,) * 3,
    ),
    dt=0.01,
    duration=20.0,
    x0=X0,
    excitation=excitation,
    kinematic_chains=tuple(KinematicChain(f"p{a}", (f"p{a}", f"v{a}", f"a{a}")) for a in AXES),
    default_observer="linear_rts",
    residual=ResidualStructure(inputs=(*(f"v{a}" for a in AXES), *(f"a{a}" for a in AXES),
                                       *(f"T{a}" for a in AXES), "vbat")),
    input_limits=INPUT_LIMITS,
)

QUADROTOR_STATE = replace(
    QUADROTOR, name="quadrotor_state",
    description="The quadrotor whose residual sees only velocity and acceleration (the paper's "
                "features: no thrust, no battery voltage).",
    residual=ResidualStructure(inputs=(*(f"v{a}" for a in AXES), *(f"a{a}" for a in AXES))),
)


def linear_dynamics(ops, x, u, p):
    """The prior ``A x`` with fitted acceleration rows: ``adot = -k_v v - k_a a`` per axis, one
    ``(k_v, k_a)`` shared by the two horizontal axes (the vehicle has no preferred heading) and one
    for the vertical. With every parameter 0 it is the triple integrator of :func:`dynamics`."""
    v, a = x[3:6], x[6:9]
    k_v = (p["k_v_xy"], p["k_v_xy"], p["k_v_z"])
    k_a = (p["k_a_xy"], p["k_a_xy"], p["k_a_z"])
    return [*v, *a, *(-k_v[i] * v[i] - k_a[i] * a[i] for i in range(3))]


#: The quadrotor whose prior ``A x`` has its acceleration rows fitted to the training flights by
#: least squares (a grey-box prior; see :mod:`learnest_codegen.learning.prior_fit`): on a flown
#: path the acceleration turns with the velocity (on a circle at rate ``w``, ``adot = -w^2 v``).
#: The registered parameters are 0 (the paper's triple integrator); a trained model's directory
#: carries the fitted ones. The residual sees velocity and acceleration, as ``quadrotor_state``.
QUADROTOR_LINEAR = replace(
    QUADROTOR_STATE, name="quadrotor_linear",
    description="The quadrotor whose prior A x has acceleration rows adot = -k_v v - k_a a fitted "
                "to the training flights (horizontal axes shared); residual on v and a.",
    dynamics=linear_dynamics, true_dynamics=true_dynamics,
    params={"k_v_xy": 0.0, "k_a_xy": 0.0, "k_v_z": 0.0, "k_a_z": 0.0},
)


def thrust_linear_dynamics(ops, x, u, p):
    """The prior ``A x`` with acceleration rows of the true model's form, linear in their
    coefficients: ``adot = c_T vbat T + c_v v + c_a a`` per axis, plus ``c_0_z`` on ``az``
    (gravity). One ``(c_v, c_a)`` shared by the two horizontal axes and one for the vertical; the
    thrust gain ``c_T`` is one for all axes (one motor gain) and ``c_T + dc_T_z`` on the vertical
    (``dc_T_z = 0`` unless fitted). With every parameter 0 it is the triple integrator of
    :func:`dynamics`; :func:`thrust_physics` reads the coefficients as ``k_T, tau, k_D``."""
    v, a = x[3:6], x[6:9]
    thrust, vbat = u[0:3], u[3]
    c_T = (p["c_T"], p["c_T"], p["c_T"] + p["dc_T_z"])
    c_v = (p["c_v_xy"], p["c_v_xy"], p["c_v_z"])
    c_a = (p["c_a_xy"], p["c_a_xy"], p["c_a_z"])
    c_0 = (0.0, 0.0, p["c_0_z"])
    return [*v, *a, *(c_T[i] * vbat * thrust[i] + c_v[i] * v[i] + c_a[i] * a[i] + c_0[i]
                      for i in range(3))]


def thrust_coefficients(k_T: float, tau: float, k_D: float, g: float = GRAVITY,
                        v_nom: float = V_NOM) -> dict[str, float]:
    """The coefficients of :func:`thrust_linear_dynamics` that equal :func:`true_dynamics` with
    physical parameters ``k_T, tau, k_D`` (the same on every axis): expanding the truth,
    ``c_T = k_T / (v_nom tau)``, ``c_v = -k_D / tau``, ``c_a = -(1 / tau + k_D)``,
    ``c_0_z = -g / tau``."""
    c_v, c_a = -k_D / tau, -(1.0 / tau + k_D)
    return {"c_T": k_T / (v_nom * tau), "dc_T_z": 0.0, "c_v_xy": c_v, "c_a_xy": c_a, "c_v_z": c_v,
            "c_a_z": c_a, "c_0_z": -g / tau}


def thrust_physics(params: dict[str, float], v_nom: float = V_NOM) -> dict[str, dict[str, float]]:
    """The motor lag ``tau`` [s], rotor drag ``k_D`` [1/s] and thrust gain ``k_T`` [m/s^2 per unit
    throttle at ``v_nom``] that :func:`thrust_linear_dynamics`' coefficients imply, per axis group
    (``"xy"``, ``"z"``); the inverse of :func:`thrust_coefficients`.

    ``tau`` and ``k_D`` solve ``c_v = -k_D / tau``, ``c_a = -(1 / tau + k_D)``, i.e.
    ``c_v tau^2 - c_a tau - 1 = 0`` (the root that tends to ``-1 / c_a`` as ``c_v -> 0``; NaN if
    there is no real one); then ``k_T = c_T v_nom tau``. On ``z`` also ``g_over_tau = -c_0_z``.
    """
    out = {}
    for group in ("xy", "z"):
        c_v, c_a = params[f"c_v_{group}"], params[f"c_a_{group}"]
        c_T = params["c_T"] + (params.get("dc_T_z", 0.0) if group == "z" else 0.0)
        disc = c_a * c_a + 4.0 * c_v
        if disc < 0.0:
            tau = float("nan")
        elif abs(c_v) < 1e-12 * max(1.0, c_a * c_a):
            tau = -1.0 / c_a if c_a != 0.0 else float("nan")
        else:
            tau = 2.0 / (-c_a + np.sqrt(disc))  # = (c_a + sqrt(disc)) / (2 c_v), stable form
        out[group] = {"tau": tau, "k_D": -c_v * tau, "k_T": c_T * v_nom * tau}
    out["z"]["g_over_tau"] = -params["c_0_z"]
    return out


#: The quadrotor whose prior has the true model's form (motor lag, thrust gain times battery
#: voltage, rotor drag) with its coefficients fitted to the training flights by least squares
#: (:mod:`learnest_codegen.learning.prior_fit`): unlike ``quadrotor_linear`` it uses the thrust
#: command, which leads the acceleration by the motor lag. Registered parameters are 0 (the
#: paper's triple integrator); a trained model's directory carries the fitted ones. The residual
#: sees velocity and acceleration, as ``quadrotor_state``.
QUADROTOR_THRUST_LINEAR = replace(
    QUADROTOR_STATE, name="quadrotor_thrust_linear",
    description="The quadrotor whose prior has acceleration rows adot = c_T vbat T + c_v v + c_a a "
                "(+ c_0 on z) fitted to the training flights: the true model's form; residual on v "
                "and a.",
    dynamics=thrust_linear_dynamics, true_dynamics=true_dynamics,
    params={"c_T": 0.0, "dc_T_z": 0.0, "c_v_xy": 0.0, "c_a_xy": 0.0, "c_v_z": 0.0, "c_a_z": 0.0,
            "c_0_z": 0.0},
)


# -- accelerometer bias ---------------------------------------------------------------------
#: Process noise of each bias state per RK4 step [m/s^2]: a random walk of 0.01 m/s^2 per
#: sqrt(s), 0.05 m/s^2 over a 30 s flight; the NanoBench flights' world-frame accelerometer
#: offsets (0.1-0.4 m/s^2 horizontally, constant within a flight: the accelerometer's mounting
#: against the motion-capture body frame) are fixed by the position within a few seconds.
BIAS_PROCESS_STD = 1e-3
#: Initial std of each bias state [m/s^2]: the largest offset on the NanoBench flights is 0.40.
BIAS_INITIAL_STD = 0.3
#: Process noise of each lagged-reading state per RK4 step [m/s^2] (what the first-order lag
#: does not describe of the accelerometer's filter and latency).
LAG_PROCESS_STD = 1e-3
#: The accelerometer lag the lagged systems are registered with [s]; a study chooses it on
#: the training flights (``experiments/quadrotor_tuning.py``).
ACCEL_LAG_S = 0.02


def with_accelerometer_bias(system: System, name: str, lag_s: float | None = None) -> System:
    """``system`` with three more states ``bx, by, bz`` [m/s^2], an offset of the world-frame
    accelerometer: ``y_a = a + b``, ``bdot = 0`` (a random walk in the estimators, process
    noise :data:`BIAS_PROCESS_STD`). Tilting a gravity vector of 9.81 m/s^2 by 1 degree reads
    0.17 m/s^2 horizontally: a few degrees between the accelerometer and the motion-capture
    body frame, or a zero offset, shows as a constant world-frame offset while the yaw holds
    (the NanoBench flights: 0.1-0.4 m/s^2 on x, up to 0.3 on y, per flight). Position fixes
    ``a`` (its second derivative), the accelerometer fixes ``a + b``: both are observable. The
    residual acts on ``ax, ay, az`` as in ``system``; the dynamics and their parameters are
    ``system``'s.

    With ``lag_s`` the accelerometer also reads the acceleration late: three more states
    ``mx, my, mz``, a first-order lag ``mdot = (a - m) / tau_acc`` (parameter ``tau_acc``,
    registered as ``lag_s`` [s]), and ``y_a = m + b``. The onboard stream reaches the log
    later than the motion capture (radio and logging) and is low-pass filtered on board; on the
    NanoBench flights the accelerometer trails the motion capture's acceleration by about one
    sample."""
    base_dynamics, base_true = system.dynamics, system.true_dynamics or system.dynamics
    lag = lag_s is not None

    def extra(ops, x, p):
        zero = [0.0 * x[9], 0.0 * x[10], 0.0 * x[11]]
        if not lag:
            return zero
        return [*zero, *((x[6 + i] - x[12 + i]) / p["tau_acc"] for i in range(3))]

    def dynamics(ops, x, u, p):
        return [*base_dynamics(ops, x, u, p), *extra(ops, x, p)]

    def true_dynamics(ops, x, u, p):
        return [*base_true(ops, x, u, p), *extra(ops, x, p)]

    def measurement(ops, x, u, p):
        read = x[12:15] if lag else x[6:9]
        return [*x[0:3], read[0] + x[9], read[1] + x[10], read[2] + x[11]]

    noise = system.noise
    residual = replace(system.residual, states=tuple(system.residual_state_names))
    states = (*system.states, *(Signal(f"b{a}", "m/s^2", f"accelerometer offset, world {a}") for a in AXES))
    more = dict(state_std=(*noise.state_std, 0.05, 0.05, 0.05),
                process_std=(*noise.process_std, *(BIAS_PROCESS_STD,) * 3),
                initial_std=(*noise.initial_std, *(BIAS_INITIAL_STD,) * 3))
    params, true_params, x0 = dict(system.params), dict(system.true_params), (*system.x0, 0.0, 0.0, 0.0)
    if lag:
        states += tuple(Signal(f"m{a}", "m/s^2", f"acceleration as the accelerometer reads it, world {a}")
                        for a in AXES)
        lagged = {"state_std": (0.05,) * 3, "process_std": (LAG_PROCESS_STD,) * 3,
                  "initial_std": noise.initial_std[6:9]}
        more = {k: (*v, *lagged[k]) for k, v in more.items()}
        params["tau_acc"] = true_params["tau_acc"] = float(lag_s)
        x0 = (*x0, *system.x0[6:9])
    return replace(
        system, name=name,
        description=system.description + " Accelerometer offset states b (y_a = a + b)"
                    + (", read through a first-order lag tau_acc." if lag else "."),
        states=states, dynamics=dynamics, true_dynamics=true_dynamics, measurement=measurement,
        noise=replace(noise, **more), x0=x0, residual=residual, params=params, true_params=true_params)


#: The paper's triple integrator with accelerometer offset states (:func:`with_accelerometer_bias`).
QUADROTOR_BIAS = with_accelerometer_bias(QUADROTOR_STATE, "quadrotor_bias")
#: ``quadrotor_linear`` (the fitted prior ``adot = -k_v v - k_a a``) with accelerometer offsets.
QUADROTOR_LINEAR_BIAS = with_accelerometer_bias(QUADROTOR_LINEAR, "quadrotor_linear_bias")
#: ``quadrotor_thrust_linear`` (thrust, drag and lag rows, fitted) with accelerometer offsets.
QUADROTOR_THRUST_LINEAR_BIAS = with_accelerometer_bias(QUADROTOR_THRUST_LINEAR,
                                                       "quadrotor_thrust_linear_bias")
#: ``quadrotor_bias`` (the paper's triple integrator with offsets) whose accelerometer reads the
#: acceleration through a first-order lag.
QUADROTOR_BIAS_LAG = with_accelerometer_bias(QUADROTOR_STATE, "quadrotor_bias_lag", lag_s=ACCEL_LAG_S)
#: ``quadrotor_linear_bias`` whose accelerometer reads the acceleration through a first-order lag.
QUADROTOR_LINEAR_BIAS_LAG = with_accelerometer_bias(QUADROTOR_LINEAR, "quadrotor_linear_bias_lag",
                                                    lag_s=ACCEL_LAG_S)

#: Every quadrotor system, in the order the registry (``systems.SYSTEMS``) lists them.
QUADROTORS = (QUADROTOR, QUADROTOR_STATE, QUADROTOR_LINEAR, QUADROTOR_THRUST_LINEAR, QUADROTOR_BIAS,
              QUADROTOR_BIAS_LAG, QUADROTOR_LINEAR_BIAS, QUADROTOR_LINEAR_BIAS_LAG,
              QUADROTOR_THRUST_LINEAR_BIAS)
