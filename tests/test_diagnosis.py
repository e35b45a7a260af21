"""`learnest diagnose`: where the gap lies, which effect, how far it shrinks; self-test; real data."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from click.testing import CliRunner

from learnest_codegen import get_system
from learnest_codegen.cli import cli
from learnest_codegen.data import write_run
from learnest_codegen.diagnosis import DiagnosisSettings, diagnose, load
from learnest_codegen.diagnosis.fit import Pairs
from learnest_codegen.diagnosis.floor import white_floor
from learnest_codegen.diagnosis.selftest import case_key, run_case, select_cases, table
from learnest_codegen.diagnosis.selftest_cases import CASES, QUICK
from learnest_codegen.diagnosis.where import regimes
from learnest_codegen.errors import DataError, UnknownNameError
from learnest_codegen.recordings import data_root
from learnest_codegen.simulation import simulate

QUICK_SETTINGS = DiagnosisSettings(estimators=())


@pytest.mark.parametrize("key", QUICK)
def test_selftest_quick_cases(key):
    """The pendulum with two wrong parameters and friction, through the observer: both parameters
    and the friction are named, each within a few percent (the truth's friction is
    tanh(qdot / 0.01 rad/s), the library's smoother), and the gap is closed to the floor."""
    (case,) = select_cases([key])
    row = run_case(case, QUICK_SETTINGS)
    assert row["pass"], row
    assert row["match"] == "exact" and row["param_error"] < 0.05
    assert row["verdict"] == "explained" and row["gap_closed"] > 0.98


def test_pendulum_rig_with_its_torque_late():
    """The twin of a torque-limited lab pendulum, its torque 3 ms (half a sample) late, two
    swing-ups through the observer: J and mgl (3.7x and 3.6x off, an actuator gain aliases both)
    and the Coulomb friction within 20 %, the delay within 1 ms, nothing else."""
    (case,) = [c for c in CASES if c.system == "pendulum_rig" and "3 ms late, 2 swing-ups" in c.label]
    row = run_case(case, QUICK_SETTINGS)
    assert row["pass"], row
    got = {e["name"]: {**e["params"], **e["equivalent"]} for e in row["found_params"]}
    assert set(got) == {"mass(qdot via J)", "parameter(qdot via mgl)", "coulomb_friction(qdot)",
                        "input_delay(qdot via tau)"}
    assert got["mass(qdot via J)"]["J"] == pytest.approx(0.187, rel=0.2)
    assert got["parameter(qdot via mgl)"]["mgl"] == pytest.approx(3.60, rel=0.2)
    assert got["coulomb_friction(qdot)"]["coulomb_friction(qdot via tau)"] == pytest.approx(0.195, rel=0.2)
    assert got["input_delay(qdot via tau)"]["delay"] == pytest.approx(0.003, abs=0.001)


@pytest.mark.parametrize("late_ms", [0.0, 2.0])
def test_pendulum_rig_on_one_run(late_ms):
    """The rig's twin on a single swing-up (the default with one recording: its last 30 % held
    out), its torque on time or 2 ms (a third of a sample) late: J, mgl and the Coulomb friction
    within 20 %, the delay within 1 ms when there is one, none when there is none, nothing else.
    The delay's held-out gain is uneven over the folds (it is seen where the torque switches) and
    below a pure-noise sum of squares' spread, so it enters on its whole-run Wald statistic by
    generalised least squares."""
    (case,) = [c for c in CASES if c.system == "pendulum_rig" and f"{late_ms:g} ms late, 1 swing-up "
               in c.label]
    row = run_case(case, QUICK_SETTINGS)
    assert row["pass"], row
    got = {e["name"]: {**e["params"], **e["equivalent"]} for e in row["found_params"]}
    names = {"mass(qdot via J)", "parameter(qdot via mgl)", "coulomb_friction(qdot)"}
    assert set(got) == (names | {"input_delay(qdot via tau)"} if late_ms else names)
    assert got["mass(qdot via J)"]["J"] == pytest.approx(0.187, rel=0.2)
    assert got["parameter(qdot via mgl)"]["mgl"] == pytest.approx(3.60, rel=0.2)
    assert got["coulomb_friction(qdot)"]["coulomb_friction(qdot via tau)"] == pytest.approx(0.195, rel=0.2)
    if late_ms:
        assert got["input_delay(qdot via tau)"]["delay"] == pytest.approx(late_ms * 1e-3, abs=0.001)


def test_exact_prior_through_the_observer_is_no_gap():
    """Pure observer noise must not be called a gap, nor explained by an effect."""
    cartpole = get_system("cartpole")
    exact = dataclasses.replace(cartpole, true_dynamics=cartpole.dynamics, true_params=cartpole.params)
    run = simulate(exact, seed=5, duration=6.0)
    d = diagnose(exact, [run], settings=dataclasses.replace(QUICK_SETTINGS, source="observer"))
    assert d.report["source"] == "observer" and d.report["verdict"] == "no gap"
    assert d.report["effects"] == []
    assert all(s["snr"] < 1.5 for s in d.report["where"] if s["residual_state"])
    assert d.report["noise_floor"]["method"].startswith("calibration")


def test_cart_mass_through_the_observer():
    """The built-in cartpole (cart 1.5 kg, prior 1.0 kg) from [p, alpha] measurements only."""
    cartpole = get_system("cartpole")
    d = diagnose(cartpole, [simulate(cartpole, seed=1, duration=6.0)],
                 settings=dataclasses.replace(QUICK_SETTINGS, source="observer"))
    (effect,) = d.report["effects"]
    assert effect["name"] == "mass(pdot via m_c)"
    dm, std = effect["params"]["dm_c"], effect["uncertainty"]["dm_c"]
    assert abs(dm - 0.5) < max(4 * std, 0.05)
    assert 0 < std < 0.1
    pdot = next(s for s in d.report["where"] if s["state"] == "pdot")
    assert pdot["share"] > 0.5 and pdot["snr"] > 1.5
    assert d.report["shrink"]["one_step"]["closed"] > 0.8


def test_where_regimes_find_the_driver():
    """A residual that is a sign step in an input is driven by that input. With 5 quantile bins of
    a symmetric input the middle bin straddles the step (mean 0) and the other four have means
    +-1, so the correlation ratio is exactly 4/5."""
    system = get_system("ground_robot")
    rng = np.random.default_rng(0)
    n = 2000
    z = np.column_stack([rng.normal(size=n), rng.normal(size=n), rng.uniform(1, 3, n), rng.normal(size=n)])
    u = np.column_stack([rng.normal(size=n), rng.uniform(-0.3, 0.3, n)])
    pairs = Pairs.from_states([(np.arange(n) * 0.01, z, u)])
    r = np.zeros((n - 1, 4))
    r[:, 2] = np.where(pairs.u[:, 0] > 0, 1.0, -1.0)
    out = regimes(system, r, pairs, QUICK_SETTINGS)
    assert out["drivers"]["v"][0]["variable"] == "a"
    assert out["drivers"]["v"][0]["eta2"] == pytest.approx(0.8, abs=0.03)
    assert out["variables"]["t"]["eta2"]["v"] < 0.05


def test_white_floor_of_white_noise():
    rng = np.random.default_rng(1)
    r = rng.normal(0, 0.3, size=(20000, 2)) + np.linspace(0, 5, 20000)[:, None]  # plus a slow drift
    np.testing.assert_allclose(white_floor(r), 0.3, rtol=0.05)


def _smoothed_noise(rng, n: int) -> np.ndarray:
    """AR(2) noise correlated over tens of samples, like the one-step residual of smoothed states."""
    w, x = rng.normal(size=n + 200), np.zeros(n + 200)
    for k in range(2, n + 200):
        x[k] = 1.6 * x[k - 1] - 0.65 * x[k - 2] + w[k]
    return x[200:] / x[200:].std()


def test_ar_fit_recovers_the_coefficients():
    """Akaike's order and least-squares coefficients of an AR(2): within 4 standard errors
    (``sqrt((1 - a2^2) / n)``, 0.006 at n = 20000), and nothing of weight on white noise."""
    from learnest_codegen.diagnosis.search import _ar_fit

    rng = np.random.default_rng(3)
    n, w = 20000, rng.normal(size=20200)
    x = np.zeros_like(w)
    for k in range(2, len(w)):
        x[k] = 1.2 * x[k - 1] - 0.5 * x[k - 2] + w[k]
    a = _ar_fit(x[200:], 12)
    se = np.sqrt((1 - 0.5 ** 2) / n)
    assert len(a) >= 2 and np.abs(a[:2] - [1.2, -0.5]).max() < 4 * se
    assert np.abs(a[2:]).max(initial=0) < 4 * se
    assert np.abs(_ar_fit(rng.normal(size=n), 12)).max(initial=0) < 4 / np.sqrt(n)


def test_whitened_wald_is_calibrated_and_sharper():
    """The Wald statistic of an effect seen only at a few sharp events (a late input step), on a
    residual correlated over tens of samples: without the effect, over 300 draws, it is a
    standard normal (mean within 4 of the draws' own scatter, 0.06; standard deviation within
    4 x 0.04 of 1) and never reaches the entry's ``z_min``; with it, whitening raises the
    statistic several fold over plain least squares."""
    from learnest_codegen.diagnosis.cv import FitData
    from learnest_codegen.diagnosis.fit import FitSettings
    from learnest_codegen.diagnosis.search import wald

    rng = np.random.default_rng(0)
    n, s = 1500, FitSettings()
    t = np.arange(n) * 0.006
    smooth = np.sin(2 * np.pi * 0.5 * t)
    events = np.zeros(n)
    events[rng.choice(n, 40, replace=False)] = rng.choice([-1.0, 1.0], 40)
    Phi = np.stack([smooth, events], axis=1)[:, None, :]

    def z(coef: float, order: int) -> float:
        R = (coef * events + _smoothed_noise(rng, n))[:, None]
        data = FitData(R, Phi, np.ones(1), np.zeros(2))
        return wald(data, [0, 1], np.zeros(2), np.array([0.0, 1.0]), s.blocks, order)

    null = np.array([z(0.0, s.whiten_order) for _ in range(300)])
    assert abs(null.mean()) < 4 * 0.06 and 1 - 4 * 0.04 < null.std() < 1 + 4 * 0.04
    assert null.max() < s.z_min
    plain = np.mean([z(0.3, 0) for _ in range(50)])
    whitened = np.mean([z(0.3, s.whiten_order) for _ in range(50)])
    assert plain < s.z_min < whitened and whitened > 3 * plain


def test_cli_diagnose_end_to_end(tmp_path):
    """A short ground-robot run with the built-in drag: files, JSON contract, compiled UKF."""
    system = get_system("ground_robot")
    csv = write_run(simulate(system, seed=2, duration=12.0), system, tmp_path / "run.csv")
    out = tmp_path / "diag"
    result = CliRunner().invoke(cli, ["diagnose", "--system", "ground_robot", "--data", str(csv),
                                      "--out", str(out), "--estimators", "ukf", "--no-progress"],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.output
    report = json.loads((out / "diagnosis.json").read_text())
    for key in ("where", "effects", "explained_in_sample", "heldout_gap_closed", "verdict_reason", "shrink",
                "regimes", "verdict", "basis"):
        assert key in report
    assert "findings rest on this one run" in report["basis"]
    assert {"state", "share", "snr"} <= set(report["where"][0])
    top = report["effects"][0]
    assert {"kind", "state", "params", "in_sample_share", "score", "physical"} <= set(top) and top["physical"]
    assert top["kind"] == "quadratic_drag" and top["state"] == "v"
    k = 0.5 * 1.225 * 0.06 * 1.05 / 1.5
    assert abs(top["params"]["k"] - k) / k < 0.01
    ukf = report["shrink"]["ukf"]
    assert {"before", "after", "closed"} <= set(ukf) and ukf["after"] < ukf["before"]
    assert ukf["closed"] > 0.5
    for name in ("report.md", "residual.png", "regimes.png", "effects.png", "shrink.png"):
        assert (out / name).stat().st_size > 1000
    assert "quadratic_drag(v)" in (out / "report.md").read_text()


def test_cli_list_effects_and_errors(tmp_path):
    runner = CliRunner()
    result = runner.invoke(cli, ["diagnose", "--list-effects", "--system", "cartpole"])
    assert result.exit_code == 0 and "coulomb_friction(pdot via F)" in result.output
    result = runner.invoke(cli, ["diagnose", "--system", "cartpole", "--data", str(tmp_path), "--out",
                                 str(tmp_path / "o")])
    assert result.exit_code == 1 and "no *.csv runs" in result.output
    bad = tmp_path / "bad.csv"
    bad.write_text("t,u_F,y_p,y_alpha\n0,1,0,0\n0.002,one,0,0\n")
    result = runner.invoke(cli, ["diagnose", "--system", "cartpole", "--data", str(bad), "--out",
                                 str(tmp_path / "o")])
    assert result.exit_code == 1 and "non-numeric" in result.output
    with pytest.raises(UnknownNameError, match="unknown data format"):
        load("cartpole", bad, "rosbag")
    with pytest.raises(UnknownNameError, match="unknown source"):
        DiagnosisSettings(source="oracle")
    short = simulate(get_system("cartpole"), seed=0, duration=0.05)
    with pytest.raises(DataError, match="too short"):
        diagnose(get_system("cartpole"), [short], settings=QUICK_SETTINGS)


def test_selftest_table_lists_every_case():
    assert len({case_key(c) for c in CASES}) == len(CASES)
    assert {c.expect for c in CASES} == {"effects", "no gap", "unexplained"}
    assert any(len(c.inject) == 2 for c in CASES)
    rows = [{"case": "x", "found": "-", "verdict": "no gap", "expect": "no gap", "match": "-",
             "param_error": None,
             "gap_closed": None, "pass": True, "seconds": 1.0}]
    assert "param err %" in table(rows) and "UKF" not in table(rows)
    rows += [{**rows[0], "case": "y", "estimator_verdicts": {"mhe": "improved", "ukf": "rejected"}}]
    lines = table(rows).splitlines()
    spans, at = [], 0  # column spans from the dashes line
    for dashes in lines[1].split("  "):
        spans.append((at, at + len(dashes)))
        at += len(dashes) + 2
    cells = [[line[a:b].strip() for a, b in spans] for line in lines]
    k = cells[0].index("MHE")
    assert cells[0][k + 1] == "UKF" and cells[0][k - 1] == "verdict"
    assert cells[2][k:k + 2] == ["-", "-"] and cells[3][k:k + 2] == ["improved", "rejected"]


@pytest.mark.slow
def test_full_selftest_passes():
    from learnest_codegen.diagnosis.selftest import run_selftest

    rows = run_selftest(progress=False)
    assert all(r["pass"] for r in rows), table(rows)


@pytest.mark.slow
@pytest.mark.parametrize("key", [case_key(c) for c in CASES if c.system == "pendulum_rig"])
def test_pendulum_rig_every_delay(key):
    """The rig's torque 0, 2, 3 and 5 ms late, one swing-up, and two and three pooled, by default
    through the observer: J, mgl and Coulomb within 20 %, the delay within 1 ms from 2 ms on, nothing else."""
    (case,) = select_cases([key])
    assert run_case(case, QUICK_SETTINGS)["pass"]


@pytest.mark.slow
@pytest.mark.parametrize("late_ms", [0.0, 2.0])
@pytest.mark.parametrize("seed", range(2, 17))
def test_pendulum_rig_on_other_swingups(late_ms, seed):
    """The rig's twin on one swing-up, on time or 2 ms late, on the swing-ups of seeds 2-16 (the
    self-test's is seed 1): right on each, the delay named within 1 ms when there is one and none
    when there is none."""
    (case,) = [c for c in CASES if c.system == "pendulum_rig" and f"{late_ms:g} ms late, 1 swing-up "
               in c.label]
    row = run_case(case, QUICK_SETTINGS, seed=seed)
    assert row["pass"], row


@pytest.mark.slow
def test_swingup_pendulum_names_parameters_and_coulomb_by_default():
    """The real pendulum's situation (prior J and mgl about 3x too small, no friction; Coulomb
    0.2 N m; swing-ups whose torque correlates with sign(qdot); three runs, the angle alone): the
    default diagnosis names both parameters and the Coulomb friction within 20 %, and no viscous
    term and no actuator gain stand in for them."""
    from learnest_codegen.diagnosis.selftest_systems import SWINGUP_TRUE, swingup_pendulum

    case = next(c for c in CASES if c.system == "pendulum_swingup")
    system = swingup_pendulum()
    runs = [simulate(system, seed) for seed in (1, 2, 3)]
    corr = [np.corrcoef(r.u[:, 0], np.sign(r.x[:, 1]))[0, 1] for r in runs]
    assert all(0.4 < c < 0.75 for c in corr), corr
    row = run_case(case, QUICK_SETTINGS)
    assert row["pass"] and row["match"] == "exact" and row["param_error"] < 0.2, row
    assert "viscous" not in row["found"] and "actuator_gain" not in row["found"], row["found"]
    assert row["verdict"] in ("explained", "partly explained") and row["gap_closed"] > 0.9
    assert SWINGUP_TRUE["J"] > 2.5 * system.params["J"] and SWINGUP_TRUE["mgl"] > 2.5 * system.params["mgl"]


@pytest.mark.slow
def test_cart_coulomb_on_true_states_alone():
    """A cart with sharp Coulomb friction (1 N), three runs, true states: the friction within 10 %
    and nothing else selected, every parameter in its physical range."""
    case = next(c for c in CASES if c.system == "cart")
    row = run_case(case, QUICK_SETTINGS)
    assert row["pass"] and row["param_error"] < 0.1 and row["physical"], row
    assert len(row["found"].split(", ")) == 1, row["found"]  # one effect (its equivalents in brackets)


@pytest.mark.slow
@pytest.mark.parametrize("key", ["pendulum_small_friction: J x2, mgl x1.6, Coulomb 0.05 N m (observer)",
                                 "cartpole: cart mass +0.5 kg (built-in), 4 runs of 4 s pooled (observer)"])
def test_selftest_with_estimators(key):
    """A small friction under two large parameter errors, and short runs pooled, with the MHE and
    the UKF: right, and each estimator improved by the correction on its own held-out runs."""
    (case,) = select_cases([key])
    row = run_case(case, DiagnosisSettings(estimators=("mhe", "ukf")))
    assert row["pass"], row
    assert row["estimator_verdicts"] == {"mhe": "improved", "ukf": "improved"}
    assert row["param_error"] < 0.1


def _real(name: str):
    root = data_root()
    if root is None or not (root / name).is_dir():
        pytest.skip(f"real recordings {name!r} not found (../shared/data/{name})")
    return root / name


def _honest(report: dict) -> None:
    """What the verdicts of a diagnosis on real data must be backed by (see diagnosis/shrink.py):
    each estimator's verdict follows from its own held-out MSE before and after the correction,
    no effect is a finding for an estimator it made worse, and the overall verdict follows from
    the held-out one-step residual and the estimators' verdicts."""
    from learnest_codegen.diagnosis.shrink import estimator_verdict

    s = DiagnosisSettings()
    one = report["shrink"]["one_step"]
    per = report["by_estimator"]
    assert set(per) == set(report["estimator_verdicts"]) and per
    names = [e["name"] for e in report["effects"] + report["rejected_effects"]]
    for name, entry in per.items():
        numbers = report["shrink"][name]
        assert np.isfinite(numbers["before"]), (name, numbers)
        # the verdict is the one its own numbers give, and the numbers are the held-out runs' means
        assert entry["verdict"] == estimator_verdict(numbers["before"], numbers["after"], s.worse_tolerance)
        assert numbers["before"] == pytest.approx(np.mean(numbers["per_segment"]["prior"]))
        assert numbers["after"] == pytest.approx(np.mean(numbers["per_segment"]["corrected"]))
        if entry["found"]:  # a finding for this estimator only if it lowered its held-out MSE
            assert numbers["after"] < numbers["before"] and entry["verdict"] == "improved"
        if numbers["after"] > numbers["before"] * (1 + s.worse_tolerance):
            assert entry["found"] == [] and entry["rejected"] == names
            assert report["verdict"] != "explained"
        for e in report["effects"]:
            assert e["estimators"][name] == entry["verdict"]
    if report["verdict"] == "explained":
        assert one["after"] <= s.explained_gap and "rejected" not in report["estimator_verdicts"].values()
    if report["verdict"] == "partly explained":
        assert one["closed"] >= 0.25 and one["after"] <= one["before"]
    if report["verdict"] == "rejected":
        assert report["effects"] == [] and report["rejected_effects"]
        assert one["after"] > one["before"] or all(v["verdict"] == "rejected" for v in per.values())
    else:
        assert one["after"] <= one["before"]
        assert not all(v["verdict"] == "rejected" for v in per.values()) or not report["effects"]
    assert len(report["consistency"]) == sum(len(e["params"]) - (e["channel"].startswith("param:"))
                                            for e in report["effects"] + report["rejected_effects"])


REAL_SETTINGS = DiagnosisSettings(source="observer", estimators=("mhe", "ukf"), estimator_runs=1)


@pytest.mark.slow
def test_real_rc_car_recordings(tmp_path):
    """The four DART recordings pooled (folds by run, each held out in turn), both estimators
    scored on the last run held out, each on its own."""
    folder = _real("dart")
    system, runs = load(None, folder, "dart")
    d = diagnose(system, runs, settings=REAL_SETTINGS, work_dir=tmp_path)
    r = d.report
    assert r["pooled"] and r["folds"] == "3 contiguous time blocks in each of 4 runs" and r["runs"] == 4
    assert r["verdict"] != "no gap"  # the prior has no friction, drag or motor curve
    assert max(s["snr"] for s in r["where"] if s["residual_state"]) > 5
    assert r["effects"] or r["rejected_effects"]
    # the throttle map of the prior is far off on this car: a physical drive curve (back-EMF
    # against Coulomb friction), not a switched-off drive, closes most of the held-out gap
    found = {e["name"]: e for e in r["effects"]}
    assert "back_emf(v via throttle)" in found and "coulomb_friction(v)" in found, sorted(found)
    assert not any(name.startswith("actuator_gain") for name in found)
    assert 0.15 < found["back_emf(v via throttle)"]["params"]["k_e"] < 0.30
    assert r["shrink"]["one_step"]["closed"] > 0.61
    # the pooled parameters are those the held-out runs were scored with: within the range of
    # the runs' own fits (a refit whitened by an autoregression of this residual, far above the
    # noise floor, puts the Coulomb friction at 15.5 where every run's fit is 3.3-3.9)
    for c in r["consistency"]:
        (value,) = found[c["effect"]]["params"].values()
        assert min(c["per_run"]) <= value <= max(c["per_run"]), (c, value)
    _honest(r)


@pytest.mark.slow
def test_real_crazyflie_flights(tmp_path):
    """Three NanoBench flights pooled: the jerk residual is near the floor; whatever is selected
    must not be a finding for an estimator it makes worse on the held-out flight."""
    folder = _real("nanobench")
    system, runs = load(None, folder, "nanobench")
    d = diagnose(system, runs[:3], settings=REAL_SETTINGS, work_dir=tmp_path)
    r = d.report
    assert r["pooled"] and r["folds"] == "4 contiguous time blocks in each of 3 runs"
    assert r["noise_floor"]["method"].startswith("calibration")
    names = {e.name for e in d.effects}
    assert all(e["name"] in names or e["name"].startswith("thrust_response") for e in r["effects"])
    _honest(r)


def test_knode_model_is_compared(cartpole):
    """The learned residual of a (briefly) trained model is set against the measured one."""
    from learnest_codegen.learning.training import TrainingSettings, train_on_run

    run = simulate(cartpole, seed=3, duration=3.0)
    model = train_on_run(run, cartpole, TrainingSettings(epochs=2, refine=0), progress=False)
    d = diagnose(cartpole, [run], model=model, settings=QUICK_SETTINGS)
    knode = d.report["knode"]
    assert set(knode) == {"pdot", "alphadot"}
    r = d.residual[:, 1]
    import torch

    with torch.no_grad():
        delta = model.net(torch.as_tensor(d.fit_pairs.x), torch.as_tensor(d.fit_pairs.u)).numpy()[:, 1]
    assert knode["pdot"]["r2"] == pytest.approx(1 - np.mean((r - delta) ** 2) / np.var(r), rel=1e-9)
    one = d.report["shrink"]["one_step"]
    assert {"prior", "corrected", "knode", "true", "closed_knode"} <= set(one)


def test_diagnose_takes_a_model_directory(cartpole, tmp_path):
    """``diagnose(model=...)`` loads a trained model from its directory (a str or a Path) and gives
    the same comparison as the loaded model; anything else is a one-line LearnestError."""
    from learnest_codegen.errors import LearnestError
    from learnest_codegen.learning.training import TrainingSettings, train_on_run

    run = simulate(cartpole, seed=3, duration=3.0)
    model = train_on_run(run, cartpole, TrainingSettings(epochs=2, refine=0), progress=False)
    folder = model.save(tmp_path / "model")
    loaded = diagnose(cartpole, [run], model=model, settings=QUICK_SETTINGS).report["knode"]
    for given in (str(folder), folder):
        assert diagnose(cartpole, [run], model=given, settings=QUICK_SETTINGS).report["knode"] == loaded
    for wrong in (tmp_path, tmp_path / "missing", 3):
        with pytest.raises(LearnestError) as err:
            diagnose(cartpole, [run], model=wrong, settings=QUICK_SETTINGS)
        assert "\n" not in str(err.value) and "model" in str(err.value)




def test_user_system_file(tmp_path, user_system_file):
    """The README's pendulum from a user's file: its missing damping is found, nothing else."""
    path = user_system_file
    run_csv = tmp_path / "run.csv"
    runner = CliRunner()
    assert runner.invoke(cli, ["simulate", "--system", str(path), "--out", str(run_csv)]).exit_code == 0
    result = runner.invoke(cli, ["diagnose", "--system", str(path), "--data", str(run_csv), "--out",
                                 str(tmp_path / "diag"), "--estimators", "", "--no-progress"],
                           catch_exceptions=False)
    assert result.exit_code == 0, result.output
    report = json.loads((tmp_path / "diag" / "diagnosis.json").read_text())
    (effect,) = report["effects"]
    assert effect["kind"] == "viscous_friction" and effect["state"] == "qdot"
    assert effect["params"]["c"] == pytest.approx(0.3, rel=1e-3)
    assert "parameter(qdot via c)" in effect["aliases"]  # the prior's own damping term, at 0


def test_quadrotor_thrust_response_physical_parameters():
    """On the simulated quadrotor the grouped thrust_response recovers tau, k_T, k_D of its truth."""
    from learnest_codegen.systems.quadrotor import K_DRAG, K_T, TAU_MOTOR

    quad = get_system("quadrotor")
    d = diagnose(quad, [simulate(quad, seed=2, duration=10.0)], settings=QUICK_SETTINGS)
    effect = next(e for e in d.report["effects"] if e["kind"] == "thrust_response")
    assert set(effect["params"]) == {"k/tau", "1/tau", "k_D/tau"}
    got = effect["derived"]
    np.testing.assert_allclose([got["tau"], got["k_T"], got["k_D"]], [TAU_MOTOR, K_T, K_DRAG], rtol=1e-3)
    assert d.report["verdict"] == "explained" and d.report["shrink"]["one_step"]["closed"] > 0.99


def test_pendulum_parameters_not_an_actuator_gain():
    """A prior with inertia and gravity torque wrong by large factors: an actuator gain plus the
    gravity torque fits as well, but the system's own parameters are named, and the friction the
    truth adds is found too (truth source: the form of the smoothing differs slightly, so the
    residual stays above the strict floor and the verdict is honest about it)."""
    from learnest_codegen.diagnosis.selftest_systems import PENDULUM_PRIOR, PENDULUM_TRUE, pendulum

    p = pendulum()
    d = diagnose(p, [simulate(p, 1, duration=10.0)], settings=dataclasses.replace(QUICK_SETTINGS,
                                                                                     estimators=("ukf",)))
    found = {e["name"]: e for e in d.report["effects"]}
    assert set(found) == {"mass(qdot via J)", "parameter(qdot via mgl)", "coulomb_friction(qdot)"}
    assert found["mass(qdot via J)"]["params"]["J"] == pytest.approx(PENDULUM_TRUE["J"], rel=0.01)
    assert found["parameter(qdot via mgl)"]["params"]["mgl"] == pytest.approx(PENDULUM_TRUE["mgl"], rel=0.01)
    torque = found["coulomb_friction(qdot)"]["equivalent"]["coulomb_friction(qdot via tau)"]["value"]
    assert torque == pytest.approx(0.2, rel=0.03)  # [N m]
    assert PENDULUM_PRIOR["J"] != PENDULUM_TRUE["J"]
    assert [s["removed"] for s in d.report["selection"]["swapped"]] == ["actuator_gain(qdot via tau)"]
    one = d.report["shrink"]["one_step"]
    assert one["after"] > DiagnosisSettings().explained_gap  # not at the floor ...
    assert d.report["verdict"] == "partly explained"  # ... so not "explained"
    assert d.report["estimator_verdicts"] == {"ukf": "improved"}
    assert d.report["shrink"]["ukf"]["after"] < 0.05 * d.report["shrink"]["ukf"]["before"]


def test_refine_never_raises_and_matches_scipy():
    """The damped, bounded LM: on a smooth problem it reaches scipy's least-squares optimum; where
    the model is undefined beyond a point (1 / (J + dJ) at dJ = -J) it stays inside its bounds;
    a residual that cannot be computed is a failed status, not an exception."""
    from scipy.optimize import least_squares

    from learnest_codegen.diagnosis.refine import refine

    x = np.linspace(0.1, 3, 200)
    y = 2.0 / (0.3 + 0.2) * np.sin(x) + 0.05 * np.cos(7 * x)  # J = 0.3 + 0.2, a small misfit

    def evaluate(th):
        J = 0.3 + th[0]
        R = y - 2.0 / J * np.sin(x)
        return R, (-2.0 / J**2 * np.sin(x))[:, None]  # R(th + d) ~ R - Phi d

    out = refine(evaluate, np.array([0.0]), np.array([-0.297]), np.array([30.0]), lambda th: 0.3 + th)
    ref = least_squares(lambda th: evaluate(th)[0], [0.0]).x
    assert out.ok and out.theta[0] == pytest.approx(ref[0], abs=1e-7)
    # start far on the wrong side: the step limit keeps J positive all the way
    far = refine(evaluate, np.array([5.0]), np.array([-0.297]), np.array([30.0]), lambda th: 0.3 + th)
    assert far.ok and far.theta[0] == pytest.approx(ref[0], abs=1e-6)

    def broken(th):
        raise np.linalg.LinAlgError("singular")

    failed = refine(broken, np.array([0.0]), np.array([-1.0]), np.array([1.0]), lambda th: th)
    assert not failed.ok and failed.status.startswith("failed")
    # a wrong-signed Jacobian: no step lowers the residual, so it stops where it started
    wrong = refine(lambda th: (evaluate(th)[0], -evaluate(th)[1]), np.array([0.0]), np.array([-0.297]),
                   np.array([30.0]), lambda th: 0.3 + th)
    assert wrong.theta[0] == 0.0 and np.isfinite(wrong.sse)


def test_verdicts_follow_the_held_out_evidence():
    """Each estimator is judged on its own; a correction one estimator rejects is never
    "explained", and one that worsens the held-out residual is "rejected"."""
    from learnest_codegen.diagnosis.shrink import by_estimator, estimator_verdict, verdict

    s = DiagnosisSettings()
    assert estimator_verdict(1.0, 0.5, 0.01) == "improved"
    assert estimator_verdict(1.0, 1.005, 0.01) == "unchanged"
    assert estimator_verdict(1.0, 2.4, 0.01) == "rejected"
    assert estimator_verdict(1.0, float("nan"), 0.01) == "rejected"
    at_floor = {"one_step": {"before": 10.0, "after": 0.1, "closed": 0.99}}
    mixed = {**at_floor, "mhe": {"verdict": "improved"}, "ukf": {"verdict": "rejected"}}
    assert verdict(True, True, "converged", at_floor, s) == "explained"
    assert verdict(True, True, "converged", mixed, s) == "partly explained"
    both = {**at_floor, "mhe": {"verdict": "rejected"}, "ukf": {"verdict": "rejected"}}
    assert verdict(True, True, "converged", both, s) == "rejected"
    worse = {"one_step": {"before": 1.0, "after": 2.0, "closed": -1.0}}
    assert verdict(True, True, "converged", worse, s) == "rejected"
    above = {"one_step": {"before": 10.0, "after": 3.0, "closed": 0.7}}
    assert verdict(True, True, "converged", above, s) == "partly explained"
    assert verdict(True, True, "failed: residual not finite", at_floor, s) == "refit failed"
    assert verdict(False, False, "converged", at_floor, s) == "no gap"
    # the effects are findings for the estimator they improve, rejected by the one they worsen
    numbers = {"mhe": {"verdict": "improved", "before": 1.0, "after": 0.2},
               "ukf": {"verdict": "rejected", "before": 1.0, "after": 1.3}}
    per = by_estimator(["coulomb_friction(v)"], numbers, ("mhe", "ukf"))
    assert per["mhe"]["found"] == ["coulomb_friction(v)"] and per["mhe"]["rejected"] == []
    assert per["ukf"]["found"] == [] and per["ukf"]["rejected"] == ["coulomb_friction(v)"]
    from learnest_codegen.diagnosis import summary
    from learnest_codegen.diagnosis.shrink import verdict_and_reason

    one = {"before": 10.0, "after": 1.0, "closed": 0.9}
    v, why = verdict_and_reason(True, True, "converged", {"one_step": one, **numbers}, s)
    report = {"system": "s", "verdict": v, "verdict_reason": why, "source": "observer",
              "explained_in_sample": 0.9,
              "heldout_gap_closed": 0.9, "basis": "2 runs fitted together, each held out in turn",
              "where": [], "consistency": [], "rejected_effects": [],
              "effects": [{"name": "coulomb_friction(v)", "params": {"F_c": 0.3},
                           "uncertainty": {"F_c": 0.01}, "in_sample_share": 0.9,
                           "estimators": {"mhe": "improved", "ukf": "rejected"}}],
              "shrink": {"one_step": one, **numbers}}
    text = summary(report)
    assert text.startswith("s: partly explained - held-out gap closed 90.0%, in-sample share explained 90.0%")
    assert "the UKF held-out MSE gets worse with the correction" in text
    assert "coulomb_friction(v): F_c=0.3 (+-0.01), 90% of the in-sample gap; rejected for the UKF" in text
    assert by_estimator(["x"], {"ukf": {"verdict": "unchanged", "before": 1.0, "after": 1.0}},
                        ("mhe", "ukf")) == {"ukf": {"verdict": "unchanged", "before": 1.0, "after": 1.0,
                                                    "found": [], "rejected": []}}


def test_pooled_runs_fold_by_run_and_agree():
    """Three short cartpole runs pooled: folds are the runs, every run is held out in turn with a
    correction that did not see it, and the mass is the same on each run."""
    cartpole = get_system("cartpole")
    runs = [simulate(cartpole, seed, duration=3.0) for seed in (1, 2, 3)]
    d = diagnose(cartpole, runs, settings=QUICK_SETTINGS)
    r = d.report
    assert r["pooled"] and r["folds"] == "4 contiguous time blocks in each of 3 runs"
    assert r["heldout_pairs"] == r["fit_pairs"] == sum(len(run) - 1 for run in runs)
    (effect,) = r["effects"]
    assert effect["name"] == "mass(pdot via m_c)" and effect["params"]["dm_c"] == pytest.approx(0.5, rel=0.01)
    (c,) = r["consistency"]
    assert c["consistent"] and c["sign_agreement"] == 1.0
    np.testing.assert_allclose(c["per_run"], 0.5, rtol=0.02)
    assert len(r["shrink"]["one_step"]["per_segment"]) == 3
    assert all(s["corrected"] < 0.01 * s["prior"] for s in r["shrink"]["one_step"]["per_segment"])
    assert r["verdict"] == "explained"


def test_inertia_alone_stays_bounded():
    """With only the inertia and friction on offer, the inertia cannot explain the wrong gravity
    torque; the refit must stay within its bounds (Gauss-Newton once went to 4e52 and raised) and
    the verdict must not claim the gap is explained."""
    from learnest_codegen.diagnosis.selftest_systems import PENDULUM_PRIOR, pendulum

    p = pendulum()
    settings = dataclasses.replace(QUICK_SETTINGS, kinds=("mass", "coulomb_friction"))
    d = diagnose(p, [simulate(p, 1, duration=10.0)], settings=settings)
    J = next((e["params"]["J"] for e in d.report["effects"] if e["name"] == "mass(qdot via J)"), None)
    assert J is None or PENDULUM_PRIOR["J"] / 100 <= J <= PENDULUM_PRIOR["J"] * 100
    assert d.report["verdict"] in ("partly explained", "unexplained", "refit failed")
    assert d.report["shrink"]["one_step"]["after"] > DiagnosisSettings().explained_gap


def test_explained_needs_the_estimators_at_the_supported_level():
    """A correction at the one-step floor is not "explained" while an estimator's corrected
    held-out MSE is more than 20 % above the level the data support; the reason names the
    estimator, by how much, and the kinds tried. Within 20 % it is."""
    from learnest_codegen.diagnosis.shrink import verdict_and_reason

    s = DiagnosisSettings()
    one = {"before": 10.0, "after": 0.1, "closed": 0.99}

    def mhe(after):
        return {"verdict": "improved", "before": 2.0, "after": after, "supported": 1.0,
                "above_supported": after - 1.0, "supported_by": "the true dynamics' estimator"}

    v, why = verdict_and_reason(True, True, "converged", {"one_step": one, "mhe": mhe(1.37)}, s,
                                ["mass", "coulomb_friction"])
    assert v == "partly explained"
    assert "MHE's held-out error stays 37% above what the data support" in why
    assert "kinds tried: mass, coulomb_friction" in why
    v, why = verdict_and_reason(True, True, "converged", {"one_step": one, "mhe": mhe(1.19)}, s)
    assert v == "explained" and "reach the error the data support" in why
    unmeasured = {**mhe(1.0), "supported": None, "above_supported": None}
    v, why = verdict_and_reason(True, True, "converged", {"one_step": one, "mhe": unmeasured}, s)
    assert v == "partly explained" and "could not be measured" in why


def test_verdict_reasons_never_contradict_the_figures():
    """The verdict follows the held-out figures by the stated rule, and its sentence quotes them:
    a correction at the floor is "explained"; one that closes 99 % but stays above the floor is
    "partly explained" and says so; one that closes less than a quarter is "unexplained"."""
    from learnest_codegen.diagnosis.shrink import verdict_and_reason

    s = DiagnosisSettings()
    cases = {(10.0, 0.1, 0.99): "explained", (1000.0, 9.5, 0.9905): "partly explained",
             (10.0, 8.0, 0.2): "unexplained", (10.0, 12.0, -0.2): "rejected"}
    for (before, after, closed), expected in cases.items():
        v, why = verdict_and_reason(True, True, "converged",
                                    {"one_step": {"before": before, "after": after, "closed": closed}}, s)
        assert v == expected
        if expected in ("partly explained", "unexplained"):
            assert f"{closed:.1%}" in why
        if expected == "partly explained":
            assert "above the noise floor" in why and f"{after:.3g}" in why


def _holey_runs():
    """Two cartpole runs (cart mass +0.5 kg) with empty measurement, input and truth cells."""
    cartpole = get_system("cartpole")
    runs = [simulate(cartpole, seed, duration=3.0) for seed in (1, 2)]
    holey = []
    for k, r in enumerate(runs):
        y, u, x = r.y.copy(), r.u.copy(), r.x.copy()
        y[50 + 7 * np.arange(40), k % 2] = np.nan
        u[300:303] = np.nan
        x[600:605, 1] = np.nan
        holey.append(dataclasses.replace(r, y=y, u=u, x=x))
    return cartpole, runs, holey


def test_missing_cells_are_tolerated():
    """Runs with empty measurement and input cells (what a reader marks as missing): inputs are
    held, pairs without truth left out; the report counts them and the diagnosis is the one of
    the complete runs."""
    cartpole, runs, holey = _holey_runs()
    d = diagnose(cartpole, holey, settings=QUICK_SETTINGS)
    r = d.report
    assert r["missing"] == {"inputs": 6, "measurements": 80, "truth": 10}
    assert r["pooled"] and r["basis"].startswith("2 runs fitted together")
    (effect,) = r["effects"]
    assert effect["name"] == "mass(pdot via m_c)" and effect["params"]["dm_c"] == pytest.approx(0.5, rel=0.01)
    assert r["fit_pairs"] == sum(len(run) - 1 for run in runs) - 2 * 6  # 5 missing truth rows: 6 pairs


@pytest.mark.slow
def test_missing_measurements_through_the_observer():
    """The same runs seen through the observer: missing measurements are interpolated for it and
    the cart mass is still the finding."""
    cartpole, _, holey = _holey_runs()
    observed = diagnose(cartpole, holey, settings=dataclasses.replace(QUICK_SETTINGS, source="observer"))
    assert observed.report["missing"]["measurements"] == 80
    assert observed.report["effects"][0]["name"] == "mass(pdot via m_c)"


def test_quadrotor_start_state_is_the_studys():
    """``diagnose`` on flights starts the estimators where the quadrotor study does."""
    from learnest_codegen.diagnosis.loading import start_state
    from learnest_codegen.experiments.quadrotor import initial_state

    run = simulate(get_system("quadrotor"), seed=3, duration=2.0)
    run = dataclasses.replace(run, y=run.y + np.random.default_rng(0).normal(0, 1e-3, run.y.shape), x=None)
    np.testing.assert_array_equal(start_state(run), initial_state(run))


def test_a_never_airborne_flight_is_skipped(tmp_path):
    """A folder holding a flight that never leaves the ground: the diagnosis reads the others and
    lists the grounded one with its reason, as the quadrotor study does."""
    from learnest_codegen.diagnosis import load_recordings
    from learnest_codegen.recordings.crazyflie import list_flights

    folder = _real("nanobench")
    source = list_flights(folder)[0]
    (tmp_path / source.name).write_bytes(source.read_bytes())
    lines = source.read_text().splitlines()
    header = lines[0].split(",")
    motors = [header.index(f"motor_motor_m{i}") for i in range(1, 5)]
    grounded = []
    for line in lines[1:]:
        cells = line.split(",")
        for m in motors:
            cells[m] = "0"
        grounded.append(",".join(cells))
    (tmp_path / "Z_grounded.csv").write_text("\n".join([lines[0], *grounded]) + "\n")
    system, found = load_recordings(None, tmp_path, "nanobench")
    assert found.names == [source.stem] and list(found.skipped) == ["Z_grounded"]
    assert "no airborne samples" in found.skipped["Z_grounded"]
    assert found.references[0].shape == (len(found.runs[0]), 9)
    assert found.reference.startswith("the quadrotor study's reference")


@pytest.mark.slow
def test_flight_estimators_scored_as_the_study_scores_them(tmp_path):
    """On a held-out flight, the nominal UKF's MSE in the diagnosis is the quadrotor study's
    nominal UKF MSE on that flight: the same reference (Savitzky-Golay of Vicon position), the
    same start state, the same compiled estimator."""
    from learnest_codegen.diagnosis import load_recordings
    from learnest_codegen.experiments.quadrotor import Case, StudySettings, nominal_results

    folder = _real("nanobench")
    system, found = load_recordings(None, folder, "nanobench")
    found = dataclasses.replace(found, runs=found.runs[:2], names=found.names[:2],
                                references=found.references[:2], starts=found.starts[:2])
    d = diagnose(system, found, settings=dataclasses.replace(REAL_SETTINGS, estimators=("ukf",)),
                 work_dir=tmp_path / "diag")
    ukf = d.report["shrink"]["ukf"]
    assert ukf["metric"] == "MSE against " + found.reference
    case = Case(found.names[1], found.runs[1], found.references[1])
    study = nominal_results([case], tmp_path / "study", StudySettings(estimators=("ukf",)), progress=False)
    assert ukf["per_segment"]["prior"][-1] == pytest.approx(study[case.name]["UKF"]["mse"], rel=1e-9)


def test_bench_finds_the_dart_recordings_under_the_data_root(tmp_path, monkeypatch):
    """The benchmark's DART part reads ``dart/`` under the data root ($LEARNEST_DATA first), an
    explicit folder as given, and is skipped (its view says so) when there are no recordings."""
    import sys
    from pathlib import Path

    scripts = Path(__file__).resolve().parents[1] / "scripts"
    monkeypatch.syspath_prepend(str(scripts))
    import bench_diagnosis
    import figures

    monkeypatch.setenv("LEARNEST_DATA", str(tmp_path))
    monkeypatch.chdir(tmp_path)
    assert bench_diagnosis._dart_folder(None) is None

    def none_kept(name):
        raise FileNotFoundError(name)

    monkeypatch.setattr(figures, "load", none_kept)  # no part kept from an earlier run
    args = type("Args", (), {"parts": "dart", "dart": None})()
    out, cond = bench_diagnosis.measure(args)
    assert "dart" not in out and "dart/ of the data root" in cond["run"]
    assert "not measured" in bench_diagnosis.render_dart({"figures": out})
    (tmp_path / "dart").mkdir()
    (tmp_path / "dart" / "run1.csv").write_text("t\n0\n")
    assert Path(bench_diagnosis._dart_folder(None)) == tmp_path / "dart"
    assert bench_diagnosis._dart_folder(str(tmp_path / "elsewhere")) == str(tmp_path / "elsewhere")
    del sys.modules["bench_diagnosis"]
