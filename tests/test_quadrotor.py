"""Quadrotor system, NanoBench loader, Savitzky-Golay reference and the flight study (issue 4)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

import learnest_codegen
from learnest_codegen.errors import DataError, SettingsError, UnknownNameError
from learnest_codegen.experiments import quadrotor as fs
from learnest_codegen.experiments.quadrotor_cases import GROUP_INDICES
from learnest_codegen.experiments.store import code_hash, tree_hash
from learnest_codegen.recordings import crazyflie as nb
from learnest_codegen.recordings import data_root
from learnest_codegen.simulation import simulate
from learnest_codegen.systems import SYSTEMS
from learnest_codegen.systems.quadrotor import (
    GRAVITY,
    K_DRAG,
    K_T,
    QUADROTOR,
    QUADROTOR_STATE,
    TAU_MOTOR,
    V_NOM,
    reference,
)

SYS = QUADROTOR


# --- the system -----------------------------------------------------------------------------------


def test_registered_and_prior_is_triple_integrator():
    assert SYSTEMS["quadrotor"] is SYS
    A = np.kron(np.diag([1.0, 1.0], 1), np.eye(3))  # [[0 I 0], [0 0 I], [0 0 0]]
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=(50, 9)), rng.normal(size=(50, 4))
    np.testing.assert_allclose(SYS.f(x, u), x @ A.T, rtol=0, atol=0)
    assert SYS.residual_state_names == ["ax", "ay", "az"]


def test_residual_inputs_leave_out_position():
    """Translation invariance: no residual sees p; the state variant sees (v, a) only, and a
    model directory loads only with the system it was trained for."""
    from learnest_codegen.errors import ModelMismatchError
    from learnest_codegen.learning.training import TrainedModel, load_model, make_net

    assert SYSTEMS["quadrotor_state"] is QUADROTOR_STATE
    va = ["vx", "vy", "vz", "ax", "ay", "az"]
    assert SYS.residual_input_names == [*va, "Tx", "Ty", "Tz", "vbat"]
    assert QUADROTOR_STATE.residual_input_names == va
    net = make_net(QUADROTOR_STATE)
    x, u = torch.randn(5, 9, dtype=torch.float64), torch.randn(5, 4, dtype=torch.float64)
    shifted = x.clone()
    shifted[:, :3] += 10.0
    u2 = u + 1.0
    torch.testing.assert_close(net(x, u), net(shifted, u2))  # blind to position and inputs
    assert not torch.equal(make_net(SYS)(x, u), make_net(SYS)(x, u2))  # sees the inputs
    with torch.no_grad():
        for param in net.parameters():
            param.add_(0.1)
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        TrainedModel(QUADROTOR_STATE, net, {"system": "quadrotor_state", "nx": 9, "nu": 4,
                                            "network": net.settings.to_json()}).save(d)
        torch.testing.assert_close(load_model(d, QUADROTOR_STATE).net(x, u), net(x, u))
        with pytest.raises(ModelMismatchError, match="quadrotor_state"):
            load_model(d, SYS)


def test_linear_rts_discretisation_and_accuracy():
    """The observer's (F, Q) are the closed-form white-jerk triple integrator (FilterPy's
    Q_continuous_white_noise), and on a simulated run its accelerations are ten times closer to
    the truth than the accelerometer's."""
    from filterpy.common import Q_continuous_white_noise

    from learnest_codegen import observers

    run = simulate(SYS, 2, duration=6.0)
    A, C = observers._linear_prior(SYS)
    q = {6: 0.3, 7: 0.3, 8: 2.0}
    kf = observers._linear_kf(run, A, C, np.eye(6), q)[3]
    dt = SYS.dt
    for axis, qa in enumerate((0.3, 0.3, 2.0)):
        idx = np.ix_([axis, 3 + axis, 6 + axis], [axis, 3 + axis, 6 + axis])
        np.testing.assert_allclose(kf.F[idx], [[1, dt, dt**2 / 2], [0, 1, dt], [0, 0, 1]], atol=1e-14)
        np.testing.assert_allclose(kf.Q[idx], Q_continuous_white_noise(3, dt, qa), rtol=1e-9, atol=1e-20)
    lin = observers.observe(run, SYS, "linear_rts")
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    assert rms(lin.zeta[:, 6:] - run.x[:, 6:]) < 0.1 * rms(run.y[:, 3:] - run.x[:, 6:])
    assert rms(lin.zeta[:, 3:6] - run.x[:, 3:6]) < 0.01  # m/s
    assert set(lin.info["spectral_density"]) == {"ax", "ay", "az"}
    with pytest.raises(ValueError, match="linear_rts"):
        observers.observe(simulate(SYSTEMS["cartpole"], 0, duration=1.0), SYSTEMS["cartpole"],
                          "linear_rts")


@pytest.mark.parametrize("variant", ["prior", "true"])
def test_numpy_torch_casadi_agree(variant):
    rng = np.random.default_rng(1)
    x, u = rng.normal(size=(20, 9)), rng.normal(size=(20, 4)) + [0, 0, 0.86, 3.5]
    ref = SYS.f(x, u, variant=variant)
    th = SYS.f(torch.as_tensor(x), torch.as_tensor(u), variant=variant).numpy()
    F = SYS.casadi_f(variant)
    ca = np.stack([np.asarray(F(xi, ui)).ravel() for xi, ui in zip(x, u)])
    np.testing.assert_allclose(th, ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ca, ref, rtol=1e-12, atol=1e-12)
    H = SYS.casadi_h()
    np.testing.assert_allclose(np.asarray(H(x[0], u[0])).ravel(), SYS.h(x[0], u[0]), atol=1e-15)


def test_true_dynamics_equal_the_thrust_lag_model():
    """The 9-state truth is the 12-state model (p, v, thrust acceleration f) reduced."""
    run = simulate(SYS, 3, duration=4.0)

    def full(t, s):
        k = min(int(t / SYS.dt + 1e-9), len(run) - 1)
        T, vbat = run.u[k, :3], run.u[k, 3]
        v, f = s[3:6], s[6:9]
        a = f - [0, 0, GRAVITY] - K_DRAG * v
        return np.concatenate([v, a, (K_T * vbat / V_NOM * T - f) / TAU_MOTOR])

    x0 = np.array([*SYS.x0[:6], 0.0, 0.0, GRAVITY])
    sol = solve_ivp(full, (0, run.t[-1]), x0, t_eval=run.t, rtol=1e-10, atol=1e-12, max_step=SYS.dt)
    s = sol.y.T
    accel = s[:, 6:9] - [0, 0, GRAVITY] - K_DRAG * s[:, 3:6]
    np.testing.assert_allclose(run.x[:, :6], s[:, :6], atol=1e-6)
    np.testing.assert_allclose(run.x[:, 6:], accel, atol=1e-5)


def test_feedforward_flies_the_reference():
    """The excitation inverts the true model, so the truth tracks the reference path."""
    run = simulate(SYS, 5, duration=10.0)
    rng = np.random.default_rng(5)  # the draws excitation() makes, in its order
    shape = str(rng.choice(sorted(["circle", "figure8"])))
    rate = rng.uniform(0.5, 1.0) * rng.choice([-1.0, 1.0])
    # The command is held for a sample (zero-order hold): the truth flies the reference half a
    # sample late (10 mm off on time, 0.01 mm half a sample later).
    ref = reference(shape, rate, np.maximum(run.t - 0.5 * SYS.dt, 0.0))
    np.testing.assert_allclose(run.x[:, :3], ref[0], atol=5e-5)
    np.testing.assert_allclose(run.x[:, 3:6], ref[1], atol=5e-5)
    np.testing.assert_allclose(run.x[:, 6:], ref[2], atol=2e-3)
    assert np.ptp(run.x[:, 0]) > 1.5  # it really flies the 1 m radius path


# --- loader ---------------------------------------------------------------------------------------

N_GROUND, N_AIR, DT = 150, 400, 0.01


def _flight_table(gap_at: int | None = 300):
    """A synthetic NanoBench log: on the ground, then a climb and a circle, then landed."""
    n = 2 * N_GROUND + N_AIR
    t = 1.7e9 + DT * np.arange(n)
    tau = np.clip(np.arange(n) - N_GROUND, 0, N_AIR) * DT  # flight time
    w, r = 1.0, 0.5
    wz = np.pi / (N_AIR * DT)  # climb and descend once
    p = np.stack([r * np.sin(w * tau), r * (1 - np.cos(w * tau)), 0.03 + 0.5 * np.sin(wz * tau)], 1)
    a = np.stack([-r * w**2 * np.sin(w * tau), r * w**2 * np.cos(w * tau),
                  -0.5 * wz**2 * np.sin(wz * tau)], 1)
    flying = (np.arange(n) >= N_GROUND) & (np.arange(n) < N_GROUND + N_AIR)
    a[~flying] = 0.0
    rot = Rotation.from_euler("xyz", np.stack([0.1 * np.sin(tau), 0.05 * np.cos(tau), 0.3 * tau], 1))
    acc_g = rot.inv().apply(a + [0, 0, GRAVITY]) / GRAVITY
    pwm = np.where(flying, 0.8 + 0.05 * np.sin(tau), 0.0) * nb.PWM_FULL
    cols = {"t": t, **dict(zip(nb.POSITION, p.T)), **dict(zip(nb.QUATERNION, rot.as_quat().T)),
            **dict(zip(nb.ACCEL, acc_g.T)), **{m: pwm for m in nb.MOTORS},
            nb.VBAT: 3.9 - 0.001 * np.arange(n),
            **{c: v for c, v in zip(nb.ONBOARD, np.hstack([p + 0.01, np.zeros((n, 3)), a]).T)},
            "extra_column": np.ones(n)}
    if gap_at is not None:
        cols = {k: np.delete(v, gap_at) for k, v in cols.items()}
    return cols, p, a, flying


def _write(path, cols):
    names = list(cols)
    table = np.stack([cols[n] for n in names], 1)
    with open(path, "w") as fh:
        fh.write(",".join(names) + "\n")
        np.savetxt(fh, table, delimiter=",", fmt="%.12f")
    return path


def test_read_flight_trims_resamples_and_converts(tmp_path):
    cols, p, a, flying = _flight_table(gap_at=300)
    path = _write(tmp_path / "B9_test_rep1.csv", cols)
    (tmp_path / "B9_test_rep1_metadata.yaml").write_text("trajectory_id: B9\nparams:\n  speed_mps: 0.5\n")
    flight = nb.read_flight(path)
    assert flight.timing.gaps == 1 and flight.timing.dt == pytest.approx(DT)
    first, last = flight.trimmed
    # airborne: motors on and more than 15 cm above the 3 cm ground level
    expected = np.flatnonzero(flying & (p[:, 2] > 0.03 + 0.15))
    assert (first, last) == (expected[0], expected[-1])
    np.testing.assert_allclose(np.diff(flight.run.t), DT, atol=1e-9)
    sl = slice(first, last + 1)
    # the missing sample (index 300) is interpolated; everywhere else the conversion is exact
    # up to the ~1e-7 s round-off of absolute time stamps stored as text
    keep = np.arange(first, last + 1) != 300
    np.testing.assert_allclose(flight.run.y[keep, :3], p[sl][keep], atol=1e-6)
    np.testing.assert_allclose(flight.run.y[~keep, :3], p[300:301], atol=1e-4)
    np.testing.assert_allclose(flight.run.y[keep, 3:], a[sl][keep], atol=1e-6)
    np.testing.assert_allclose(flight.run.y[~keep, 3:], a[300:301], atol=2e-3)
    throttle = 0.8 + 0.05 * np.sin((np.arange(first, last + 1) - N_GROUND) * DT)
    np.testing.assert_allclose(np.linalg.norm(flight.run.u[:, :3], axis=1)[keep], throttle[keep], atol=1e-6)
    np.testing.assert_allclose(flight.run.u[:, 3], 3.9 - 0.001 * np.arange(first, last + 1), atol=1e-6)
    assert flight.onboard.shape == flight.reference.shape == (len(flight.run), 9)
    assert flight.metadata == {"trajectory_id": "B9", "params.speed_mps": "0.5"}
    assert flight.run.system == "quadrotor"


def test_held_position_and_accelerometer_rows_are_missing(tmp_path):
    """A row repeating the previous position (or accelerometer) exactly is a held value: the
    grid sample at it has that output missing, the other output and the neighbours stay;
    ``held="hold"`` reads the file as before."""
    cols, p, a, flying = _flight_table(gap_at=None)
    n = len(cols["t"])  # a real Vicon never repeats a pose exactly on the ground either
    for i, name in enumerate(nb.POSITION):
        cols[name] = cols[name] + 1e-5 * np.sin(0.7 * np.arange(n) + i)
    air = np.flatnonzero(flying & (p[:, 2] > 0.3))
    k_pos, k_acc = int(air[50]), int(air[120])
    for name in nb.POSITION:
        cols[name][k_pos] = cols[name][k_pos - 1]
    for name in nb.ACCEL:
        cols[name][k_acc] = cols[name][k_acc - 1]
    path = _write(tmp_path / "B9_held_rep1.csv", cols)
    flight, before = nb.read_flight(path), nb.read_flight(path, held="hold")
    first = flight.trimmed[0]
    missing = np.argwhere(np.isnan(flight.run.y))
    assert sorted({(r + first, c // 3) for r, c in missing}) == [(k_pos, 0), (k_acc, 1)]
    assert not np.isnan(before.run.y).any()
    fresh = ~np.isnan(flight.run.y)
    np.testing.assert_allclose(flight.run.y[fresh], before.run.y[fresh], atol=1e-9)
    with pytest.raises(ValueError, match="held must be one of"):
        nb.read_flight(path, held="drop")


def test_thrust_vector_is_body_z_times_throttle():
    rot = Rotation.from_euler("xyz", [[0.2, -0.1, 1.0]])
    got = nb.thrust_vector(rot.as_quat(), np.array([0.8]))
    np.testing.assert_allclose(got[0], 0.8 * rot.as_matrix()[0][:, 2], atol=1e-15)


@pytest.mark.parametrize("change, match", [
    (lambda c: c.pop("imu_acc_y"), "missing columns \\['imu_acc_y'\\]"),
    (lambda c: c["t"].__setitem__(20, c["t"][19]), "time must increase strictly"),
    # a dropout of 0.21 s in a 4 s flight, cut with 1.5 s either side, leaves too little
    (lambda c: c["t"].__setitem__(slice(400, None), c["t"][400:] + 0.2),
     "left once the faulty spans are cut.*dropout.*no data for 0.210 s"),
    (lambda c: [c[m].__setitem__(slice(None), 0.0) for m in nb.MOTORS], "no airborne samples"),
])
def test_malformed_flights_raise_data_error(tmp_path, change, match):
    cols, *_ = _flight_table(gap_at=None)
    change(cols)
    with pytest.raises(DataError, match=match):
        nb.read_flight(_write(tmp_path / "bad.csv", cols))


def test_a_row_with_a_non_finite_value_is_left_out_and_said(tmp_path):
    """A marker occlusion (NaN) drops the row: resampling bridges it, a finding says so."""
    cols, *_ = _flight_table(gap_at=None)
    cols["px"][10] = np.nan
    flight = nb.read_flight(_write(tmp_path / "occluded.csv", cols))
    (finding,) = flight.findings
    assert (finding.check, finding.action) == ("dropout", "kept")
    assert "1 row(s) with non-finite values" in finding.detail
    with pytest.raises(DataError, match="non-finite value in column 'px' at data row 11"):
        nb.read_table(tmp_path / "occluded.csv")


def test_non_numeric_and_empty_files(tmp_path):
    cols, *_ = _flight_table(gap_at=None)
    path = _write(tmp_path / "text.csv", cols)
    lines = path.read_text().splitlines()
    lines[5] = lines[5].replace(lines[5].split(",")[1], "abc", 1)
    path.write_text("\n".join(lines))
    with pytest.raises(DataError, match="non-numeric"):
        nb.read_flight(path)
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(DataError, match="empty file"):
        nb.read_flight(tmp_path / "empty.csv")
    with pytest.raises(FileNotFoundError):
        nb.read_flight(tmp_path / "absent.csv")


# --- Savitzky-Golay reference ---------------------------------------------------------------------


def test_savgol_reference_exact_on_quadratics():
    t = np.arange(600) * DT
    c = np.array([[0.3, -1.0, 0.5], [2.0, 0.1, -0.7], [1.0, 0.0, 0.2]])  # p = c0 + c1 t + c2 t^2
    p = c[0] + np.outer(t, c[1]) + np.outer(t**2, c[2])
    ref = nb.reference_states(p, DT)
    np.testing.assert_allclose(ref[:, :3], p, atol=0)
    np.testing.assert_allclose(ref[:, 3:6], c[1] + 2 * np.outer(t, c[2]), atol=1e-9)
    np.testing.assert_allclose(ref[:, 6:], np.broadcast_to(2 * c[2], (600, 3)), atol=1e-8)


@pytest.mark.parametrize("w", [1.0, 2.0])
def test_savgol_velocity_gain_on_a_sinusoid(w):
    """The velocity of an order-2 least-squares fit to sin(w t) over samples t_j = j dt,
    |j| <= m, is cos(w t) sum(t_j sin(w t_j)) / sum(t_j^2) at the window's centre (the odd part
    of the fit; the even t^2 term has no slope there): closed form against scipy's filter."""
    t = np.arange(3000) * DT
    p = np.stack([np.sin(w * t)] * 3, 1)
    ref = nb.reference_states(p, DT, window=151)
    tj = DT * np.arange(-75, 76)
    gain = np.sum(tj * np.sin(w * tj)) / (w * np.sum(tj**2))
    x = w * 75 * DT  # the docstring's continuous approximation 3 (sin x - x cos x) / x^3
    assert gain == pytest.approx(3 * (np.sin(x) - x * np.cos(x)) / x**3, rel=5e-3)
    inner = slice(200, -200)
    np.testing.assert_allclose(ref[inner, 3], gain * w * np.cos(w * t[inner]), atol=1e-9)


# --- the study, end to end on simulated runs ------------------------------------------------------


def test_flight_study_on_simulated_quadrotor(tmp_path):
    """Train on one simulated run, compile KNODE-UKF and KNODE-MHE-RTI, test on the others: the
    pipeline of the real experiment, fast (short runs, the fast estimators). The report is
    paired per run, and records the gate's rejections and the share outside the training range.
    12 s runs: trained on 8 s, the KNODE estimators were 3-4 % worse on sim_seed1 (measured:
    +10/+8 % and +54/+50 % on the two test runs with 12 s)."""
    cases = fs.simulated_cases(range(3), duration=12.0)
    settings = fs.StudySettings(training=replace(fs.StudySettings().training, epochs=30),
                                estimators=("ukf", "mhe_rti"))
    (summary,) = fs.run_study(cases, tmp_path, train=["sim_seed0"], features=["state"],
                              settings=settings, progress=False)
    assert set(summary.per_case) == {"sim_seed1", "sim_seed2"}
    for label in ("UKF", "KNODE-UKF", "MHE-RTI", "KNODE-MHE-RTI"):
        mses = [summary.per_case[c][label]["mse"] for c in summary.per_case]
        assert summary.medians[label] == pytest.approx(np.median(mses))
        assert all(np.isfinite(mses))
        assert all(summary.per_case[c][label]["rejected"] >= 0 for c in summary.per_case)
    for knode, nominal in (("KNODE-UKF", "UKF"), ("KNODE-MHE-RTI", "MHE-RTI")):
        paired = summary.paired[knode]["all"]
        changes = [100 * (summary.per_case[c][nominal]["mse"] - summary.per_case[c][knode]["mse"])
                   / summary.per_case[c][nominal]["mse"] for c in ("sim_seed1", "sim_seed2")]
        assert paired.mean == pytest.approx(np.mean(changes))
        assert paired.improved == sum(c > 0 for c in changes) == 2  # it learns the lag and drag
        assert set(summary.paired[knode]) == {"all", "sim"}
    nominal, knode = summary.medians["UKF"], summary.medians["KNODE-UKF"]
    assert summary.improvement["KNODE-UKF"] == pytest.approx(100 * (nominal - knode) / nominal)
    assert all(0.0 <= summary.per_case[c]["KNODE-UKF"]["outside"] <= 1.0 for c in summary.per_case)
    assert (tmp_path / "quadrotor.png").is_file()
    report = (tmp_path / "quadrotor.md").read_text()
    assert "| sim_seed0 | state | KNODE-UKF | all (2) |" in report
    # resumable: a second call reuses the results file
    again = fs.train_and_test(cases[0], cases[1:], "state", tmp_path, settings, progress=False)
    knode_mse = summary.per_case["sim_seed1"]["KNODE-UKF"]["mse"]
    assert again["cases"]["sim_seed1"]["KNODE-UKF"]["mse"] == knode_mse


def test_paired_figures_against_hand_computation():
    from learnest_codegen.experiments.quadrotor_report import Paired, trajectory_type

    nominal = {"a": 1.0, "b": 2.0, "c": 4.0, "d": float("nan")}
    knode = {"a": 0.5, "b": 2.2, "c": 3.0, "d": 1.0}
    p = Paired.of(nominal, knode)
    assert p.changes == pytest.approx({"a": 50.0, "b": -10.0, "c": 25.0})  # d has no nominal MSE
    assert (p.mean, p.median, p.improved, p.n) == (pytest.approx(65 / 3), 25.0, 2, 3)
    assert (p.worst_flight, p.worst) == ("b", pytest.approx(-10.0))
    assert p.median_mse == pytest.approx(100 * (2.0 - 2.2) / 2.0)  # the medians' change: worse
    assert "2/3 better" in p.headline()
    assert trajectory_type("B3_figure8_fast_rep1") == "figure8"
    assert trajectory_type("B2_circle_slow_rep3") == "circle"
    assert trajectory_type("sim_seed12") == "sim"


def test_protocol_folds():
    run = fs.simulated_cases([0], duration=1.0)[0].run
    names = ["B2_circle_a_rep1", "B2_circle_b_rep1", "B3_figure8_a_rep1", "B3_figure8_b_rep1",
             "B3_figure8_c_rep1"]
    cases = [fs.Case(n, run, run.x) for n in names]
    by_type = fs.folds(cases, "leave-type-out")
    assert [(f.label, [c.name for c in f.train], [c.name for c in f.tests]) for f in by_type] == [
        ("all_but_circle", names[2:], names[:2]), ("all_but_figure8", names[:2], names[2:])]
    one_out = fs.folds(cases, "leave-one-out")
    assert [len(f.train) for f in one_out] == [4] * 5
    assert [f.tests[0].name for f in one_out] == names
    assert all(f.tests[0] not in f.train for f in one_out)
    with pytest.raises(UnknownNameError, match="unknown protocol"):
        fs.folds(cases, "leave-all-out")
    with pytest.raises(DataError, match="two trajectory types"):
        fs.folds(cases[:2], "leave-type-out")
    with pytest.raises(UnknownNameError, match="mhe_fast"):
        fs.StudySettings(estimators=("mhe_fast",))
    with pytest.raises(SettingsError, match="not to 'leave-one-out'"):  # before any work
        fs.run_study(cases, "unused", protocol="leave-one-out", matrix=["B2_circle_a_rep1"])


def test_unknown_names():
    cases = fs.simulated_cases([0, 1], duration=2.0)
    with pytest.raises(UnknownNameError, match="unknown training case"):
        fs.run_study(cases, "/nonexistent", train=["nope"])
    with pytest.raises(UnknownNameError, match="unknown features"):
        fs.feature_system("wind")


def test_initial_state_from_first_measurements():
    run = simulate(SYS, 1, duration=2.0, x0=np.array([0.5, -0.2, 1.0, 0.3, 0.1, -0.2, 0, 0, 0]))
    x0 = fs.initial_state(run)
    np.testing.assert_allclose(x0[:3], run.y[0, :3])
    np.testing.assert_allclose(x0[3:6], run.x[5, 3:6], atol=0.05)  # 0.1 s line fit through 1 mm noise


# --- real flights ---------------------------------------------------------------------------------


def _nanobench():
    root = data_root()
    if root is None or not (root / "nanobench").is_dir() or not nb.list_flights(root):
        pytest.skip("NanoBench flights not found (../shared/data/nanobench or $LEARNEST_DATA)")
    return root


def test_real_flights_load():
    flights = [nb.read_flight(p) for p in nb.list_flights(_nanobench())]
    assert len(flights) >= 2
    # the dataset interpolates its onboard streams onto the Vicon clock: no held output is
    # left inside a trimmed flight, so held="missing" changes nothing (docs/reports/flights.md)
    assert not any(np.isnan(f.run.y).any() for f in flights)
    for f in flights:
        assert f.duration > 10.0 and f.run.y.shape[1] == 6
        assert np.all(f.run.y[:, 2] > 0.15)  # trimmed: airborne only
        assert np.all(np.abs(f.run.y[:, 3:]) < 20.0)  # in m/s^2; no landing impact, no brown-out
        assert np.median(np.abs(f.run.u[:, 2])) == pytest.approx(0.86, abs=0.06)  # hover throttle


def test_real_flights_inside_the_declared_input_limits():
    """The quadrotor declares its inputs' real ranges (thrust components +-1, one LiPo cell
    0-4.5 V) and the estimators gate inputs beyond them: no sample of any real flight is outside
    (the limits leave out only glitches), while a value just beyond each end is rejected."""
    from learnest_codegen.estimators.inputs import InputCheck, plausible_inputs

    flights = [nb.read_flight(p) for p in nb.list_flights(_nanobench())]
    quadrotors = [s for n, s in SYSTEMS.items() if n.startswith("quadrotor")]
    assert len({s.input_limits for s in quadrotors}) == 1  # the same vehicle, the same inputs
    system = quadrotors[0]
    check = InputCheck(plausible_inputs(system), system.nu)
    for f in flights:
        assert not check.apply(f.run.u)[1].any(), f.name
    lo, hi = np.array(system.input_limits).T
    assert check.apply(lo - 1e-3)[1].all() and check.apply(hi + 1e-3)[1].all()


def test_real_flights_fitted_prior_helps_every_held_out_figure_eight(tmp_path):
    """The grey-box step on real data in the default run (UKF only, so it is quick): the prior's
    acceleration rows fitted on three circles make the UKF better on every figure-eight held
    out (measured: +7 to +13 %, mean +10 %)."""
    from learnest_codegen.export import prior_model
    from learnest_codegen.learning.prior_fit import fit_linear_params, fitted_system
    from learnest_codegen.observers import observe
    from learnest_codegen.pipeline import make_estimator
    from learnest_codegen.systems.quadrotor import QUADROTOR_LINEAR

    cases = {c.name: c for c in fs.flight_cases(_nanobench())}
    train = [cases[f"B2_circle_{s}_rep1"] for s in ("slow", "medium", "fast")]
    tests = [c for name, c in cases.items() if name.startswith("B3_figure8") and name.endswith("rep1")]
    zetas = [observe(c.run, SYS, "linear_rts").zeta for c in train]
    params = fit_linear_params(QUADROTOR_LINEAR, list(QUADROTOR_LINEAR.params), zetas,
                               [c.run.u for c in train], SYS.dt)
    assert 0.5 < params["k_v_xy"] < 3.0 and 0.5 < params["k_v_z"] < 5.0  # 1/s^2: the paths' turn rates
    fitted = fitted_system(QUADROTOR_LINEAR, params)
    nominal = make_estimator("nominal", "ukf", system=SYS, out=tmp_path)
    grey = make_estimator(prior_model(fitted), "ukf", system=fitted, out=tmp_path)
    changes = []
    for case in tests:
        mse = [fs._run_method(e, case)["mse"] for e in (nominal, grey)]
        changes.append(100 * (mse[0] - mse[1]) / mse[0])
    assert len(tests) == 3 and min(changes) > 2.0 and np.mean(changes) > 5.0, changes


@pytest.mark.slow
def test_real_flights_knode_beats_nominal(tmp_path):
    """Issue 4's acceptance: trained on one flight, KNODE-UKF and KNODE-MHE beat UKF and MHE
    in median MSE over all other flights."""
    cases = fs.flight_cases(_nanobench())
    (summary,) = fs.run_study(cases, tmp_path, train=[fs.DEFAULT_TRAIN], features=["state"],
                              progress=False)
    assert summary.medians["KNODE-UKF"] < summary.medians["UKF"]
    assert summary.medians["KNODE-MHE"] < summary.medians["MHE"]


# --- references, per-state scores and the accelerometer offset ------------------------------------


def test_central_velocity_and_the_windowed_references_are_exact_on_quadratics():
    """Central differences are exact on a quadratic (and off by p''' h^2 / 6 on a cubic); every
    Savitzky-Golay window of :func:`references` is exact on a quadratic; the central-difference
    reference has no acceleration (NaN)."""
    t = np.arange(1200) * DT
    c = np.array([[0.3, -1.0, 0.5], [2.0, 0.1, -0.7], [1.0, 0.0, 0.2]])
    p = c[0] + np.outer(t, c[1]) + np.outer(t**2, c[2])
    v = c[1] + 2 * np.outer(t, c[2])
    cd = nb.central_velocity(p, DT)
    np.testing.assert_allclose(cd[5:-5], v[5:-5], atol=1e-10)
    assert np.isnan(cd[:5]).all() and np.isnan(cd[-5:]).all()
    cubic = np.stack([t**3] * 3, 1)
    h = 0.05  # the half window
    want = np.broadcast_to(3 * t[5:-5, None] ** 2 + h**2, (len(t) - 10, 3))
    np.testing.assert_allclose(nb.central_velocity(cubic, DT)[5:-5], want, atol=1e-9)
    refs = nb.references(p, DT)
    assert list(refs) == ["sg_0.5s", "sg_1s", "sg_1.5s", "sg_3s", "cd_0.1s"]
    inner = slice(200, -200)
    for name, ref in refs.items():
        np.testing.assert_allclose(ref[:, :3], p, atol=0)
        np.testing.assert_allclose(ref[inner, 3:6], v[inner], atol=1e-8, err_msg=name)
        if name.startswith("sg"):
            np.testing.assert_allclose(ref[inner, 6:], np.broadcast_to(2 * c[2], ref[inner, 6:].shape),
                                       atol=1e-7, err_msg=name)
        else:
            assert np.isnan(ref[:, 6:]).all()


def test_group_scores_and_the_normalised_change():
    from learnest_codegen.evaluation import group_mse, normalised_change, state_groups
    from learnest_codegen.systems.quadrotor import QUADROTOR_BIAS

    assert state_groups(SYS) == {"m": [0, 1, 2], "m/s": [3, 4, 5], "m/s^2": [6, 7, 8]}
    assert state_groups(QUADROTOR_BIAS)["m/s^2"] == [6, 7, 8, 9, 10, 11]
    rng = np.random.default_rng(3)
    x, ref = rng.normal(size=(50, 9)), rng.normal(size=(50, 9))
    ref[:10, 3] = np.nan  # no reference there
    ref[:, 6:] = np.nan  # no acceleration reference at all
    got = group_mse(x, ref, GROUP_INDICES)
    assert set(got) == {"p", "v"}
    ok = ~np.isnan(ref[:, 3:6])
    assert got["v"] == pytest.approx(np.mean((x[:, 3:6][ok] - ref[:, 3:6][ok]) ** 2), rel=1e-14)
    # every group weighs the same: halving one group's MSE and doubling another's is no change
    assert normalised_change({"p": 0.5, "v": 2.0, "a": 1.0}, {"p": 1.0, "v": 1.0, "a": 1.0}) == \
        pytest.approx(100 * (1 - (0.5 + 2.0 + 1.0) / 3))
    assert normalised_change({"p": 1e-9, "v": 1.0}, {"p": 2e-9, "v": 1.0}) == pytest.approx(25.0)


def test_the_offset_ukf_is_the_kalman_filter_and_finds_the_offset(tmp_path):
    """``quadrotor_bias`` is linear: its compiled UKF equals a hand-written Kalman filter of
    the same model (to 1e-9 of the states' scale), and on a simulated run whose accelerometer
    reads 0.3 m/s^2 high on x and 0.2 low on y it estimates the offset to 0.03 m/s^2 after 5 s."""
    from learnest_codegen.pipeline import make_estimator
    from learnest_codegen.systems.quadrotor import QUADROTOR_BIAS

    run = simulate(SYS, 4, duration=10.0)
    offset = np.array([0.3, -0.2, 0.0])
    y = run.y.copy()
    y[:, 3:] += offset
    biased = replace(run, y=y)
    ukf = make_estimator("nominal", "ukf", system=QUADROTOR_BIAS, out=tmp_path)
    x0 = np.concatenate([fs.initial_state(biased), np.zeros(3)])
    x_hat = ukf.run(biased.u, biased.y, x0)
    assert ukf.rejections == 0
    n, noise, dt = 12, QUADROTOR_BIAS.noise, SYS.dt
    A = np.zeros((n, n))
    A[0:3, 3:6] = A[3:6, 6:9] = np.eye(3)
    h = dt * A
    F = np.eye(n) + h + h @ h / 2 + h @ h @ h / 6 + h @ h @ h @ h / 24
    H = np.zeros((6, n))
    H[0:3, 0:3] = H[3:6, 6:9] = H[3:6, 9:12] = np.eye(3)
    Q, R = np.diag(np.square(noise.process_std)), np.diag(np.square(noise.measurement_std))
    x, P = x0.copy(), np.diag(np.square(noise.initial_std))
    for k, yk in enumerate(biased.y):
        if k:
            x, P = F @ x, F @ P @ F.T + Q
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        x, P = x + K @ (yk - H @ x), P - K @ S @ K.T
        np.testing.assert_allclose(x_hat[k], x, atol=1e-9 * (1 + np.abs(x)).max())
    late = biased.t > 5.0
    np.testing.assert_allclose(x_hat[late][:, 9:12].mean(axis=0), offset, atol=0.03)


def test_the_lagged_accelerometer_model_in_closed_form():
    """``quadrotor_linear_bias_lag``: the linear prior's rows, ``bdot = 0``, ``mdot = (a - m) /
    tau_acc``, ``y_a = m + b``; numpy, torch and CasADi agree (the load-time check)."""
    from learnest_codegen.learning.prior_fit import fitted_system
    from learnest_codegen.systems.check import check_system
    from learnest_codegen.systems.quadrotor import QUADROTOR_LINEAR_BIAS_LAG

    system = fitted_system(QUADROTOR_LINEAR_BIAS_LAG, {"k_v_xy": 1.5, "k_a_xy": 0.1, "k_v_z": 2.0,
                                                       "k_a_z": -0.05, "tau_acc": 0.04})
    check_system(system, "fitted quadrotor_linear_bias_lag")
    rng = np.random.default_rng(5)
    x, u = rng.normal(size=(30, 15)), rng.normal(size=(30, 4))
    f = system.f(x, u)
    k_v, k_a = np.array([1.5, 1.5, 2.0]), np.array([0.1, 0.1, -0.05])
    np.testing.assert_allclose(f[:, :6], x[:, 3:9], rtol=0, atol=0)
    np.testing.assert_allclose(f[:, 6:9], -k_v * x[:, 3:6] - k_a * x[:, 6:9], rtol=1e-14)
    np.testing.assert_allclose(f[:, 9:12], 0.0, atol=0)
    np.testing.assert_allclose(f[:, 12:15], (x[:, 6:9] - x[:, 12:15]) / 0.04, rtol=1e-14)
    np.testing.assert_allclose(system.h(x[0], u[0]), [*x[0, :3], *(x[0, 12:15] + x[0, 9:12])], rtol=1e-15)


def test_a_prior_parameter_is_chosen_by_the_same_criterion(tmp_path, monkeypatch):
    """``tune(parameters=...)``: each value of the accelerometer lag is scored at the scales
    found for the registered one, the best is kept (the record's lowest), and the estimator
    returned is that model's (its criterion the record's)."""
    from learnest_codegen.evaluation import run_estimator
    from learnest_codegen.experiments import quadrotor_tuning as qt
    from learnest_codegen.export import prior_model
    from learnest_codegen.systems.quadrotor import QUADROTOR_LINEAR_BIAS_LAG

    monkeypatch.setattr(qt, "COARSE_EXPONENTS", (-2, 0))
    monkeypatch.setattr(qt, "EXPONENT_LIMIT", 3)
    case = fs.simulated_cases([1], duration=4.0)[0]
    model = prior_model(QUADROTOR_LINEAR_BIAS_LAG)
    with pytest.warns(UserWarning, match="grid's edge"):  # two values: the choice is always an end
        tuning, estimator, record = qt.tune(model, "ukf", [case], tmp_path, system=QUADROTOR_LINEAR_BIAS_LAG,
                                            outputs=["px", "py", "pz"],
                                            parameters=[("tau_acc", (0.01, 0.04))])
    crit = record["parameter_criteria"]
    assert set(crit) == {"0.01", "0.04"}
    assert record["parameters"]["tau_acc"] == float(min(crit, key=crit.get))
    assert ["tau_acc"] in record["edge"]
    again = qt.reuse(model, "ukf", tmp_path, record, system=QUADROTOR_LINEAR_BIAS_LAG)[1]
    x0 = qt.start_state(case, 15)
    np.testing.assert_array_equal(run_estimator(again, case.run, x0, "u").x_hat,
                                  run_estimator(estimator, case.run, x0, "u").x_hat)


def test_a_study_model_with_a_fitted_prior_and_a_net_compiles_without_its_system(tmp_path):
    """A study's ``linear`` model (the fitted prior and a net) names the built-in system it was
    fitted on and its fitted parameters, so ``learnest-compile MODEL --target crazyflie`` needs
    no ``--system``: the app's estimator is the one of that model (its manifest's model hash and
    system fingerprint, the fitted parameters included) and finds its system by itself."""
    import json

    from click.testing import CliRunner

    from learnest_codegen.cli.estimation import compile_cmd
    from learnest_codegen.experiments.quadrotor_models import trained_model
    from learnest_codegen.learning.model import load_model
    from learnest_codegen.pipeline import estimator_system, expected_manifest, load_estimator

    cases = fs.simulated_cases(range(2), duration=6.0)
    settings = fs.StudySettings(training=replace(fs.StudySettings().training, epochs=3))
    directory = tmp_path / "runs" / "sim" / "linear" / "model"
    model = trained_model(cases, "linear", tmp_path, settings, directory, progress=False)
    meta = json.loads((directory / "model.json").read_text())
    assert meta["system_source"]["name"] == "quadrotor_linear" and meta["system_source"]["builtin"]
    fitted = meta["prior_params"]
    assert set(fitted) == set(SYSTEMS["quadrotor_linear"].params) and any(v != 0.0 for v in fitted.values())
    assert load_model(directory).system.fingerprint() == model.system.fingerprint()

    result = CliRunner().invoke(compile_cmd, [str(directory), "--target", "crazyflie",
                                                     "--out", str(tmp_path / "generated")])
    assert result.exit_code == 0, result.output
    (folder,) = [p for p in (tmp_path / "generated").iterdir()
                 if p.is_dir() and not p.name.endswith("_crazyflie")]
    assert (tmp_path / "generated" / f"{folder.name}_crazyflie").is_dir()
    estimator = load_estimator(folder, expect=expected_manifest(model))  # refuses another model
    found = estimator_system(estimator)  # from the folder's record, checked against its manifest
    assert found.params == fitted and found.fingerprint() == model.system.fingerprint()


def test_a_study_result_is_keyed_on_the_c_kit_as_well_as_the_python(tmp_path):
    """A resumed study reuses a result only if the code that made it is the same: a change to a C
    header (the estimators' own code) changes the hash as a Python change does."""
    (tmp_path / "ckit").mkdir()
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "ckit" / "k.h").write_text("#define K 1\n")
    before = tree_hash(tmp_path)
    (tmp_path / "__pycache__").mkdir()
    (tmp_path / "__pycache__" / "a.pyc").write_bytes(b"\0")
    assert tree_hash(tmp_path) == before
    (tmp_path / "ckit" / "k.h").write_text("#define K 2\n")
    assert tree_hash(tmp_path) != before
    assert code_hash() == tree_hash(Path(learnest_codegen.__file__).parent)
