"""The quadrotor study's noise chosen on the training flights (``--tune-noise``): by predicting
raw measurements, never by matching a smoothed copy of them."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from learnest_codegen.experiments import quadrotor as fs
from learnest_codegen.experiments import quadrotor_tuning
from learnest_codegen.experiments.quadrotor_cases import initial_state
from learnest_codegen.experiments.quadrotor_tuning import Tuning, prediction_errors, tune
from learnest_codegen.systems.quadrotor import QUADROTOR

#: a small grid keeps the tests quick: measurement scales 1/4 and 1 per output group, widened
#: by one step past an edge
SMALL_GRID = {"COARSE_EXPONENTS": (-2, 0), "EXPONENT_LIMIT": 4}
POSITION = ["px", "py", "pz"]


@pytest.fixture
def small_grid(monkeypatch):
    for name, value in SMALL_GRID.items():
        monkeypatch.setattr(quadrotor_tuning, name, value)


def _transition() -> tuple[np.ndarray, np.ndarray]:
    """RK4 of the nominal quadrotor's triple integrator (on a linear model the fourth-order
    Taylor series of exp(A dt)) and its measurement matrix."""
    A = np.zeros((9, 9))
    A[0:3, 3:6] = A[3:6, 6:9] = np.eye(3)
    h = QUADROTOR.dt * A
    F = np.eye(9) + h + h @ h / 2 + h @ h @ h / 6 + h @ h @ h @ h / 24
    H = np.zeros((6, 9))
    H[0:3, 0:3] = H[3:6, 6:9] = np.eye(3)
    return F, H


def _kalman(case, process_std, measurement_std) -> np.ndarray:
    """A hand-written Kalman filter of the nominal quadrotor."""
    F, H = _transition()
    Q, R = np.diag(np.square(process_std)), np.diag(np.square(measurement_std))
    x, P = initial_state(case.run), np.diag(np.square(QUADROTOR.noise.initial_std))
    out = np.empty((len(case.run), 9))
    for k, y in enumerate(case.run.y):
        if k:
            x, P = F @ x, F @ P @ F.T + Q
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        x, P = x + K @ (y - H @ x), P - K @ S @ K.T
        out[k] = x
    return out


def _predicted(x_hat, run, horizons, stride, outputs=(0, 1, 2)) -> dict[int, float]:
    """The criterion's prediction errors by matrix powers of the linear model."""
    F, H = _transition()
    starts = np.arange(0, len(x_hat) - 1, stride)
    out = {}
    for h in horizons:
        k = starts[starts + h < len(x_hat)]
        pred = x_hat[k] @ np.linalg.matrix_power(F, h).T @ H.T
        out[h] = float(np.mean((pred[:, outputs] - run.y[k + h][:, outputs]) ** 2))
    return out


@pytest.mark.parametrize("stride", [1, 5])
def test_the_predictions_are_the_matrix_powers_of_a_linear_model(stride):
    """Open-loop predictions through the CasADi model, h steps from every stride-th estimate,
    against F^h of the same linear model (to 1e-9)."""
    from learnest_codegen.export import prior_model

    run = fs.simulated_cases([2], duration=3.0)[0].run
    x_hat = run.x + 0.01 * np.random.default_rng(0).normal(size=run.x.shape)
    got = prediction_errors(prior_model(QUADROTOR), x_hat, run, [0, 1, 2], (1, 10, 50), stride)
    want = _predicted(x_hat, run, (1, 10, 50), stride)
    assert set(got) == {1, 10, 50}
    for h in want:
        assert got[h] == pytest.approx(want[h], rel=1e-9), h


def test_each_grid_point_scores_as_a_kalman_filter_and_the_best_is_kept(tmp_path, small_grid):
    """On the nominal (linear) quadrotor the compiled UKF is the Kalman filter: every grid
    point's criterion (mean log prediction error of the position) equals a hand-written
    filter's with those measurement scales per output group, where the innovation gate
    rejected nothing (the same build at that point rejects samples otherwise); the search
    keeps the lowest and records the chosen point's own figures."""
    from learnest_codegen.compilation import estimator_kind
    from learnest_codegen.evaluation import run_estimator
    from learnest_codegen.export import prior_model

    case = fs.simulated_cases([0], duration=4.0)[0]
    tuning, estimator, record = tune("nominal", "ukf", [case], tmp_path, system=QUADROTOR, outputs=POSITION)
    groups = quadrotor_tuning.output_groups(QUADROTOR)
    assert groups == (("px", "py", "pz"), ("ax", "ay", "az"))
    horizons = (1, 10, 50)
    stride = int(round(quadrotor_tuning.STRIDE_S / QUADROTOR.dt))
    noise = QUADROTOR.noise
    matched = 0
    for label, value in record["grid"].items():
        exponents = [int(e) for e in label.split("_")]
        scales = np.repeat([2.0 ** e for e in exponents], 3)
        x_hat = _kalman(case, noise.process_std, scales * np.asarray(noise.measurement_std))
        expected = float(np.mean(np.log(list(_predicted(x_hat, case.run, horizons, stride).values()))))
        if value == pytest.approx(expected, rel=1e-6):
            matched += 1
        else:
            point = Tuning(1.0, 1.0, tuple(2.0 ** e for e in exponents), groups)
            again = estimator_kind("ukf").compiled(estimator.directory,
                                                   settings=point.settings("ukf", prior_model(QUADROTOR)))
            assert run_estimator(again, case.run, initial_state(case.run), "ukf").rejections > 0, label
    assert matched >= len(record["grid"]) // 2
    best = min(record["grid"], key=record["grid"].get)
    assert tuning.measurement_scales == tuple(2.0 ** int(e) for e in best.split("_"))
    assert record["criterion"] == pytest.approx(record["grid"][best], rel=1e-12)
    assert record["predicted_outputs"] == POSITION and record["edge"] == []


def test_the_search_widens_past_the_edge_and_refines(monkeypatch):
    """On a bowl whose minimum lies outside the coarse grid the search widens the grid towards
    it and refines by factors of 2 to the exact point; past the widest grid it stops at the
    limit (which ``tune`` reports as on the edge)."""
    calls = []

    def bowl(target):
        def f(point):
            calls.append(point)
            return float(sum((p - t) ** 2 for p, t in zip(point, target)))
        return f

    assert quadrotor_tuning._search(bowl((-11, 5)), 2) == (-11, 5)
    assert len(set(calls)) < 150  # far fewer than the full grid of 33 x 33
    monkeypatch.setattr(quadrotor_tuning, "EXPONENT_LIMIT", 6)
    assert quadrotor_tuning._search(bowl((-11, 1)), 2) == (-6, 1)


def test_measurement_scales_apply_per_output_group():
    """Tuning.settings scales each group's measurement stds by its factor (times the common
    scale) and every process std by the process scale."""
    from learnest_codegen.export import prior_model

    groups = quadrotor_tuning.output_groups(QUADROTOR)
    tuning = Tuning(2.0, 2.0, (1 / 16, 4.0), groups)
    settings = tuning.settings("ukf", prior_model(QUADROTOR))
    noise = QUADROTOR.noise
    np.testing.assert_allclose(np.sqrt(np.diag(settings.R())),
                               2.0 * np.array([1 / 16] * 3 + [4.0] * 3) * noise.measurement_std, rtol=1e-12)
    np.testing.assert_allclose(np.sqrt(np.diag(settings.Q())), 2.0 * np.asarray(noise.process_std),
                               rtol=1e-12)
    assert tuning.label == "q2_r0.0625_4"


def test_a_tuned_mhe_is_the_mhe_of_the_system_with_the_scaled_noise():
    """One door: the tuned settings are the MHE settings of a system whose process noise is
    scaled, the arrival cost recomputed for it (not the untuned one's)."""
    from learnest_codegen.estimators.mhe_problem import mhe_settings
    from learnest_codegen.export import prior_model

    model = prior_model(QUADROTOR)
    tuned = Tuning(0.25).settings("mhe_rti", model)
    noise = replace(QUADROTOR.noise, process_std=tuple(0.25 * s for s in QUADROTOR.noise.process_std))
    scaled = mhe_settings(prior_model(replace(QUADROTOR, noise=noise)))
    assert tuned.process_std == scaled.process_std
    np.testing.assert_allclose(tuned.arrival_covariance, scaled.arrival_covariance, rtol=1e-12)
    untuned = mhe_settings(model)
    assert not np.allclose(tuned.arrival_covariance, untuned.arrival_covariance, rtol=1e-3)
    doubled = tuple(2.0 * s for s in QUADROTOR.noise.process_std)
    assert Tuning(2.0).settings("ukf", model).process_std == doubled


def test_a_tuned_study_pairs_knode_with_both_nominal_estimators(tmp_path, small_grid):
    """``tune_noise``: the KNODE estimator runs with the noise chosen on its training run, each
    flight is paired with the nominal estimator as built and, as a control, with the nominal
    estimator tuned the same way; the report shows the tunings, and a second study reuses the
    stored ones."""
    cases = fs.simulated_cases(range(2), duration=6.0)
    settings = fs.StudySettings(estimators=("ukf",), tune_noise=True)
    (summary,) = fs.run_study(cases, tmp_path, train=["sim_seed0"], features=["linear_prior"],
                              settings=settings, progress=False)
    assert set(summary.paired) == {"KNODE-UKF", "KNODE-UKF vs UKF (tuned)"}
    flight = summary.per_case["sim_seed1"]
    for key, nominal in (("KNODE-UKF", "UKF"), ("KNODE-UKF vs UKF (tuned)", "UKF (tuned)")):
        change = 100 * (flight[nominal]["mse"] - flight["KNODE-UKF"]["mse"]) / flight[nominal]["mse"]
        assert summary.paired[key]["all"].mean == pytest.approx(change)
        velocity = summary.by_reference[key]["truth"]["v"]
        v_nom, v_knode = (flight[m]["by_reference"]["truth"]["v"] for m in (nominal, "KNODE-UKF"))
        assert velocity.mean == pytest.approx(100 * (v_nom - v_knode) / v_nom)
    record = summary.tunings["sim_seed0"]
    for chosen in (record["ukf"], record["nominal"]["ukf"]):
        best = min(chosen["grid"], key=chosen["grid"].get)
        assert chosen["label"] == Tuning(1.0, 1.0, tuple(2.0 ** int(e) for e in best.split("_"))).label \
            or chosen["gate_widened"] > 0
    report = (tmp_path / "quadrotor.md").read_text()
    assert "KNODE-UKF vs UKF (tuned)" in report and "Noise tuned on the training flights" in report
    assert (tmp_path / "quadrotor.png").is_file()
    stored = tmp_path / "nominal" / "tuning" / "sim_seed0" / "ukf" / "tuning.json"
    assert stored.is_file()
    again = fs.train_and_test(cases[0], cases[1:], "linear_prior", tmp_path, settings, force=True,
                              progress=False)["tuning"]
    assert again["nominal"]["ukf"] == record["nominal"]["ukf"]


def _flights():
    from learnest_codegen.recordings import crazyflie as nb
    from learnest_codegen.recordings import data_root

    root = data_root()
    if root is None or not (root / "nanobench").is_dir() or not nb.list_flights(root):
        pytest.skip("NanoBench flights not found (../shared/data/nanobench or $LEARNEST_DATA)")
    return fs.flight_cases(root, echo=False)


@pytest.mark.slow
def test_real_flights_per_state_with_the_sensor_model_as_built(tmp_path):
    """Leave one trajectory type out, the recommended model (accelerometer offset and lag
    states, fitted prior) with the system's hand tuning against the nominal estimators as
    built, KNODE-UKF and KNODE-MHE-RTI: velocity better on every flight at every reference and
    by at least +10 % on average from the central differences to the 1.5 s fit, position and
    acceleration never more than 5 % worse on any flight, the normalised overall at least
    +10 % at every window, and the velocity better than the onboard EKF's on at least 90 % of
    the flights against the central differences (docs/reports/flights_study.md)."""
    cases = _flights()
    settings = fs.StudySettings(estimators=("ukf", "mhe_rti"))
    (summary,) = fs.run_study(cases, tmp_path, features=[fs.RECOMMENDED_FEATURES], settings=settings,
                              protocol="leave-type-out", progress=False)
    for key in ("KNODE-UKF", "KNODE-MHE-RTI"):
        refs = summary.by_reference[key]
        for ref, row in refs.items():
            v = row["v"]
            assert v.n == len(cases) and v.improved == v.n, (key, ref)
            if ref in ("cd_0.1s", "sg_0.5s", "sg_1s", "sg_1.5s"):
                assert v.mean >= 10.0, (key, ref, v.mean)
            assert row["p"].worst > -5.0 and row["overall"].mean >= 10.0, (key, ref)
            if "a" in row:
                assert row["a"].worst > -5.0, (key, ref, row["a"].worst)
        onboard = summary.onboard[key]["cd_0.1s"]
        assert onboard.improved >= 0.9 * onboard.n, key
