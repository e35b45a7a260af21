"""Ground robot of the paper's eq. (14): a kinematic bicycle localised by four range beacons.

State ``[x, y, v, psi]`` (position in the world frame [m], speed [m/s], heading [rad]); inputs
``[a, delta]`` (longitudinal acceleration command [m/s^2], front steering angle [rad]). With the
slip angle ``beta = atan(l_r tan(delta) / (l_f + l_r))``::

    xdot = v cos(psi + beta),   ydot = v sin(psi + beta),
    vdot = a - a_drag(v),       psidot = v cos(beta) tan(delta) / (l_f + l_r),

    a_drag(v) = 0.5 rho S C_D v |v| / m.

Measurements: the ranges ``r_i = sqrt((x - px_i)^2 + (y - py_i)^2)`` to the four static beacons
:data:`BEACONS` (the corners of a 20 m x 20 m square around the trajectories), and the
heading ``psi`` from an onboard sensor. Noise stds 0.05 m (ranges) and 1.0 deg (heading), as in
the paper; full-state training noise ``[0.005 m, 0.005 m, 0.005 m/s, 0.1 deg]``.

Parameters (a light robot with a boxy body, e.g. a 1/8-scale RC chassis carrying a sensor box):
``l_f = 0.18 m``, ``l_r = 0.15 m`` (wheelbase 0.33 m), ``m = 1.5 kg``, frontal area
``S = 0.06 m^2`` (about 0.25 m x 0.24 m), air density ``rho = 1.225 kg/m^3`` and, for the true
robot, the drag coefficient of a cube-like bluff body ``C_D = 1.05``. The paper writes
``0.5 S C_D v^2 / m`` with the density absorbed; here it is explicit. ``v |v|`` equals ``v^2``
for the forward motion simulated here and keeps the drag opposing the motion otherwise.
The drag coefficient ``k = 0.5 rho S C_D / m = 0.0257 1/m`` gives a drag deceleration of
0.026 m/s^2 at 1 m/s, 0.10 m/s^2 at 2 m/s, 0.23 m/s^2 at 3 m/s and 0.41 m/s^2 at 4 m/s -
physically plausible (a real RC car also loses a comparable amount to rolling resistance) and,
integrated over seconds, far larger than the speed and position accuracy the estimators reach.

Prior vs truth, cartpole-style: one dynamics function; the prior has ``C_D = 0`` (it does not
know about the drag), the truth ``C_D = 1.05``. So ``f_true - f_prior = (0, 0, -a_drag(v), 0)``.

Estimator tuning (``process_std`` per RK4 step of ``dt = 0.01 s``, ``initial_std``): the process
noise models what an estimator designer would assume for the inputs, not the drag: an
acceleration-command error of std 0.1 m/s^2 (``0.1 * dt = 1e-3 m/s`` per step on ``v``) and a
turn-rate error of about 0.1 rad/s (``1e-3 rad`` per step on ``psi``); on ``x, y`` 1e-3 m per
step covers the slip and path-curvature model error of a real vehicle. ``initial_std``
``(0.1 m, 0.1 m, 0.2 m/s, 2 deg)`` is a realistic start-up uncertainty. These make the estimators
with the true dynamics accurate (on the demo's test run, seed 1: MSE 5.2e-5 for the UKF, 5.0e-5
for the MHE; other process stds within a factor 3-10 do not do markedly better); the drag then
matters for the prior because its deceleration (up to 0.4 m/s^2) exceeds the assumed 0.1 m/s^2
input error (nominal UKF 8.7e-3, nominal MHE 5.0e-3 on the same run).

Excitation (:func:`excitation`): a figure-eight-like tour in the middle of the beacons. A
reference heading ``psi_ref(t) = psi_0 + A (sin(w t + phi) - sin(phi))`` with ``A = 2.405 rad``
(the first zero of the Bessel function J0: at constant speed the mean of ``exp(i psi)`` over a
period vanishes, so the path closes instead of drifting away) and a random period of 10-13 s and
phase per seed; a reference speed ``v_ref(t) = 2.2 + s1 0.9 sin(w1 t) + s2 0.45 sin(w2 t)`` m/s
with random signs and frequencies 1.3-1.7 and 2.3-2.7 times ``w`` (not harmonics of it, so the
speed modulation does not pile up drift), which stays within 0.85-3.55 m/s and exercises the
drag over its range. The inputs realise these references: the steering angle solves
``psidot = psi_ref'`` at ``v_ref`` in closed form, and ``a = v_ref' + k v_ref^2`` is the
feed-forward of the robot's own low-level speed loop, which knows the true drag (the estimator's
prior does not). The tour starts at the figure's centre (``phi = +-pi/2`` plus a jitter of
+-0.3 rad, the sign choosing the first turn's direction). Over seeds 0-15 the truth stays within
+-9 m of the origin (the beacons are at +-10 m), the speed within 0.85-3.55 m/s and the steering
angle within +-30 deg.
"""

from __future__ import annotations

import numpy as np

from .base import NoiseModel, ResidualStructure, Signal, System
from .bicycle import bicycle_states, kinematic_bicycle

L_F, L_R = 0.18, 0.15  # distances front / rear axle to the centre of gravity [m]
MASS, AREA, RHO = 1.5, 0.06, 1.225  # [kg], frontal area [m^2], air density [kg/m^3]
C_D_TRUE = 1.05  # drag coefficient of the true robot (bluff, cube-like body)
BEACONS = ((-10.0, -10.0), (10.0, -10.0), (10.0, 10.0), (-10.0, 10.0))  # (px_i, py_i) [m]

_PARAMS = {"l_f": L_F, "l_r": L_R, "m": MASS, "S": AREA, "rho": RHO}


def drag_deceleration(ops, v, p):
    """``a_drag = 0.5 rho S C_D v |v| / m`` [m/s^2]."""
    return 0.5 * p["rho"] * p["S"] * p["C_D"] * v * ops.abs(v) / p["m"]


def dynamics(ops, x, u, p):
    """Kinematic bicycle with aerodynamic drag, eq. (14) plus ``-a_drag`` on ``vdot``."""
    a, delta = u
    return kinematic_bicycle(ops, x, a - drag_deceleration(ops, x[2], p), delta, p["l_r"],
                             p["l_f"] + p["l_r"])


def measurement(ops, x, u, p):
    """Ranges to the four beacons, then the heading."""
    px, py, _, psi = x
    return [ops.sqrt((px - bx) ** 2 + (py - by) ** 2) for bx, by in BEACONS] + [psi]


# -- excitation -----------------------------------------------------------------------------
HEADING_AMPLITUDE = 2.404825557695773  # first zero of J0 [rad]
PERIOD_RANGE_S = (10.0, 13.0)
PHASE_JITTER = 0.3  # [rad]
SPEED_MEAN, SPEED_AMPLITUDES = 2.2, (0.9, 0.45)  # [m/s]
SPEED_FREQ_RATIOS = ((1.3, 1.7), (2.3, 2.7))  # speed frequencies / heading frequency
X0 = (0.0, 0.0, SPEED_MEAN, 0.0)
_K_DRAG = 0.5 * RHO * AREA * C_D_TRUE / MASS  # [1/m]


def excitation(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Inputs ``[a, delta]`` of shape ``(len(t), 2)`` for the seeded figure-eight tour."""
    w = 2.0 * np.pi / rng.uniform(*PERIOD_RANGE_S)
    phase = rng.choice([-0.5 * np.pi, 0.5 * np.pi]) + rng.uniform(-PHASE_JITTER, PHASE_JITTER)
    signs = rng.choice([-1.0, 1.0], size=2)
    w_v = w * np.array([rng.uniform(*r) for r in SPEED_FREQ_RATIOS])
    amp = signs * np.array(SPEED_AMPLITUDES)
    v_ref = SPEED_MEAN + np.sin(np.outer(t, w_v)) @ amp  # v_ref(0) = x0's speed
    dv_ref = np.cos(np.outer(t, w_v)) @ (amp * w_v)
    psi_rate = HEADING_AMPLITUDE * w * np.cos(w * t + phase)
    # psidot = v tan(delta) / (L sqrt(1 + c^2 tan^2 delta)), c = l_r / L, solved for tan(delta).
    wheelbase = L_F + L_R
    r = psi_rate * wheelbase / v_ref
    c = L_R / wheelbase
    delta = np.arctan(r / np.sqrt(1.0 - (c * r) ** 2))
    accel = dv_ref + _K_DRAG * v_ref * np.abs(v_ref)
    return np.stack([accel, delta], axis=1)


GROUND_ROBOT = System(
    name="ground_robot",
    description="Ground robot, paper eq. (14): kinematic bicycle, 4 range beacons + heading; "
                "true robot has aerodynamic drag (C_D 1.05), the prior none.",
    states=bicycle_states(),
    inputs=(
        Signal("a", "m/s^2", "acceleration command"),
        Signal("delta", "rad", "front steering angle"),
    ),
    outputs=(
        *(Signal(f"r{i + 1}", "m", f"range to beacon {i + 1} at {b}") for i, b in enumerate(BEACONS)),
        Signal("psi", "rad", "heading"),
    ),
    params={**_PARAMS, "C_D": 0.0},
    true_params={**_PARAMS, "C_D": C_D_TRUE},
    dynamics=dynamics,
    measurement=measurement,
    noise=NoiseModel(
        measurement_std=(0.05, 0.05, 0.05, 0.05, float(np.deg2rad(1.0))),
        state_std=(0.005, 0.005, 0.005, float(np.deg2rad(0.1))),
        process_std=(1e-3, 1e-3, 1e-3, 1e-3),
        initial_std=(0.1, 0.1, 0.2, float(np.deg2rad(2.0))),
    ),
    dt=0.01,
    duration=25.0,
    x0=X0,
    excitation=excitation,
    periodic_states=("psi",),
    default_observer="ukf_rts",
    residual=ResidualStructure(
        # x, y are kinematics of (v, psi) through the slip angle; unknown forces act on v and psi.
        states=("v", "psi"),
        # Invariance to translation and rotation: without wind or slopes no force depends on
        # where the robot is or which way it points, so the residual sees speed and inputs only.
        inputs=("v", "a", "delta"),
    ),
    planar_pose=("x", "y", "v", "psi"),
)
