"""Real sensor streams in the Python estimators, from theory: missing outputs, pure predictions,
run-time tuning and a wrong start.

- On a linear-Gaussian model the UKF with missing outputs equals FilterPy's Kalman filter
  that skips the missing updates (to 1e-10), and the MHE whose window holds the whole run
  equals the same filter at every sample and the Rauch-Tung-Striebel smoother over its window.
- Missing every output for k samples is k predictions (UKF: FilterPy's predict; MHE: the
  model's transition, while the window fills).
- ``set_noise`` on a running estimator equals an estimator started with those covariances.
"""

from __future__ import annotations

import dataclasses

import casadi as cs
import numpy as np
import pytest
from conftest import unscented_rounding
from filterpy.kalman import KalmanFilter

from learnest_codegen import NoiseModel, Signal, System, get_system, simulation
from learnest_codegen.data import Run, read_run, resample, write_run
from learnest_codegen.errors import DataError
from learnest_codegen.estimators.ekf import EKF
from learnest_codegen.estimators.gate import GateSettings, GateState
from learnest_codegen.estimators.mhe import MHE
from learnest_codegen.estimators.mhe_problem import MHESettings
from learnest_codegen.estimators.ukf import UKF, UKFSettings
from learnest_codegen.export import prior_model

T = 60


def oscillator() -> System:
    """A linear two-output system: RK4 of it is linear, so the filters must be the KF."""
    def dynamics(ops, x, u, p):
        return [x[1], (-p["k"] * x[0] - p["c"] * x[1] + u[0]) / p["m"]]

    params = {"m": 2.0, "k": 3.0, "c": 0.4}
    return System(
        name="osc", states=(Signal("q", "m"), Signal("v", "m/s")), inputs=(Signal("F", "N"),),
        outputs=(Signal("q", "m"), Signal("qv", "m")), params=params, true_params=params,
        dynamics=dynamics, measurement=lambda ops, x, u, p: [x[0], x[0] + 0.5 * x[1]],
        noise=NoiseModel(measurement_std=(0.05, 0.08), state_std=(0.01, 0.01),
                         process_std=(1e-2, 3e-2), initial_std=(0.5, 0.5)),
        dt=0.05, duration=10.0, x0=(1.0, 0.0),
        excitation=lambda t, rng: np.sin(t + rng.uniform())[:, None])


def linear_matrices(system: System):
    model = prior_model(system)
    x, u = cs.SX.sym("x", 2), cs.SX.sym("u", 1)
    A, B = (np.array(M) for M in cs.Function("AB", [x, u], [cs.jacobian(model.F(x, u), x),
                                                             cs.jacobian(model.F(x, u), u)])(0, 0))
    return model, A, B, np.array([[1.0, 0.0], [1.0, 0.5]])


def masked_data(system: System, A, B, C):
    """A run with noise matching the tuning, and a mask: output 0 every other sample, output 1
    every third, both missing for samples 20..29 (a dropout)."""
    rng = np.random.default_rng(4)
    noise = system.noise
    U = system.excitation(np.arange(T) * system.dt, rng)
    X = np.empty((T, 2))
    X[0] = np.array(system.x0) + rng.normal(size=2) * noise.initial_std
    for k in range(T - 1):
        X[k + 1] = A @ X[k] + B @ U[k] + rng.normal(size=2) * noise.process_std
    Y = X @ C.T + rng.normal(size=(T, 2)) * noise.measurement_std
    Y[1::2, 0] = np.nan
    Y[np.arange(T) % 3 != 0, 1] = np.nan
    Y[20:30] = np.nan
    return U, Y


def kalman(system, A, B, C, U, Y):
    """FilterPy's KF skipping missing updates: posterior means, covariances and the RTS smoother."""
    noise = system.noise
    kf = KalmanFilter(dim_x=2, dim_z=2, dim_u=1)
    kf.F, kf.B = A, B
    kf.Q, kf.R = np.diag(np.square(noise.process_std)), np.diag(np.square(noise.measurement_std))
    kf.x, kf.P = np.array(system.x0, dtype=float), np.diag(np.square(noise.initial_std))
    Xs, Ps, Xp, Pp = [], [], [], []
    for k in range(T):
        if k > 0:
            kf.predict(u=U[k - 1])
        Xp.append(kf.x.copy())
        Pp.append(kf.P.copy())
        seen = ~np.isnan(Y[k])
        if seen.any():
            kf.update(Y[k][seen], R=kf.R[np.ix_(seen, seen)], H=C[seen])
        Xs.append(kf.x.copy())
        Ps.append(kf.P.copy())
    return np.array(Xs), np.array(Ps), np.array(Xp), np.array(Pp)


def rts(A, Xs, Ps, Xp, Pp, first: int, last: int) -> np.ndarray:
    """The Rauch-Tung-Striebel smoother of samples ``first..last`` (given all up to ``last``)."""
    x = Xs[last].copy()
    out = [x]
    for k in range(last - 1, first - 1, -1):
        G = Ps[k] @ A.T @ np.linalg.inv(Pp[k + 1])
        x = Xs[k] + G @ (x - Xp[k + 1])
        out.append(x)
    return np.array(out[::-1])


@pytest.fixture(scope="module")
def linear():
    system = oscillator()
    model, A, B, C = linear_matrices(system)
    U, Y = masked_data(system, A, B, C)
    return system, model, A, C, U, Y, kalman(system, A, B, C, U, Y)


@pytest.mark.parametrize("kind", [UKF, EKF])
def test_kalman_filters_with_missing_outputs_are_the_kalman_filter_that_skips_them(linear, kind):
    """The UKF and the EKF on the linear model, outputs missing at two rates and a dropout:
    both are the Kalman filter that skips the missing outputs (x and P to 1e-10)."""
    system, model, _, _, U, Y, (Xs, Ps, _, _) = linear
    ukf = kind(model, kind.SETTINGS.from_system(system))
    ukf.reset(system.x0)
    for k in range(T):
        ukf.step(U[max(k - 1, 0)], Y[k])
        np.testing.assert_allclose(ukf.x, Xs[k], rtol=0, atol=1e-10 * np.abs(Xs[k]).max())
        np.testing.assert_allclose(ukf.P, Ps[k], rtol=0, atol=1e-10 * np.abs(Ps[k]).max())
        assert ukf.missing.tolist() == np.isnan(Y[k]).tolist() and ukf.last_status == 0


def test_mhe_with_missing_outputs_is_the_kalman_filter_and_its_smoother(linear):
    """Window of T samples (the whole run, full information) and prior (x0, P0): at every
    sample the estimate is the KF's, and the window is the RTS smoother of the samples so far
    (Ipopt's tolerance: 1e-9 measured ~1e-12)."""
    system, model, A, _, U, Y, (Xs, Ps, Xp, Pp) = linear
    settings = MHESettings.from_system(system, horizon=T - 1, arrival="arrival_std")
    mhe = MHE(model, settings)
    mhe.reset(system.x0, settings.initial_covariance())
    for k in range(T):
        x = mhe.step(U[k - 1] if k else np.zeros(1), Y[k])
        np.testing.assert_allclose(x, Xs[k], rtol=0, atol=1e-9)
        if k in (25, T - 1):  # inside the dropout and at the end
            window = mhe.window[T - 1 - k:]
            np.testing.assert_allclose(window, rts(A, Xs, Ps, Xp, Pp, 0, k), rtol=0, atol=1e-9)


def test_mhe_with_a_short_window_stays_near_the_filter_through_the_dropout(linear):
    """Once the window slides, the arrival prior (the previous window's smoothed estimate, its
    covariance carried by the filter's recursion from P0) stands in for the samples that left.
    In the filter's own standard deviations, after the window is full (measured 0.38 at
    N = 15, 0.059 at N = 30), the carried covariance beats a fixed arrival weight
    ``diag(1/arrival_std**2)`` (0.64, 0.13) and the error shrinks with N."""
    system, model, _, _, U, Y, (Xs, Ps, _, _) = linear
    std = np.sqrt(np.einsum("kii->ki", Ps))
    worst = {}
    for N in (15, 30):
        for arrival in ("steady_state", "arrival_std"):
            settings = MHESettings.from_system(system, horizon=N, arrival=arrival)
            X = MHE(model, settings).run(U, Y, system.x0, settings.initial_covariance())
            np.testing.assert_allclose(X[:N + 1], Xs[:N + 1], rtol=0, atol=1e-9)
            worst[N, arrival] = np.max(np.abs(X - Xs)[N + 1:] / std[N + 1:])
    assert worst[15, "steady_state"] < worst[15, "arrival_std"]
    assert worst[30, "steady_state"] < worst[30, "arrival_std"]
    assert worst[30, "steady_state"] < worst[15, "steady_state"] / 3 and worst[30, "steady_state"] < 0.1


def test_missing_everything_is_a_prediction(linear):
    """k samples without outputs: UKF = FilterPy's k predictions (x and P), MHE = the model's
    transition k times (the window has not slid: the new stages only add process terms whose
    minimum is the prediction)."""
    system, model, _, _, U, Y, (Xs, Ps, _, _) = linear
    ukf = UKF(model, UKFSettings.from_system(system))
    ukf.reset(system.x0)
    for k in range(12):
        ukf.step(U[max(k - 1, 0)], Y[k])
    kf = KalmanFilter(dim_x=2, dim_z=2)
    kf.x, kf.P, kf.Q = ukf.x, ukf.P, ukf.Q
    kf.F, kf.B = linear_matrices(system)[1:3]
    W = ukf._points.Wm, ukf._points.Wc
    for k in range(12, 17):
        ukf.predict(U[k - 1])
        kf.predict(u=U[k - 1])
        tol = unscented_rounding(*W, gain=k - 11)  # k - 11 transforms' rounding since the start
        np.testing.assert_allclose(ukf.x, kf.x, rtol=0, atol=tol * np.abs(kf.x).max())
        np.testing.assert_allclose(ukf.P, kf.P, rtol=0, atol=tol * np.abs(kf.P).max())
        assert ukf.last_status == 0 and ukf.rejections == 0

    cartpole = get_system("cartpole")
    run = simulation.simulate(cartpole, seed=2, duration=40 * cartpole.dt)
    cart = prior_model(cartpole)
    mhe = MHE(cart)
    mhe.reset(cartpole.x0)
    for k in range(10):
        mhe.step(run.u[k - 1] if k else np.zeros(1), run.y[k])
    x = mhe.x
    for k in range(10, 15):
        x = cart.step(x, run.u[k - 1])
        np.testing.assert_allclose(mhe.predict(run.u[k - 1]), x, rtol=0, atol=1e-8)


def test_gate_ignores_missing_outputs():
    """A missing output is no rejection; the streaks are per output, so a step without outputs
    changes nothing and a slow output's rejections add up while a fast one is accepted."""
    gate = GateState(GateSettings(recover_after=2, inflation=2.0), 2)
    d2 = np.array([1e6, np.nan])
    assert gate.test(d2, np.array([False, False])).tolist() == [False, False]
    assert gate.test(d2, np.array([True, False])).tolist() == [True, False]
    both, none = np.array([True, True]), np.array([False, False])
    gate.record(np.array([True, False]), both)
    assert gate.record(np.array([True, True]), both) == 2.0  # output 0's second rejection
    assert (gate.streaks.tolist(), gate.inflation) == ([2, 1], 2.0)
    assert gate.record(np.zeros(2, bool), none) == 1.0  # a pure prediction: nothing changes
    assert (gate.streaks.tolist(), gate.inflation, gate.status) == ([2, 1], 2.0, 0)
    assert not gate.ends_episode(np.zeros(2, bool), np.array([False, True]))  # 1 not in episode
    assert gate.ends_episode(np.zeros(2, bool), np.array([True, False]))
    gate.record(np.zeros(2, bool), np.array([True, False]))  # output 0 seen and accepted
    assert (gate.streaks.tolist(), gate.inflation) == ([0, 1], 1.0)
    slow = GateState(GateSettings(recover_after=3, inflation=2.0), 2)
    for k in range(9):  # output 1 every fourth step, always rejected; output 0 always fine
        seen = np.array([True, k % 4 == 0])
        slow.record(np.array([False, k % 4 == 0]), seen)
    assert slow.streaks.tolist() == [0, 3] and slow.inflation == 2.0  # its third: recovery


def test_set_noise_on_a_running_ukf_is_the_kalman_filter_retuned(linear):
    """Q and R changed after sample 30: the state and covariance are kept, and from then on
    the UKF is FilterPy's KF with the new Q and R (to 1e-10)."""
    system, model, A, C, U, Y, _ = linear
    Q, R = np.diag([2e-2, 5e-2]) ** 2, np.diag([0.1, 0.1]) ** 2
    ukf = UKF(model, UKFSettings.from_system(system))
    kf = KalmanFilter(dim_x=2, dim_z=2, dim_u=1)
    kf.F, kf.B = A, linear_matrices(system)[2]
    kf.Q, kf.R = ukf.settings.Q(), ukf.settings.R()
    kf.x, kf.P = np.array(system.x0, dtype=float), ukf.settings.P0()
    ukf.reset(system.x0)
    for k in range(T):
        if k == 30:
            before, P_before = ukf.x, ukf.P
            ukf.set_noise(Q=Q, R=R)
            kf.Q, kf.R = Q, R
            np.testing.assert_array_equal(ukf.x, before)
            np.testing.assert_array_equal(ukf.P, P_before)
        if k > 0:
            kf.predict(u=U[k - 1])
        seen = ~np.isnan(Y[k])
        if seen.any():
            kf.update(Y[k][seen], R=kf.R[np.ix_(seen, seen)], H=C[seen])
        ukf.step(U[max(k - 1, 0)], Y[k])
        np.testing.assert_allclose(ukf.x, kf.x, rtol=0, atol=1e-10 * np.abs(kf.x).max())
    with pytest.raises(TypeError, match="no arrival cost"):
        ukf.set_noise(P_arrival=np.eye(2))
    with pytest.raises(ValueError, match="positive"):
        ukf.set_noise(R=-np.eye(2))
    ukf.reset(system.x0)  # reset returns to the settings
    np.testing.assert_array_equal(ukf.R, ukf.settings.R())


def test_set_noise_on_a_running_mhe_reweighs_its_window(linear):
    """The MHE weighs every stage of its window with the weights in force: with the whole run
    in the window, retuning after sample 30 gives, from then on, the estimates of an MHE tuned
    that way from the start (same data, same cost; Ipopt's tolerance)."""
    system, model, _, _, U, Y, _ = linear
    Q, R = np.diag([2e-2, 5e-2]) ** 2, np.diag([0.1, 0.1]) ** 2
    noise = dataclasses.replace(system.noise, process_std=(2e-2, 5e-2), measurement_std=(0.1, 0.1))
    settings = MHESettings.from_system(system, horizon=T - 1, arrival="arrival_std")
    tuned = dataclasses.replace(settings, process_std=noise.process_std,
                                measurement_std=noise.measurement_std)
    est, ref = MHE(model, settings), MHE(model, tuned)
    for mhe in (est, ref):
        mhe.reset(system.x0, settings.initial_covariance())
    for k in range(T):
        if k == 30:
            window = est.window
            est.set_noise(Q=Q, R=R)
            np.testing.assert_array_equal(est.window, window)
        u = U[k - 1] if k else np.zeros(1)
        x, x_ref = est.step(u, Y[k]), ref.step(u, Y[k])
        if k >= 30:
            np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-8)
    est.set_noise(P_arrival=np.diag([0.3, 0.3]) ** 2)
    with pytest.raises(ValueError, match="positive definite"):
        est.set_noise(Q=np.zeros((2, 2)))


# -- the data path ----------------------------------------------------------------------------

def test_run_csv_with_missing_measurements_round_trips(tmp_path):
    """Missing outputs are written as empty cells and read back as NaN, bit for bit; NaN
    written by hand reads the same."""
    cartpole = get_system("cartpole")
    run = simulation.simulate(cartpole, 0, duration=0.1)
    y = run.y.copy()
    y[3, 1], y[10:20, 0] = np.nan, np.nan
    run = Run(run.t, run.u, y, run.x, run.system)
    path = write_run(run, cartpole, tmp_path / "r.csv")
    assert path.read_text().splitlines()[4].split(",")[3] == ""  # sample 3, y_alpha
    back = read_run(path, cartpole)
    for name in ("t", "u", "y", "x"):
        np.testing.assert_array_equal(getattr(back, name), getattr(run, name))
    assert back.missing.sum() == 11
    path.write_text(path.read_text().replace(",,", ",nan,"))
    np.testing.assert_array_equal(read_run(path, cartpole).y, y)


def test_resample_keeps_missing_outputs_missing():
    """A resampled output lies between two raw samples; if either is missing, so is it (a grid
    time on a raw sample takes that sample)."""
    t = np.arange(6) * 0.1
    y = np.c_[t, t]
    y[2, 0] = np.nan
    run = Run(t, np.zeros((6, 1)), y, None, "cartpole")
    out = resample(run, 0.05)
    between = (out.t > 0.1 + 1e-9) & (out.t < 0.3 - 1e-9)  # the grid around the missing 0.2 s
    np.testing.assert_array_equal(np.isnan(out.y[:, 0]), between)
    assert not np.isnan(out.y[:, 1]).any()


def set_cell(text: str, row: int, column: int, value: str) -> str:
    """``text`` (a CSV) with the cell at line ``row`` (0: the header), ``column`` replaced."""
    lines = text.splitlines()
    cells = lines[row].split(",")
    cells[column] = value
    lines[row] = ",".join(cells)
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("edit, message", [
    (lambda text: text.replace("y_alpha", "y_p", 1), r"column\(s\) \['y_p'\] appear more than once"),
    (lambda text: set_cell(text, 3, 2, "1+2j"),
     "non-numeric value '1\\+2j' in column 'y_p' at data row 3 \\(a complex number"),
    (lambda text: "\ufeff" + text, None),  # a byte-order mark: read as if absent
    (lambda text: set_cell(text, 3, 1, ""),
     "empty or NaN value in column 'u_F' at data row 3.*only measurement"),
    (lambda text: set_cell(text, 2, 0, "nan"), "empty or NaN value in column 't' at data row 2"),
    (lambda text: set_cell(text, 3, 5, ""), "empty or NaN value in column 'x_pdot'"),
    (lambda text: set_cell(text, 3, 3, "-inf"),
     "infinite value in column 'y_alpha'.*leave a measurement cell empty"),
    (lambda text: text + "1,2\n", "data row 6 has 2 values, the header 8"),
])
def test_hostile_run_csvs_are_one_clear_line_or_read_right(tmp_path, edit, message):
    cartpole = get_system("cartpole")
    run = simulation.simulate(cartpole, 0, duration=0.01)
    path = write_run(run, cartpole, tmp_path / "r.csv")
    path.write_text(edit(path.read_text()), encoding="utf-8")
    if message is None:
        np.testing.assert_array_equal(read_run(path, cartpole).y, run.y)
        return
    with pytest.raises(DataError, match=message) as info:
        read_run(path, cartpole)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_files_that_are_not_run_csvs(tmp_path):
    cartpole = get_system("cartpole")
    latin = tmp_path / "latin.csv"
    latin.write_bytes("t,u_F,y_p,y_\xe4lpha\n0,1,2,3\n".encode("latin-1"))
    with pytest.raises(DataError, match=r"latin.csv: not UTF-8 text \(byte 12, line 1"):
        read_run(latin, cartpole)
    with pytest.raises(DataError, match="/dev/zero: not a regular file"):
        read_run("/dev/zero", cartpole)
    with pytest.raises(DataError, match="not a regular file"):
        read_run(tmp_path, cartpole)
    nul = tmp_path / "nul.csv"
    nul.write_bytes(b"t,u_F\x00\n")
    with pytest.raises(DataError, match="NUL bytes"):
        read_run(nul, cartpole)


# -- the command line ---------------------------------------------------------------------------

def _cli(*args):
    from click.testing import CliRunner

    from learnest_codegen.cli import cli

    result = CliRunner().invoke(cli, [str(a) for a in args])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise AssertionError(f"uncaught {result.exception!r}") from result.exception
    return result.exit_code, " ".join(result.output.split())


@pytest.fixture(scope="module")
def gappy_csv(tmp_path_factory):
    """0.3 s of the cartpole with the pole angle at a quarter of the rate and a dropout of p."""
    cartpole = get_system("cartpole")
    run = simulation.simulate(cartpole, 1, duration=0.3)
    y = run.y.copy()
    y[np.arange(len(y)) % 4 != 0, 1] = np.nan
    y[60:90, 0] = np.nan
    path = tmp_path_factory.mktemp("gappy") / "gappy.csv"
    write_run(Run(run.t, run.u, y, run.x, run.system), cartpole, path)
    return path, run


def test_estimate_takes_missing_measurements_and_a_wrong_start(gappy_csv, tmp_path):
    """Both Python estimators run a gappy run from a start 3 sigma off (--x0, --P0 initial; the
    MHE with --horizon 10): the rates begin at the guess and end where the same estimator
    started at the true state ends."""
    path, run = gappy_csv
    missing = int(np.isnan(read_run(path, get_system("cartpole")).y).sum())
    for estimator in ("ukf", "mhe"):
        horizon = ["--horizon", "10"] if estimator == "mhe" else []
        X = {}
        for start, extra in (("wrong", ["--x0", "0.15,-0.3,0.45,-0.3", "--P0", "initial"]),
                             ("true", [])):
            out = tmp_path / f"{estimator}_{start}.csv"
            code, text = _cli("estimate", "--data", path, "--estimator", estimator, "--backend",
                              "python", *horizon, *extra, "--out", out)
            assert code == 0 and f"{missing} missing" in text, text
            X[start] = np.loadtxt(out, delimiter=",", skiprows=1)[:, 1:]
        np.testing.assert_allclose(X["wrong"][0, [1, 3]], [-0.3, -0.3], atol=0.01)  # the guess
        gap = np.abs(X["wrong"] - X["true"]).max(axis=1)
        assert gap[-20:].max() < 0.3 * gap[0], (estimator, gap[0], gap[-20:].max())  # 0.04, 0.2


def test_estimate_options_are_checked(gappy_csv, tmp_path):
    path, _ = gappy_csv
    out = tmp_path / "e.csv"
    code, text = _cli("estimate", "--data", path, "--estimator", "ukf", "--out", tmp_path / "c.csv")
    assert code == 0 and "missing" in text, text  # the compiled estimators take them too
    code, text = _cli("estimate", "--data", path, "--estimator", "ukf", "--backend", "python",
                      "--x0", "1,2", "--out", out)
    assert code == 2 and "--x0" in text and "expected 4 finite comma-separated numbers" in text, text
    code, text = _cli("estimate", "--data", path, "--estimator", "ukf", "--backend", "python",
                      "--P0", "1,2,3", "--out", out)
    assert code == 2 and "expected 'initial', 4 variances or 16 entries" in text, text
    code, text = _cli("estimate", "--data", path, "--estimator", "ukf", "--backend", "python",
                      "--horizon", "5", "--out", out)
    assert code == 2 and "a horizon applies to the MHEs" in text, text
    code, text = _cli("estimate", "--data", path, "--estimator", "ukf", "--backend", "python",
                      "--P0", "1,0,0,0,0,1,0,0,0,0,-1,0,0,0,0,1", "--out", out)
    assert code == 2 and "--P0" in text and "positive semidefinite" in text, text
    code, text = _cli("estimate", "--data", "/dev/zero", "--estimator", "ukf", "--out", out)
    assert code == 1 and "/dev/zero: not a regular file" in text, text
