"""The whole job on a system file of one's own (the README's pendulum), from the command line and
from the API: simulate, train, compile all four estimators, estimate, diagnose, with no
``--system`` (``system=``) after training. A trained model records its system file (path and
content hash) and every later step finds it, or refuses in one line when the file changed."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import USER_SYSTEM

import learnest_codegen as ln
from learnest_codegen.cli import cli, compile_cmd
from learnest_codegen.errors import ModelMismatchError, SystemFileError
from learnest_codegen.learning.model import load_model

ESTIMATORS = ("ukf", "mhe", "mhe_gn", "mhe_rti")
SHORT = ln.TrainingSettings(epochs=30, validation_fraction=0.2)


def run(args, command=cli):
    result = CliRunner().invoke(command, [str(a) for a in args])
    return result


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    """A folder with the pendulum file, and the job run on it through the command line."""
    d = tmp_path_factory.mktemp("own")
    (d / "my_pendulum.py").write_text(USER_SYSTEM)
    system = str(d / "my_pendulum.py")
    for seed, name in ((0, "train.csv"), (1, "test.csv")):
        r = run(["simulate", "--system", system, "--seed", seed, "--duration", 2.0, "--out", d / name])
        assert r.exit_code == 0, r.output
    r = run(["train", "--system", system, "--data", d / "train.csv", "--out", d / "model", "--epochs", 30])
    assert r.exit_code == 0, r.output
    return d


def test_the_model_records_its_system_file(work):
    meta = json.loads((work / "model" / "model.json").read_text())
    source = meta["system_source"]
    assert source["file"] == str((work / "my_pendulum.py").resolve())
    assert len(source["sha256"]) == 64 and source["name"] == "my_pendulum"
    assert meta["observer"].split("+")[0] == "rts"  # the chain q -> qdot read from the equations


def test_the_command_line_job_needs_no_system_after_training(work):
    r = run([work / "model", "--out", work / "generated", *sum((["--estimator", e] for e in ESTIMATORS), [])],
            command=compile_cmd)
    assert r.exit_code == 0, r.output
    assert all(f"{e}:" in r.output for e in ESTIMATORS)
    for estimator in ESTIMATORS:
        r = run(["estimate", "--data", work / "test.csv", "--estimator", estimator, "--model", work / "model",
                 "--out", work / f"est_{estimator}.csv"])
        assert r.exit_code == 0, r.output
        mse = float(re.search(r"MSE vs truth (\S+)", r.output).group(1))
        assert 0 < mse < 1, (estimator, r.output)  # finite and sane; quality: the API test
        assert re.search(r"RMS error per state: q \S+ rad, qdot \S+ rad/s", r.output), r.output
    compiled = work / "generated" / "my_pendulum_knode_ukf"
    r = run(["estimate", "--data", work / "test.csv", "--estimator", "ukf", "--model", work / "model",
             "--compiled", compiled, "--out", work / "est_compiled.csv"])
    assert r.exit_code == 0, r.output
    r = run(["diagnose", "--data", work / "test.csv", "--model", work / "model", "--out", work / "diag",
             "--estimators", "ukf", "--no-progress"])
    assert r.exit_code == 0, r.output
    assert (f"comparing against the true states in {work / 'test.csv'} (x_q, x_qdot)") in r.output
    assert (work / "diag" / "diagnosis.json").is_file()
    # a compiled folder finds its system file too: ``load_estimator`` then ``evaluate``, no system
    test_run = ln.read_run(work / "test.csv", ln.get_system(str(work / "my_pendulum.py")))
    result = ln.evaluate(ln.load_estimator(work / "generated" / "my_pendulum_knode_mhe_rti_n20"), test_run)
    written = np.loadtxt(work / "est_mhe_rti.csv", delimiter=",", skiprows=1)[:, 1:]
    np.testing.assert_allclose(result.x_hat, written, rtol=0, atol=1e-12)


def test_the_api_job_needs_no_system_after_training(tmp_path):
    (tmp_path / "my_pendulum.py").write_text(USER_SYSTEM)
    system = ln.get_system(str(tmp_path / "my_pendulum.py"))
    train_run, test_run = ln.simulate(system, 0, duration=2.0), ln.simulate(system, 1, duration=2.0)
    ln.train(train_run, system, SHORT, progress=False).save(tmp_path / "model")
    from learnest_codegen import diagnosis

    model = load_model(tmp_path / "model")  # no system: the recorded file
    assert model.system.name == "my_pendulum" and model.system.fingerprint() == system.fingerprint()
    errors = {}
    for estimator in ESTIMATORS:
        compiled = ln.make_estimator(tmp_path / "model", estimator, out=tmp_path / "generated")
        errors[estimator] = ln.evaluate(compiled, test_run).mse(test_run.x)
        folder = f"my_pendulum_knode_{estimator}" + ("" if estimator == "ukf" else "_n20")  # N = 20
        again = ln.load_estimator(tmp_path / "generated" / folder)
        assert ln.evaluate(again, test_run).mse(test_run.x) == pytest.approx(errors[estimator], rel=1e-12)
    nominal = ln.evaluate(ln.make_estimator("nominal", "ukf", system=system, out=tmp_path / "generated"),
                          test_run).mse(test_run.x)
    assert errors["ukf"] < nominal, (errors, nominal)  # the learned damping helps
    assert errors["mhe_gn"] == pytest.approx(errors["mhe"], rel=1e-6)  # the same NLP
    result = diagnosis.diagnose(model.system, [test_run], model=model,
                                settings=diagnosis.DiagnosisSettings(estimators=()),
                                work_dir=tmp_path / "diag", progress=False)
    assert result.report


def test_an_edited_system_file_is_refused_in_one_line(work, tmp_path):
    """The model was trained on the file as it was: once edited, every step that would load it
    on the model's behalf refuses, naming the file and what to do; naming --system overrides."""
    import shutil

    model = tmp_path / "model"
    shutil.copytree(work / "model", model)
    edited = tmp_path / "my_pendulum.py"
    edited.write_text(USER_SYSTEM.replace('"c": 0.3', '"c": 0.4'))
    meta = json.loads((model / "model.json").read_text())
    meta["system_source"]["file"] = str(edited.resolve())  # the model now points at the edited copy
    (model / "model.json").write_text(json.dumps(meta))
    with pytest.raises(ModelMismatchError, match="changed since"):
        load_model(model)
    r = run([model, "--out", tmp_path / "generated", "--estimator", "ukf"], command=compile_cmd)
    assert r.exit_code == 1 and "changed since" in r.output and len(r.output.strip().splitlines()) == 1
    r = run(["estimate", "--data", work / "test.csv", "--estimator", "ukf", "--model", model,
             "--out", tmp_path / "est.csv"])
    assert r.exit_code == 1 and "changed since" in r.output, r.output
    edited.unlink()
    with pytest.raises(SystemFileError, match="no longer exists"):
        load_model(model)
    r = run(["estimate", "--data", work / "test.csv", "--estimator", "ukf", "--model", model,
             "--system", work / "my_pendulum.py", "--out", tmp_path / "est.csv"])
    assert r.exit_code == 0, r.output  # named explicitly: used as it is


def test_diagnose_says_which_states_it_compares_against(work):
    """The truth when every run has ``x_`` columns (``--source auto``), else the observer's
    estimates from the measurements; ``--source observer`` forces the latter."""
    from learnest_codegen.cli.diagnose import compared_against
    from learnest_codegen.data import Run
    from learnest_codegen.diagnosis import DiagnosisSettings

    system = ln.get_system(str(work / "my_pendulum.py"))
    full = ln.read_run(work / "test.csv", system)
    bare = Run(full.t, full.u, full.y, None, full.system)
    auto = DiagnosisSettings(source="auto")
    assert compared_against(system, [full], auto, "d.csv").startswith(
        "diagnose: comparing against the true states in d.csv (x_q, x_qdot)")
    for runs, settings in (([full, bare], auto), ([full], DiagnosisSettings(source="observer"))):
        line = compared_against(system, runs, settings, "d.csv")
        assert line == ("diagnose: comparing against the states the 'rts' observer estimates from the "
                        "measurements in d.csv (y_q)"), line
