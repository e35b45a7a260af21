"""The command-line contract, end to end: simulate -> train -> compile -> estimate, and the demo."""

from __future__ import annotations

import json
import re

import click
import numpy as np
import pytest
from click.testing import CliRunner

from learnest_codegen.cli import cli, compile_cmd
from learnest_codegen.data import read_run
from learnest_codegen.systems import get_system


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("cli")


def invoke(command, args):
    result = CliRunner().invoke(command, [str(a) for a in args], catch_exceptions=False)
    return result


def test_simulate_train_compile_estimate(workdir):
    run_csv, model_dir, compiled = workdir / "run.csv", workdir / "model", workdir / "compiled"
    r = invoke(cli, ["simulate", "--system", "cartpole", "--seed", 3, "--duration", 0.6, "--out", run_csv])
    assert r.exit_code == 0, r.output
    run = read_run(run_csv, get_system("cartpole"))
    assert len(run) == 300 and run.x is not None

    r = invoke(cli, ["train", "--system", "cartpole", "--data", run_csv, "--out", model_dir, "--epochs", 3,
                     "--weight-decay", 0.1, "--final-lr", 1e-3, "--weight-average", 0.9])
    assert r.exit_code == 0, r.output
    # not a terminal here: the recipe, the observer's choice and one line per training on stderr
    lines = r.stderr.splitlines()
    assert lines[0] == (f"training cartpole on {run_csv} (300 samples): observer chosen for the system; "
                        "3 epochs (full batch), 2 refinement rounds, 3 initialisations per training, "
                        "weight decay 0.1, float32"), lines
    assert lines[1].startswith("pre-training observer: rts (")
    assert [line.split(" ", 1)[0] for line in lines[2:]] == ["[1/3]", "[2/3]", "[3/3]"], lines
    assert all(re.search(r"best epoch \d+, validation loss \S+, \d+\.\d s$", line) for line in lines[2:])
    training = json.loads((model_dir / "model.json").read_text())["training"]
    assert (training["epochs"], training["weight_decay"], training["final_learning_rate"],
            training["weight_average"]) == (3, 0.1, 1e-3, 0.9)

    r = invoke(cli, ["train", "--system", "cartpole", "--data", run_csv, "--out", workdir / "quiet",
                     "--epochs", 1, "--refine", 0, "--quiet"])
    assert r.exit_code == 0 and r.stderr == "" and r.stdout.startswith(f"wrote {workdir / 'quiet'}: ")

    r = invoke(compile_cmd, [model_dir, "--out", compiled])
    assert r.exit_code == 0, r.output
    folders = {"mhe": "cartpole_knode_mhe_n20", "ukf": "cartpole_knode_ukf"}  # an MHE's: its horizon
    for est in ("mhe", "ukf"):
        manifest = json.loads((compiled / folders[est] / "manifest.json").read_text())
        assert manifest["system"] == "cartpole" and manifest["nx"] == 4

    outputs = {}
    for est in ("ukf", "mhe"):
        for backend in ("python", "c"):
            out = workdir / f"{est}_{backend}.csv"
            args = ["estimate", "--system", "cartpole", "--data", run_csv, "--estimator", est,
                    "--model", model_dir, "--backend", backend, "--out", out]
            if backend == "c":
                args += ["--compiled", compiled / folders[est]]
            r = invoke(cli, args)
            assert r.exit_code == 0, r.output
            header = out.read_text().splitlines()[0]
            assert header == "t,xhat_p,xhat_pdot,xhat_alpha,xhat_alphadot"
            outputs[est, backend] = np.loadtxt(out, delimiter=",", skiprows=1)
        np.testing.assert_allclose(outputs[est, "c"], outputs[est, "python"], atol=1e-6)


def test_estimate_compiles_on_demand_and_nominal_compile(workdir):
    run_csv = workdir / "run2.csv"
    invoke(cli, ["simulate", "--duration", 0.2, "--out", run_csv])
    r = invoke(cli, ["estimate", "--data", run_csv, "--estimator", "ukf", "--model", "true",
                     "--out", workdir / "true_ukf.csv"])
    assert r.exit_code == 0 and "MSE vs truth" in r.stdout
    where = workdir.resolve() / ".learnest_compiled"  # said on stderr, one line
    assert r.stderr == f"compiling ukf into {where} (reused while the model is unchanged; --compiled " \
                       "DIR runs a folder of learnest-compile)\n", r.stderr
    assert (where / "cartpole_true_ukf" / "manifest.json").is_file()
    r = invoke(cli, ["compile", "--nominal", "--out", workdir / "nominal", "--estimator", "ukf"])
    assert r.exit_code == 0 and (workdir / "nominal" / "cartpole_nominal_ukf" / "manifest.json").is_file()


def test_errors_are_one_clear_line(workdir, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,u_F\n0,1\n")
    r = CliRunner().invoke(cli, ["estimate", "--data", str(bad), "--estimator", "ukf",
                                 "--out", str(tmp_path / "o.csv")])
    assert r.exit_code != 0 and "missing columns" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(cli, ["simulate", "--system", "nope", "--out", str(tmp_path / "x.csv")])
    assert r.exit_code != 0 and "unknown system" in r.output
    r = CliRunner().invoke(compile_cmd, [])
    assert r.exit_code != 0 and "--nominal" in r.output


def test_demo_end_to_end(tmp_path):
    """The main job on a short horizon: every estimator runs in Python and C and they agree."""
    r = invoke(cli, ["demo", "--out", tmp_path, "--epochs", 20, "--duration", 0.6])
    assert r.exit_code == 0, r.output
    report = json.loads((tmp_path / "report.json").read_text())
    rows = {(row["method"], row["backend"]): row for row in report["rows"]}
    for method in (f"{k}{e}{t}" for k in ("", "KNODE-") for e in ("MHE", "UKF", "EKF")
                   for t in ("", " (true dynamics)") if not (k and t)):
        c, py = rows[method, "C"], rows[method, "python"]
        assert np.isfinite(c["mse"]) and c["mse"] == pytest.approx(py["mse"], rel=1e-5)
    assert rows["UKF (true dynamics)", "C"]["mse"] < rows["UKF", "C"]["mse"]
    assert rows["EKF (true dynamics)", "C"]["mse"] < rows["EKF", "C"]["mse"]
    for png in ("estimates.png", "errors.png", "training_loss.png"):
        assert (tmp_path / png).stat().st_size > 10_000


def test_demo_defaults_are_the_one_default_training():
    """The demo's option defaults are DEFAULT_TRAINING's (read from config, so that `learnest
    --help` imports no torch), and Table I's cartpole task trains with its own recipe."""
    from learnest_codegen.config import DEFAULT_TRAINING, TABLE1_CARTPOLE_TRAINING
    from learnest_codegen.experiments import DEFAULT_TASKS

    defaults = {p.name: p.default for p in cli.commands["demo"].params}
    for name in ("epochs", "refine", "restarts", "weight_decay", "weight_average"):
        assert defaults[name] == getattr(DEFAULT_TRAINING, name), name
    help_text = " ".join(cli.commands["demo"].get_help(click.Context(cli)).split())
    assert f"Table I uses {TABLE1_CARTPOLE_TRAINING.refine})" in help_text
    assert DEFAULT_TASKS["cartpole"].training == TABLE1_CARTPOLE_TRAINING


def test_gate_options_default_to_the_gate_settings():
    from learnest_codegen.estimators.gate import GateSettings

    for command in (cli.commands["estimate"], cli.commands["compile"]):
        defaults = {p.name: p.default for p in command.params}
        assert (defaults["gate_threshold"], defaults["gate_recover_after"], defaults["gate_inflation"]) == (
            GateSettings().threshold, GateSettings().recover_after, GateSettings().inflation)


def test_estimate_gates_garbage_and_the_gate_can_be_turned_off(workdir):
    """Three absurd samples of p: the default gate rejects them (the summary counts them) and
    the estimate stays near the truth; with --gate-threshold 0 they are used and it does not."""
    clean, bad = workdir / "gate_run.csv", workdir / "gate_bad.csv"
    invoke(cli, ["simulate", "--duration", 1, "--seed", 4, "--out", clean])
    lines = clean.read_text().splitlines()
    col = lines[0].split(",").index("y_p")
    for k in (300, 301, 302):
        cells = lines[k + 1].split(",")
        cells[col] = "1000"
        lines[k + 1] = ",".join(cells)
    bad.write_text("\n".join(lines) + "\n")
    truth = read_run(clean, get_system("cartpole")).x
    errors, outputs = {}, {}
    for name, extra in (("gated", []), ("open", ["--gate-threshold", 0])):
        out = workdir / f"gate_{name}.csv"
        r = invoke(cli, ["estimate", "--data", bad, "--estimator", "ukf", "--model", "true",
                         "--out", out, *extra])
        assert r.exit_code == 0, r.output
        x_hat = np.loadtxt(out, delimiter=",", skiprows=1)[:, 1:]
        errors[name], outputs[name] = np.max(np.abs(x_hat[300:320, 0] - truth[300:320, 0])), r.output
    assert "3 output(s) rejected" in outputs["gated"] and "0 output(s) rejected" in outputs["open"]
    assert errors["gated"] < 0.01 < 1.0 < errors["open"], errors


def test_estimate_reports_samples_outside_the_training_range_and_clamps(workdir, tmp_path):
    """A quadrotor model trained on one run, estimated on a run whose battery voltage is above
    anything in training: the summary gives the share outside the range, naming vbat; the
    clamp compiles a model of its own; a nominal model cannot be clamped (one line, exit 1)."""
    train_csv, test_csv, model_dir = tmp_path / "train.csv", tmp_path / "test.csv", tmp_path / "model"
    invoke(cli, ["simulate", "--system", "quadrotor", "--duration", 2, "--seed", 1, "--out", train_csv])
    r = invoke(cli, ["train", "--system", "quadrotor", "--data", train_csv, "--out", model_dir,
                     "--epochs", 2, "--refine", 0])
    assert r.exit_code == 0, r.output
    lines = train_csv.read_text().splitlines()
    col = lines[0].split(",").index("u_vbat")
    for k in range(1, 101):  # the first 100 samples: 1 V above the run's battery
        cells = lines[k].split(",")
        cells[col] = repr(float(cells[col]) + 1.0)
        lines[k] = ",".join(cells)
    test_csv.write_text("\n".join(lines) + "\n")
    outputs = {}
    for name, extra in (("free", ["--no-clamp-inputs"]), ("clamped", ["--clamp-inputs"])):
        out = tmp_path / name / "x.csv"  # one compile folder each: a process loads a path once
        out.parent.mkdir()
        r = invoke(cli, ["estimate", "--system", "quadrotor", "--data", test_csv, "--estimator", "ukf",
                         "--model", model_dir, "--out", out, *extra])
        assert r.exit_code == 0, r.output
        outputs[name] = np.loadtxt(out, delimiter=",", skiprows=1)
        assert "outside the training range" in r.output and "vbat 50.0 %" in r.output, r.output
    assert np.abs(outputs["free"][:100] - outputs["clamped"][:100]).max() > 0  # another model
    r = CliRunner().invoke(cli, ["estimate", "--system", "quadrotor", "--data", str(test_csv), "--estimator",
                                 "ukf", "--model", "nominal", "--clamp-inputs",
                                 "--out", str(tmp_path / "n.csv")])
    assert r.exit_code == 1 and "has no net" in r.output and len(r.output.strip().splitlines()) == 1
