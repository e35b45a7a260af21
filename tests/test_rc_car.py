"""The DART RC car: model parity and closed forms, the recording reader, and the real recordings."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.optimize import brentq
from scipy.signal import savgol_filter

from learnest_codegen import get_system
from learnest_codegen.data import Run
from learnest_codegen.errors import DataError
from learnest_codegen.estimators.inputs import InputCheck, plausible_inputs
from learnest_codegen.observers import observe
from learnest_codegen.recordings.dart import (
    DartSettings,
    beacon_ranges,
    list_recordings,
    read_recording,
)
from learnest_codegen.simulation import simulate

L, L_R, A_MAX, DELTA_MAX = 0.1735, 0.115, 25.35849952697754 / 1.580, 0.36  # documented values
HEADER = ("elapsed time sensors,current,voltage,acc x (IMU),acc y (IMU),W (IMU),vel encoder,"
          "safety_value,throttle,steering,vicon time,vicon x,vicon y,vicon yaw")


@pytest.fixture(scope="module")
def car():
    return get_system("rc_car")


def random_points(n=200, seed=0):
    rng = np.random.default_rng(seed)
    x = np.c_[rng.uniform(-4, 4, (n, 2)), rng.uniform(0, 4.5, n), rng.uniform(-7, 7, n)]
    u = np.c_[rng.uniform(0, 1, n), rng.uniform(-1, 1, n)]
    return x, u


def constant(system, throttle, steering):
    return dataclasses.replace(system, excitation=lambda t, rng: np.tile([throttle, steering],
                                                                          (len(t), 1)))


# -- model ------------------------------------------------------------------------------------
@pytest.mark.parametrize("variant", ["prior", "true"])
def test_numpy_torch_casadi_agree(car, variant):
    x, u = random_points()
    f_np = car.f(x, u, variant=variant)
    f_torch = car.f(torch.tensor(x), torch.tensor(u), variant=variant).numpy()
    f_cs = car.casadi_f(variant).map(len(x))(x.T, u.T).full().T
    np.testing.assert_allclose(f_torch, f_np, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(f_cs, f_np, rtol=1e-12, atol=1e-12)
    h_np = car.h(x, u)
    np.testing.assert_allclose(h_np, x[:, [0, 1, 3, 2]], rtol=0, atol=0)
    np.testing.assert_allclose(car.casadi_h().map(len(x))(x.T, u.T).full().T, h_np, atol=1e-15)


def test_prior_is_the_documented_bicycle(car):
    x, u = random_points(seed=1)
    _, _, v, psi = x.T
    delta = DELTA_MAX * u[:, 1]
    beta = np.arctan(L_R * np.tan(delta) / L)
    expected = np.c_[v * np.cos(psi + beta), v * np.sin(psi + beta), A_MAX * u[:, 0],
                     v * np.cos(beta) * np.tan(delta) / L]
    np.testing.assert_allclose(car.f(x, u), expected, rtol=1e-13, atol=1e-13)


def test_true_model_is_darts(car):
    """DART's fitted curves, written out independently: dead band, friction, steering ends."""
    p = car.true_params
    # Below the dead band the motor is off (up to the smooth switch, tanh(-6.4)): at rest the
    # car stays put, while the prior would accelerate at a_max * 0.1.
    assert abs(car.f(np.zeros(4), np.array([0.1, 0.0]), variant="true")[2]) < 1e-5
    np.testing.assert_allclose(car.f(np.zeros(4), np.array([0.1, 0.0]))[2], 0.1 * A_MAX)
    # Full steering: +0.32 rad left, -0.40 rad right (asymmetric servo).
    c_s = 0.0029959678649902344 - 0.03  # at the ends the tanh switch is 1 (left) or 0 (right)
    left, right = 0.36576229333877563 * np.tanh(1.392930030822754 * (1 + c_s)), \
        0.5147881507873535 * np.tanh(1.0230425596237183 * (-1 + c_s))
    assert 0.31 < left < 0.33 and -0.41 < right < -0.39
    for s, angle in ((1.0, left), (-1.0, right)):
        r = car.f(np.array([0, 0, 1.0, 0]), np.array([0.0, s]), variant="true")[3]
        beta = np.arctan(L_R * np.tan(angle) / L)
        np.testing.assert_allclose(r, np.cos(beta) * np.tan(angle) / L, rtol=1e-9)
    # Coasting at 2 m/s: only rolling friction and drag act.
    v = 2.0
    drag = (p["a_f"] * np.tanh(p["b_f"] * v) + p["c_f"] * v + p["d_f"] * v**2) / p["m"]
    np.testing.assert_allclose(car.f(np.array([0, 0, v, 0]), np.array([0.0, 0.0]),
                                     variant="true")[2], -drag, rtol=1e-9)


def test_constant_throttle_drives_a_straight_line(car):
    """Prior, steering 0: v = v0 + a_max th t, x = v0 t + a_max th t^2 / 2, y = psi = 0."""
    th, v0, T = 0.3, 0.5, 200
    x = simulate(constant(car, th, 0.0), 0, variant="prior", duration=T * car.dt,
                 x0=np.array([0, 0, v0, 0])).x
    t = np.arange(T) * car.dt
    np.testing.assert_allclose(x[:, 2], v0 + A_MAX * th * t, rtol=1e-9)
    np.testing.assert_allclose(x[:, 0], v0 * t + 0.5 * A_MAX * th * t**2, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(x[:, [1, 3]], 0.0, atol=1e-12)


def test_constant_steering_drives_a_circle(car):
    """Prior, throttle 0: radius l / (cos(beta) tan(delta)), yaw rate v / R."""
    v, s, T = 1.5, 0.5, 400
    delta = DELTA_MAX * s
    beta = np.arctan(L_R * np.tan(delta) / L)
    radius = L / (np.cos(beta) * np.tan(delta))
    x = simulate(constant(car, 0.0, s), 0, variant="prior", duration=T * car.dt,
                 x0=np.array([0, 0, v, 0])).x
    centre = np.array([-radius * np.sin(beta), radius * np.cos(beta)])
    np.testing.assert_allclose(np.hypot(*(x[:, :2] - centre).T), radius, rtol=1e-8)
    np.testing.assert_allclose(x[:, 3], v / radius * car.dt * np.arange(T), rtol=1e-8, atol=1e-12)


def test_true_car_reaches_darts_steady_speed(car):
    """At constant throttle the true speed settles where motor force equals friction (brentq)."""
    p, th = car.true_params, 0.35

    def net_force(v):
        motor = (p["a_m"] - p["b_m"] * v) * (th + p["c_m"])
        return motor - (p["a_f"] * np.tanh(p["b_f"] * v) + p["c_f"] * v + p["d_f"] * v**2)

    v_ss = brentq(net_force, 0.1, 5.0)
    x = simulate(constant(car, th, 0.0), 0, duration=12.0, x0=np.array([0, 0, 2.0, 0])).x
    np.testing.assert_allclose(x[-1, 2], v_ss, rtol=1e-4)
    assert 1.5 < v_ss < 3.0  # the recordings cruise at 1-3 m/s with throttle 0.3-0.45


def test_simulated_free_driving_is_plausible(car):
    run = simulate(car, seed=4)
    assert run.u.shape == (2000, 2) and run.y.shape == (2000, 4)
    changes = np.flatnonzero(np.any(np.diff(run.u, axis=0) != 0, axis=1)) + 1
    assert np.all(changes % 10 == 0)  # commands held at 10 Hz like the car's
    assert run.u[:, 0].max() <= 0.45 and np.abs(run.u[:, 1]).max() <= 1.0
    v = run.x[200:, 2]
    assert 0.5 < v.min() and v.max() < 3.5
    noise = run.y - car.h(run.x, run.u)
    np.testing.assert_allclose(noise.std(axis=0), car.noise.measurement_std, rtol=0.1)


# -- the reader on synthetic recordings ---------------------------------------------------------
def write_dart_csv(path, t_vicon, x, y, yaw, throttle, steering, enc, safety=None, t_sensors=None):
    n = len(t_vicon)
    zeros = np.zeros(n)
    safety = np.ones(n) if safety is None else safety
    t_sensors = zeros if t_sensors is None else t_sensors
    table = np.c_[t_sensors, zeros, zeros, zeros, zeros, zeros, enc, safety, throttle, steering,
                  t_vicon, x, y, yaw]
    with open(path, "w") as fh:
        fh.write(HEADER + "\n")
        np.savetxt(fh, table, delimiter=",", fmt="%.17g")
    return path


@pytest.fixture
def synthetic(tmp_path):
    """12 s at ~100 Hz with 0.3 ms clock jitter: 2 s at rest, 8 s on a circle at 1 m/s
    (yaw wraps), 2 s at rest; commands and encoder updated at 10 Hz and held."""
    rng = np.random.default_rng(0)
    t = np.arange(1200) * 0.01 + rng.normal(0, 3e-4, 1200) + 1.7e9
    s = t - t[0]
    omega = 1.0  # [rad/s] on a 1 m circle
    moving = (s > 2.0) & (s < 10.0)
    angle = omega * np.clip(s - 2.0, 0.0, 8.0)
    x, y = np.sin(angle), 1.0 - np.cos(angle)
    yaw = np.angle(np.exp(1j * angle))  # wrapped to (-pi, pi]
    held = np.floor(s * 10) / 10
    throttle = np.where((held >= 2.0) & (held < 10.0), 0.3, 0.0)
    steering = np.where((held >= 2.0) & (held < 10.0), 0.5 * np.sin(held), 0.0)
    enc = np.where(moving, 1.0, 0.0)
    t_sensors = np.where(s < 0.5, 0.0, s + 300.0)  # the unusable sensor clock of real files
    path = write_dart_csv(tmp_path / "rec.csv", t, x, y, yaw, throttle, steering, enc,
                          t_sensors=t_sensors)
    return path, dict(t=t, s=s, angle=angle, throttle=throttle, steering=steering)


def test_reader_builds_a_uniform_trimmed_run(synthetic):
    path, truth = synthetic
    settings = DartSettings(command_delay_s=0.0, trim_margin_s=0.5)
    run = read_recording(path, settings)
    assert run.x is None and run.system == "rc_car" and run.y.shape == (len(run), 4)
    np.testing.assert_allclose(np.diff(run.t), 0.01, atol=1e-9)
    # Trimmed to 1.5 s .. 10.5 s of the recording (motion or throttle 2-10 s, 0.5 s margins;
    # the motion detector's 50 ms smoothing may widen it by a few samples).
    assert abs(run.t[0] - 1.5) < 0.04 and abs(run.t[-1] - 10.5) < 0.04
    s_grid = run.t
    angle = 1.0 * np.clip(s_grid - 2.0, 0.0, 8.0)
    np.testing.assert_allclose(run.y[:, 2], angle, atol=2e-3)  # unwrapped past pi
    assert run.y[:, 2].max() > 7.5
    np.testing.assert_allclose(run.y[:, 0], np.sin(angle), atol=2e-3)
    # Zero-order hold at 10 Hz: the throttle steps at 2.0 s and 10.0 s of the recording.
    on = s_grid[run.u[:, 0] > 0]
    assert abs(on[0] - 2.0) < 0.012 and abs(on[-1] - 9.99) < 0.012
    # Steering 0.5 sin(held time); next to a 0.1 s boundary the 0.3 ms clock jitter decides
    # whether the row before or after it is the last one, so allow the previous value there.
    got = run.u[run.u[:, 0] > 0, 1]
    now, before = (0.5 * np.sin(np.floor(np.round(on - d, 6) * 10) / 10) for d in (0.0, 0.01))
    assert np.all(np.isclose(got, now, atol=1e-12) | np.isclose(got, before, atol=1e-12))
    assert np.mean(np.isclose(got, now, atol=1e-12)) > 0.9


def test_held_encoder_samples_are_missing(tmp_path):
    """Sensor packets at 10 Hz inside the 100 Hz Vicon rows: each grid sample with a new packet
    since the previous one has its encoder value, the nine copies between are missing (NaN);
    ``held="hold"`` keeps the copies. A packet whose encoder value repeats is still a sample."""
    rng = np.random.default_rng(1)
    t = np.arange(600) * 0.01 + rng.normal(0, 3e-4, 600) + 1.7e9
    s = t - t[0]
    packet = np.floor(s * 10) / 10  # the sensor packet each row holds
    enc = np.where(packet < 3.0, 1.0 + packet, 4.0)  # constant from 3 s: repeated, yet sampled
    path = write_dart_csv(tmp_path / "p.csv", t, s, 0 * s, 0 * s, 0.3 + 0 * s, 0 * s, enc,
                          t_sensors=packet + 300.0)
    settings = DartSettings(command_delay_s=0.0, trim_margin_s=0.0)
    run, held = read_recording(path, settings), read_recording(path, DartSettings(
        command_delay_s=0.0, trim_margin_s=0.0, held="hold"))
    fresh = ~np.isnan(run.y[:, 3])
    assert 0.09 < fresh.mean() < 0.11 and np.isnan(held.y[:, 3]).sum() == 0
    np.testing.assert_array_equal(run.y[fresh, 3], held.y[fresh, 3])
    # each fresh sample is within two grid steps after a packet boundary (the clock jitter
    # decides whether the row at a boundary still holds the previous packet)
    after = run.t[fresh] - np.floor(np.round(run.t[fresh], 6) * 10) / 10
    assert np.all(after < 0.022)
    assert fresh[run.t > 3.5].sum() >= 20  # repeated values of new packets are samples
    np.testing.assert_array_equal(run.y[:, :3], held.y[:, :3])
    np.testing.assert_array_equal(run.u, held.u)  # commands are held either way
    with pytest.raises(ValueError, match="held must be one of"):
        DartSettings(held="drop")


def test_command_delay_shifts_the_commands(synthetic):
    path, _ = synthetic
    raw = read_recording(path, DartSettings(command_delay_s=0.0))
    late = read_recording(path, DartSettings(command_delay_s=0.05))
    np.testing.assert_array_equal(late.y, raw.y)
    k = int(np.argmax(raw.u[:, 0] > 0))
    assert late.u[k + 4, 0] == 0.0 and late.u[k + 6, 0] == 0.3  # 5 samples later (+-1 jitter)


def test_safety_off_zeroes_the_throttle(tmp_path):
    s = np.arange(300) * 0.01
    x = np.where(s > 1.0, s - 1.0, 0.0)
    safety = (s < 2.0).astype(float)
    path = write_dart_csv(tmp_path / "s.csv", s, x, 0 * s, 0 * s, 0.4 + 0 * s, 0 * s, 0 * s, safety)
    run = read_recording(path, DartSettings(command_delay_s=0.0, trim_margin_s=0.0))
    assert run.u[:, 0].max() == 0.4 and run.u[-1, 0] == 0.0


@pytest.mark.parametrize("problem, match", [
    ("missing", "missing columns"),
    ("text", "non-numeric"),
    ("nan", "non-finite value in column 'vicon x'"),
    ("backwards", "must increase strictly"),
    ("gap", "Vicon gap of 0.200 s"),
    ("still", "never moves"),
])
def test_malformed_recordings_fail_clearly(tmp_path, problem, match):
    s = np.arange(100) * 0.01
    cols = dict(t_vicon=s.copy(), x=s.copy(), y=0 * s, yaw=0 * s, throttle=0.3 + 0 * s,
                steering=0 * s, enc=0 * s)
    if problem == "backwards":
        cols["t_vicon"][50] = cols["t_vicon"][48]
    elif problem == "gap":
        cols["t_vicon"][60:] += 0.19
    elif problem == "still":
        cols["x"][:], cols["throttle"][:] = 0.0, 0.0
    elif problem == "nan":
        cols["x"][7] = np.nan
    path = write_dart_csv(tmp_path / "bad.csv", *cols.values())
    if problem == "missing":
        lines = path.read_text().splitlines()
        path.write_text("\n".join(line.rsplit(",", 1)[0] for line in lines) + "\n")
    elif problem == "text":
        lines = path.read_text().splitlines()
        lines[5] = lines[5].replace(lines[5].split(",")[11], "abc")
        path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=match):
        read_recording(path)


def test_missing_file_and_bad_settings(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_recording(tmp_path / "nope.csv")
    with pytest.raises(ValueError, match="command_delay_s"):
        DartSettings(command_delay_s=-0.1)
    assert list_recordings(tmp_path) == []


def test_beacon_ranges():
    pos = np.array([[0.0, 0.0], [3.0, 4.0]])
    ranges = beacon_ranges(pos, ((0.0, 0.0), (3.0, 0.0)))
    np.testing.assert_allclose(ranges, [[0.0, 3.0], [5.0, 4.0]], atol=1e-15)
    with pytest.raises(DataError, match=r"\(T, 2\)"):
        beacon_ranges(np.zeros((3, 3)))


# -- the real recordings (skipped without ../shared/data) --------------------------------------
RECORDINGS = list_recordings()
needs_data = pytest.mark.skipif(not RECORDINGS, reason="DART recordings not found (../shared/data)")


def vicon_derivatives(run: Run):
    """States and their derivatives from the Vicon data by Savitzky-Golay (0.31 s, cubic)."""
    def sg(z, d=0):
        return savgol_filter(z, 31, 3, deriv=d, delta=run.dt)

    x, y, psi = run.y[:, 0], run.y[:, 1], run.y[:, 2]
    vx, vy = sg(x, 1), sg(y, 1)
    v = np.hypot(vx, vy)
    return np.c_[sg(x), sg(y), v, sg(psi)], np.c_[vx, vy, sg(v, 1), sg(psi, 1)]


@needs_data
@pytest.mark.parametrize("path", RECORDINGS, ids=lambda p: p.stem[-8:])
def test_real_recording_sanity_and_prior_gap(car, path):
    """Numbers measured on the four recordings (see the rc_car docstring), with margins."""
    run = read_recording(path)
    assert 40.0 < run.t[-1] < 105.0
    np.testing.assert_allclose(np.diff(run.t), car.dt, atol=1e-9)
    assert np.abs(np.diff(run.y[:, 2])).max() < 0.1  # yaw unwrapped
    assert run.u[:, 0].min() >= 0 and run.u[:, 0].max() <= 1 and np.abs(run.u[:, 1]).max() <= 1
    # the car's declared input limits are the commands' real ranges: the estimators keep every
    # logged command
    assert not InputCheck(plausible_inputs(car), car.nu).apply(run.u)[1].any()
    states, derivs = vicon_derivatives(run)
    moving = states[:, 2] > 0.3
    assert 1.0 < np.median(states[moving, 2]) < 3.0 and states[:, 2].max() < 4.5
    err = derivs - car.f(states, run.u)
    rms = np.sqrt(np.mean(err[moving] ** 2, axis=0))
    print(f"{path.name}: prior derivative error rms (xdot, ydot, vdot, psidot) {rms.round(3)}")
    # Kinematics: the prior explains the velocity direction and most of the yaw rate.
    assert np.all(rms[:2] < 0.35)
    assert rms[3] < 0.5 * np.sqrt(np.mean(derivs[moving, 3] ** 2))  # measured 0.09-0.43
    # The gap the diagnosis must explain: no dead band or friction, so vdot is far too high...
    assert -9.0 < err[moving, 2].mean() < -4.0
    # ... and DART's own motor and friction model removes most of it.
    err_true = derivs[:, 2] - car.f(states, run.u, variant="true")[:, 2]
    assert np.sqrt(np.mean(err_true[moving] ** 2)) < rms[2] / 3


@needs_data
@pytest.mark.parametrize("method", ["rts", "ukf_rts"])
def test_observers_run_on_a_real_recording(car, method):
    """15 s of the first recording: the observers track the Vicon pose and the Vicon speed."""
    full = read_recording(RECORDINGS[0], DartSettings(held="hold"))  # observers: no missing yet
    n = 1500
    run = Run(full.t[:n], full.u[:n], full.y[:n], None, full.system)
    obs = observe(run, car, method)
    states, _ = vicon_derivatives(run)
    pose_err = np.abs(obs.zeta[:, [0, 1, 3]] - run.y[:, :3]).max(axis=0)
    speed_rms = np.sqrt(np.mean((obs.zeta[50:-50, 2] - states[50:-50, 2]) ** 2))
    print(f"{method}: max pose error {pose_err}, speed rms vs Vicon {speed_rms:.3f} m/s")
    assert np.all(pose_err < [0.01, 0.01, 0.05])
    assert speed_rms < (0.02 if method == "ukf_rts" else 0.1)  # measured 0.002, 0.041
