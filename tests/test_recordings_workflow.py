"""Many recordings through the command line: one model trained on many runs, estimators
evaluated on many runs per state group, and the quadrotor study on a training set and a test
set of flights (docs/guide/recordings_workflow.md)."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from learnest_codegen import get_system
from learnest_codegen.cli import cli
from learnest_codegen.recordings import data_root
from learnest_codegen.recordings.runs import read_reference


def invoke(*args):
    result = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return result


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("runs")
    for seed in range(4):
        invoke("simulate", "--system", "cartpole", "--seed", seed, "--duration", 3,
               "--out", folder / f"r{seed}.csv")
    return folder


def test_train_on_many_runs_counts_a_copy_once(runs, tmp_path):
    shutil.copy(runs / "r0.csv", tmp_path / "r0_again.csv")
    result = CliRunner().invoke(cli, ["train", "--system", "cartpole", "--data", str(runs / "r0.csv"),
                                      "--data", str(runs / "r1.csv"), "--data",
                                      str(tmp_path / "r0_again.csv"), "--out", str(tmp_path / "model"),
                                      "--epochs", "3"])
    assert result.exit_code == 0, result.output
    meta = json.loads((tmp_path / "model" / "model.json").read_text())
    assert meta["runs"] == ["r0", "r1"] and meta["run_samples"] == [1500, 1500]
    assert "r0_again: duplicate: the same data as r0; counted once" in result.output


def test_evaluate_many_runs_per_state_group(runs, tmp_path):
    """``evaluate``'s per-run, per-group MSEs are those of ``estimate``'s estimates against the
    truth (an independent path through the same compiled estimator), its changes and
    normalised overall follow from them, and a partial reference scores only its states."""
    invoke("train", "--system", "cartpole", "--data", runs / "r0.csv", "--data", runs / "r1.csv",
           "--out", tmp_path / "model", "--epochs", 3)
    report = tmp_path / "report.json"
    out = invoke("evaluate", "--model", tmp_path / "model", "--data", runs / "r2.csv", "--data",
                 runs / "r3.csv", "--estimator", "ukf", "--build", tmp_path / "build", "--out", report).output
    assert "runs better" in out and "overall" in out
    data = json.loads(report.read_text())
    assert data["groups"] == {"m": ["p"], "rad": ["alpha"], "m/s": ["pdot"], "rad/s": ["alphadot"]}
    per_run = data["estimators"]["ukf"]["per_run"]
    truth_cols = None
    for name, model in (("model", str(tmp_path / "model")), ("against", "nominal")):
        for run in ("r2", "r3"):
            est = tmp_path / f"{run}_{name}.csv"
            invoke("estimate", "--data", runs / f"{run}.csv", "--estimator", "ukf", "--model", model,
                   "--out", est)
            x_hat = np.loadtxt(est, delimiter=",", skiprows=1)[:, 1:]
            table = np.genfromtxt(runs / f"{run}.csv", delimiter=",", names=True)
            truth_cols = [c for c in table.dtype.names if c.startswith("x_")]
            truth = np.column_stack([table[c] for c in truth_cols])
            for group, states in data["groups"].items():
                idx = [truth_cols.index(f"x_{s}") for s in states]
                want = float(np.mean((x_hat[:, idx] - truth[:, idx]) ** 2))
                assert per_run[run][name][group] == pytest.approx(want, rel=1e-12), (run, name, group)
    for r in per_run.values():
        ratios = [r["model"][g] / r["against"][g] for g in data["groups"]]
        assert r["overall_change"] == pytest.approx(100 * (1 - np.mean(ratios)), rel=1e-12)
    summary = data["estimators"]["ukf"]["summary"]["m"]
    changes = [100 * (r["against"]["m"] - r["model"]["m"]) / r["against"]["m"] for r in per_run.values()]
    assert summary["mean"] == pytest.approx(np.mean(changes)) and summary["runs"] == 2

    # a reference of the angle only: one group scored
    ref_dir = tmp_path / "refs"
    ref_dir.mkdir()
    for run in ("r2", "r3"):
        table = np.genfromtxt(runs / f"{run}.csv", delimiter=",", names=True)
        lines = ["t,x_alpha"] + [f"{float(t)!r},{float(a)!r}" for t, a in zip(table["t"], table["x_alpha"])]
        lines[5] = lines[5].split(",")[0] + ","  # an empty cell: no reference there
        (ref_dir / f"{run}.csv").write_text("\n".join(lines) + "\n")
    t2 = np.genfromtxt(runs / "r2.csv", delimiter=",", names=True)["t"]
    system = get_system("cartpole")
    ref = read_reference(ref_dir / "r2.csv", system, t2)
    alpha = system.state_names.index("alpha")
    assert np.isnan(ref[4, alpha]) and np.isfinite(ref[5:, alpha]).all()
    assert np.isnan(np.delete(ref, alpha, axis=1)).all()
    partial = tmp_path / "partial.json"
    invoke("evaluate", "--model", tmp_path / "model", "--data", runs / "r2.csv", "--data", runs / "r3.csv",
           "--reference", ref_dir, "--build", tmp_path / "build", "--out", partial)
    assert set(json.loads(partial.read_text())["estimators"]["ukf"]["summary"]) == {"rad", "overall"}


def test_estimate_many_runs_into_a_folder(runs, tmp_path):
    invoke("estimate", "--data", runs / "r2.csv", "--data", runs / "r3.csv", "--estimator", "ukf",
           "--model", "nominal", "--system", "cartpole", "--out", tmp_path / "estimates")
    written = sorted(p.name for p in (tmp_path / "estimates").iterdir() if p.suffix == ".csv")
    assert written == ["r2.csv", "r3.csv"]


def _flights():
    root = data_root()
    if root is None or not (root / "nanobench").is_dir():
        pytest.skip("NanoBench flights not found (../shared/data/nanobench or $LEARNEST_DATA)")
    return root / "nanobench"


def _drifting_copy(src, dst, start_s, rate_g_per_s):
    """``src`` with its y accelerometer climbing by ``rate_g_per_s`` from ``start_s`` (the motion
    capture unchanged), written as ``dst``."""
    from learnest_codegen.recordings import crazyflie as nb

    header = src.read_text().splitlines()[0].split(",")
    columns = nb.read_table(src)
    t = columns["t"] - columns["t"][0]
    columns["imu_acc_y"] = columns["imu_acc_y"] + rate_g_per_s * np.clip(t - start_s, 0, None)
    np.savetxt(dst, np.column_stack([columns[h] for h in header]), delimiter=",", header=",".join(header),
               comments="", fmt="%.9f")


def test_reproduce_quadrotor_on_a_training_set_and_a_test_set(tmp_path):
    """The command of docs/guide/recordings_workflow.md, ``--recommended --train DIR/ --test
    'DIR2/*.csv'``, on NanoBench flights: a training folder holding a renamed copy of one of its
    flights and a flight whose accelerometer drifts by 0.2 g/s from 12 s, and a test folder
    holding a copy of a training flight. One model is trained on the three distinct training
    flights (the drifting one up to 1 s before its drift, at most), tested on the one new
    flight; both copies are counted once and the drift is cut, each said on stderr and in the
    report; the report has the per-state table of both estimators at every reference."""
    src = _flights()
    train, test = tmp_path / "flights" / "train", tmp_path / "flights" / "new"
    train.mkdir(parents=True)
    test.mkdir()
    for name in ("B2_circle_slow_rep1", "B2_circle_fast_rep1"):
        shutil.copy(src / f"{name}.csv", train / f"{name}.csv")
    shutil.copy(src / "B2_circle_slow_rep1.csv", train / "Z9_copy.csv")
    _drifting_copy(src / "B2_circle_medium_rep1.csv", train / "B2_circle_drifting.csv", 12.0, 0.2)
    shutil.copy(src / "B3_figure8_slow_rep1.csv", test / "B3_figure8_slow_rep1.csv")
    shutil.copy(src / "B2_circle_slow_rep1.csv", test / "B9_renamed_rep1.csv")
    out = tmp_path / "results" / "mine"
    result = CliRunner().invoke(cli, ["reproduce", "quadrotor", "--recommended", "--train", f"{train}/",
                                      "--test", f"{test}/*.csv", "--out", str(out)])
    assert result.exit_code == 0, result.output
    for line in ("Z9_copy: duplicate: the same data as B2_circle_slow_rep1; counted once",
                 "B9_renamed_rep1: duplicate: the same data as B2_circle_slow_rep1; counted once",
                 "B2_circle_drifting: accelerometer"):
        assert f"warning: {line}" in result.output, line
    data = json.loads((out / "quadrotor.json").read_text())
    assert data["protocol"] == "train-test"
    (drift,) = [f for f in data["findings"] if f["check"] == "accelerometer"]
    assert drift["recording"] == "B2_circle_drifting" and drift["action"] == "cut"
    assert 11.5 <= drift["start_s"] <= 12.5  # the hinge dates the drift's start
    (study,) = data["studies"]
    assert study["features"] == "bias_lag_prior" and list(study["per_case"]) == ["B3_figure8_slow_rep1"]
    trained_on = ["B2_circle_drifting", "B2_circle_fast_rep1", "B2_circle_slow_rep1"]
    assert study["trained_on"]["B3_figure8_slow_rep1"] == trained_on
    meta = json.loads((out / "runs" / "train_set" / "bias_lag_prior" / "model" / "model.json").read_text())
    samples = dict(zip(meta["runs"], meta["run_samples"]))
    assert sorted(samples) == trained_on
    kept = re.fullmatch(r"kept (\d+\.\d+)-(\d+\.\d+) s of the log", drift["note"])
    assert kept and float(kept[2]) <= drift["start_s"] - 1.0 + 0.005  # ends 1 s before the drift
    assert samples["B2_circle_drifting"] == pytest.approx(100 * (float(kept[2]) - float(kept[1])) + 1, abs=1)
    for knode in ("KNODE-UKF", "KNODE-MHE-RTI"):
        refs = study["by_reference"][knode]
        assert set(refs) == {"sg_0.5s", "sg_1s", "sg_1.5s", "sg_3s", "cd_0.1s"}
        assert set(refs["sg_1s"]) == {"p", "v", "a", "overall"}
        assert set(refs["cd_0.1s"]) == {"p", "v", "overall"}  # central differences: no acceleration
    report = (out / "quadrotor.md").read_text()
    assert "### Per state group and reference" in report and report.count("| cd_0.1s |") >= 3
    assert "Recordings checked" in report and "B2_circle_drifting: accelerometer" in report
    assert "Z9_copy: duplicate" in report and "B9_renamed_rep1: duplicate" in report
