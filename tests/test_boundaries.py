"""Trust boundaries of the command line and the run files: the time base, outputs that never
destroy inputs, damaged model folders, and one-line errors for everything a user can cause."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from learnest_codegen.cli import cli
from learnest_codegen.data import Run, check_sampling, read_run, resample, write_run
from learnest_codegen.errors import DataError, OutputError
from learnest_codegen.outputs import atomic_dir, atomic_file, claim_output
from learnest_codegen.recordings import data_root
from learnest_codegen.simulation import simulate
from learnest_codegen.systems import get_system


def run_cli(*args):
    """Exit code and output (white space folded); an exception escaping the command fails."""
    result = CliRunner().invoke(cli, [str(a) for a in args])
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        raise AssertionError(f"uncaught {result.exception!r}") from result.exception
    return result.exit_code, " ".join(result.output.split())


def assert_one_line_error(code, output, *needles):
    assert code == 1, output
    assert "Traceback" not in output and output.startswith("Error:"), output
    for needle in needles:
        assert needle in output, (needle, output)


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    """A 0.4 s cartpole run CSV (200 samples at the system's 2 ms)."""
    path = tmp_path_factory.mktemp("boundaries") / "run.csv"
    system = get_system("cartpole")
    write_run(simulate(system, seed=4, duration=0.4), system, path)
    return path


# --- time base ------------------------------------------------------------------------------------


def _linear_run(t: np.ndarray) -> Run:
    u = (t > 0.0105).astype(float)[:, None]  # a step between samples: held, it stays a step
    y = np.column_stack([2 * t + 1, -t])
    return Run(t, u, y, np.column_stack([t, t, t, t]), "cartpole")


def test_resample_is_exact_on_linear_signals_and_holds_the_input():
    run = _linear_run(np.arange(0, 0.1 + 1e-12, 0.001))
    out = resample(run, 0.002)
    np.testing.assert_allclose(out.t, np.arange(51) * 0.002, atol=1e-15)
    np.testing.assert_allclose(out.y, np.column_stack([2 * out.t + 1, -out.t]), atol=1e-12)
    # u[k] applies from t[k] to t[k+1]: at 0.010 s the input is still 0, from 0.012 s on it is 1
    np.testing.assert_array_equal(out.u[:, 0], (out.t > 0.0105).astype(float))
    check_sampling(out, 0.002, "resampled")  # passes


def test_check_sampling_tells_rate_and_gap_apart():
    system = get_system("cartpole")
    t = np.arange(100) * 0.002 + 1e-5 * np.sin(np.arange(100))  # 0.5 % jitter passes
    check_sampling(_linear_run(t), system.dt, "jittered")
    with pytest.raises(DataError, match="sampled every 0.01 s.*steps every 0.002 s.*--resample"):
        check_sampling(_linear_run(np.arange(100) * 0.01), system.dt, "slow run")
    t_gap = np.concatenate([np.arange(50) * 0.002, 0.2 + np.arange(50) * 0.002])
    with pytest.raises(DataError, match="sample 49.*a gap"):
        check_sampling(_linear_run(t_gap), system.dt, "gappy run")


def test_commands_refuse_a_run_at_another_rate_unless_asked(short_run, tmp_path):
    """Finding 3: a 0.01 s run was estimated (MSE 125) and trained on silently."""
    system = get_system("cartpole")
    run = read_run(short_run, system)
    slow = tmp_path / "slow.csv"
    write_run(Run(run.t * 5, run.u, run.y, run.x, run.system), system, slow)
    code, out = run_cli("train", "--data", slow, "--out", tmp_path / "model", "--epochs", 1)
    assert_one_line_error(code, out, "sampled every 0.01 s", "0.002 s")
    assert not (tmp_path / "model").exists()
    code, out = run_cli("estimate", "--data", slow, "--estimator", "ukf", "--backend", "python",
                        "--out", tmp_path / "est.csv")
    assert_one_line_error(code, out, "sampled every 0.01 s")
    code, out = run_cli("estimate", "--data", slow, "--estimator", "ukf", "--backend", "python",
                        "--resample", "--out", tmp_path / "est.csv")
    assert code == 0, out
    est = np.loadtxt(tmp_path / "est.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(np.diff(est[:, 0]), system.dt, rtol=1e-9)


# --- outputs --------------------------------------------------------------------------------------


def test_out_never_replaces_the_input_or_earlier_results(short_run, tmp_path):
    """Finding 5: --out overwrote the command's own --data and existing models."""
    before = short_run.read_bytes()
    code, out = run_cli("estimate", "--data", short_run, "--estimator", "ukf", "--backend", "python",
                        "--out", short_run)
    assert_one_line_error(code, out, "refusing to write", "input")
    code, out = run_cli("estimate", "--data", short_run, "--estimator", "ukf", "--backend", "python",
                        "--out", short_run, "--force")
    assert_one_line_error(code, out, "refusing to write")
    assert short_run.read_bytes() == before

    existing = tmp_path / "existing.csv"
    existing.write_text("keep me\n")
    code, out = run_cli("simulate", "--duration", 0.1, "--out", existing)
    assert_one_line_error(code, out, "exists", "--force")
    assert existing.read_text() == "keep me\n"
    assert run_cli("simulate", "--duration", 0.1, "--out", existing, "--force")[0] == 0
    assert existing.read_text().startswith("t,u_F")

    model = tmp_path / "model"
    model.mkdir()
    (model / "weights.pt").write_bytes(b"earlier weights")
    code, out = run_cli("train", "--data", short_run, "--out", model, "--epochs", 1)
    assert_one_line_error(code, out, "not empty", "--force")
    assert (model / "weights.pt").read_bytes() == b"earlier weights"
    code, out = run_cli("train", "--data", short_run, "--out", short_run.parent, "--epochs", 1, "--force")
    assert_one_line_error(code, out, "holds the input")


def test_atomic_writes_leave_the_old_content_on_failure(tmp_path):
    target = tmp_path / "result.csv"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_file(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("disk full")
    assert target.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["result.csv"]
    folder = tmp_path / "model"
    folder.mkdir()
    (folder / "a").write_text("old")
    with pytest.raises(KeyboardInterrupt), atomic_dir(folder) as tmp:
        (tmp / "a").write_text("new")
        raise KeyboardInterrupt
    assert (folder / "a").read_text() == "old"
    with atomic_dir(folder) as tmp:
        (tmp / "b").write_text("new")
        # CasADi will not write "<name>.c" under a path holding "<name>.c": never "<name>." here
        assert f"{folder.name}." not in tmp.name and tmp.name.startswith(f".{folder.name}-")
    assert sorted(p.name for p in folder.iterdir()) == ["b"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["model", "result.csv"]


def test_claim_output_rejects_unwritable_places(tmp_path):
    with pytest.raises(OutputError, match="cannot create the folder"):
        claim_output("/dev/null/x.csv")
    (tmp_path / "d").mkdir()
    with pytest.raises(OutputError, match="is a folder"):
        claim_output(tmp_path / "d")


# --- damaged inputs and settings: one line, exit 1 -------------------------------------------------


def test_damaged_model_folders_and_bad_settings_are_one_line(short_run, tmp_path):
    """Finding 6: these printed tracebacks."""
    model = tmp_path / "model"
    code, out = run_cli("train", "--data", short_run, "--out", model, "--epochs", 2,
                        "--refine", 0, "--validation-fraction", 0)
    assert code == 0, out
    good_meta, good_weights = (model / "model.json").read_text(), (model / "weights.pt").read_bytes()

    (model / "model.json").write_text(good_meta[: len(good_meta) // 2])
    code, out = run_cli("estimate", "--data", short_run, "--estimator", "ukf", "--model", model,
                        "--backend", "python", "--out", tmp_path / "e1.csv")
    assert_one_line_error(code, out, "model.json is not valid JSON")

    (model / "model.json").write_text(good_meta)
    (model / "weights.pt").write_bytes(good_weights[: len(good_weights) // 2])
    code, out = run_cli("estimate", "--data", short_run, "--estimator", "ukf", "--model", model,
                        "--backend", "python", "--out", tmp_path / "e2.csv")
    assert_one_line_error(code, out, "weights.pt cannot be read")

    code, out = run_cli("train", "--data", short_run, "--out", tmp_path / "m2", "--validation-fraction", 0.95)
    assert_one_line_error(code, out, "validation_fraction")
    code, out = run_cli("simulate", "--duration", 0.1, "--out", "/dev/null/run.csv")
    assert_one_line_error(code, out, "/dev/null")


def test_absurd_measurement_on_the_python_backend_is_one_line(short_run, tmp_path):
    table = np.loadtxt(short_run, delimiter=",", skiprows=1)
    header = short_run.read_text().splitlines()[0]
    table[100, header.split(",").index("y_p")] = 1e300
    bad = tmp_path / "absurd.csv"
    np.savetxt(bad, table, delimiter=",", header=header, comments="", fmt="%.17g")
    code, out = run_cli("estimate", "--data", bad, "--estimator", "ukf", "--backend", "python",
                        "--out", tmp_path / "e.csv")
    if code:  # the UKF's numerics refuse the sample; with innovation gating it is rejected instead
        assert_one_line_error(code, out)


# --- studies ----------------------------------------------------------------------------------------


def test_one_bad_flight_is_skipped_and_listed(tmp_path):
    """Finding 8: a flight that never leaves the ground stopped the whole quadrotor study."""
    from learnest_codegen.experiments import quadrotor as fs
    from learnest_codegen.recordings.crazyflie import list_flights

    root = data_root(None)
    if root is None or not (root / "nanobench").is_dir():
        pytest.skip("NanoBench recordings not found (../shared/data/nanobench or $LEARNEST_DATA)")
    flights = list_flights(root / "nanobench")[:2]
    folder = tmp_path / "nanobench"
    folder.mkdir()
    for f in flights:
        shutil.copy(f, folder / f.name)
        meta = f.with_name(f.stem + "_metadata.yaml")
        if meta.exists():
            shutil.copy(meta, folder / meta.name)
    grounded = folder / "grounded_2s.csv"
    lines = flights[0].read_text().splitlines()
    grounded.write_text("\n".join(lines[:201]) + "\n")  # the first 2 s: motors off, on the ground

    with pytest.raises(DataError, match="grounded_2s"):
        fs.flight_cases(folder)
    skipped: dict[str, str] = {}
    cases = fs.flight_cases(folder, skipped=skipped)
    assert sorted(c.name for c in cases) == sorted(f.stem for f in flights)
    assert list(skipped) == ["grounded_2s"] and "airborne" in skipped["grounded_2s"]
    json.dumps(skipped)  # goes into quadrotor.json as it is


# --- compiled libraries ---------------------------------------------------------------------------


def test_a_truncated_or_altered_library_is_refused_before_it_is_opened(tmp_path):
    """Finding 1: a library cut short killed the process inside dlopen (SIGBUS, no message).

    The loading runs in a child process, so a regression crashes the child, not the test run.
    """
    import subprocess
    import sys

    from learnest_codegen.compilation import compile_estimators
    from learnest_codegen.pipeline import resolve

    # built but not loaded here: rewriting a library this process has mapped would crash it
    compile_estimators(resolve("nominal", "cartpole").model, tmp_path, model_hash="nominal",
                       estimators=("ukf",))
    folder = tmp_path / "cartpole_nominal_ukf"
    library = next(folder.glob("lib*.so"))
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["library_bytes"] == library.stat().st_size and len(manifest["library_sha256"]) == 64
    load = ("import sys; from learnest_codegen.pipeline import load_estimator\n"
            "try:\n    load_estimator(sys.argv[1])\nexcept Exception as e:\n"
            "    print(type(e).__name__, e); sys.exit(3)\nprint('loaded')")
    good = library.read_bytes()
    for damaged in (good[: len(good) // 3], good[:-1] + bytes([good[-1] ^ 1])):
        library.write_bytes(damaged)
        child = subprocess.run([sys.executable, "-c", load, str(folder)], capture_output=True, text=True,
                               timeout=120)
        assert child.returncode == 3, (child.returncode, child.stdout, child.stderr)
        assert "ModelMismatchError" in child.stdout and "recompile" in child.stdout
    library.write_bytes(good)
    child = subprocess.run([sys.executable, "-c", load, str(folder)], capture_output=True, text=True,
                           timeout=120)
    assert child.stdout.strip() == "loaded", child.stderr


def test_another_system_of_the_same_name_is_refused(tmp_path, short_run):
    """Finding 4: a user's `cartpole` with another pole length passed the manifest check."""
    import dataclasses

    from learnest_codegen.errors import ModelMismatchError
    from learnest_codegen.pipeline import expected_manifest, load_estimator, make_estimator

    cartpole = get_system("cartpole")
    longer = dataclasses.replace(cartpole, params={**cartpole.params, "l": 0.6})
    assert longer.name == cartpole.name and longer.fingerprint() != cartpole.fingerprint()
    make_estimator("nominal", "ukf", system=longer, out=tmp_path)
    folder = tmp_path / "cartpole_nominal_ukf"
    with pytest.raises(ModelMismatchError, match="system_fingerprint: library has"):
        load_estimator(folder, expect=expected_manifest("nominal", cartpole))
    load_estimator(folder, expect=expected_manifest("nominal", longer))  # its own system loads
    code, out = run_cli("estimate", "--system", "cartpole", "--data", short_run, "--estimator", "ukf",
                        "--compiled", folder, "--out", tmp_path / "est.csv")
    assert_one_line_error(code, out, "system_fingerprint")


# --- special files, folders of compiled estimators, re-compiles (issue 28) ---------------------------


def test_force_replaces_only_regular_files_and_folders(tmp_path):
    """As root, `--out /dev/full --force` turned the device into a 487 kB regular file."""
    import os
    import socket
    import stat

    made = {"fifo": lambda p: os.mkfifo(p),
            "socket": lambda p: socket.socket(socket.AF_UNIX).bind(str(p)),
            "link": lambda p: os.symlink(tmp_path / "target.csv", p)}
    if os.geteuid() == 0:  # a copy of /dev/full, made where it harms nothing
        made["device"] = lambda p: os.mknod(p, 0o666 | stat.S_IFCHR, os.makedev(1, 7))
    for name, make in made.items():
        target = tmp_path / name
        make(target)
        before = os.lstat(target).st_mode
        for force in (False, True):
            with pytest.raises(OutputError, match="not a regular file or folder"):
                claim_output(target, force=force)
            with pytest.raises(OutputError, match="not a regular file or folder"):
                claim_output(target, force=force, kind="dir")
        code, out = run_cli("simulate", "--duration", 0.1, "--out", target, "--force")
        assert_one_line_error(code, out, "refusing to write")
        assert os.lstat(target).st_mode == before, name


def _nominal_ukf(out):
    from learnest_codegen.compilation import compile_estimators
    from learnest_codegen.pipeline import resolve

    return compile_estimators(resolve("nominal", "cartpole").model, out, model_hash="nominal",
                              estimators=("ukf",))["ukf"]


def test_learnest_compile_needs_force_to_replace_a_folder(tmp_path):
    """The README's promise now holds for learnest-compile too: a hand edit is not written over
    unasked; with --force the folder is replaced whole (an unchanged library is reused)."""
    from learnest_codegen.cli import compile_cmd

    args = ["--nominal", "--estimator", "ukf", "--out", str(tmp_path)]
    assert CliRunner().invoke(compile_cmd, args).exit_code == 0
    folder = tmp_path / "cartpole_nominal_ukf"
    (folder / "notes.txt").write_text("my notes")
    result = CliRunner().invoke(compile_cmd, args)
    assert result.exit_code == 1 and "exists and is not empty; pass --force" in result.output
    assert (folder / "notes.txt").read_text() == "my notes"
    result = CliRunner().invoke(compile_cmd, [*args, "--force"])
    assert result.exit_code == 0 and "reused" in result.output, result.output
    assert not (folder / "notes.txt").exists() and (folder / "manifest.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cartpole_nominal_ukf"]


def test_an_interrupted_compile_leaves_the_folder_as_it_was(tmp_path, monkeypatch):
    """Ctrl-C while an estimator's folder is written: no empty or partial folder, no temporary
    one, and an existing folder unchanged."""
    import dataclasses

    from learnest_codegen import compilation

    real = compilation.ESTIMATORS["ukf"]

    class Interrupted(compilation.EstimatorKind):
        def generate(self, model, settings, directory, **kw):
            (directory / "half.c").write_text("/* half */")
            raise KeyboardInterrupt

    interrupted = Interrupted(**{f.name: getattr(real, f.name) for f in dataclasses.fields(real)})
    monkeypatch.setitem(compilation.ESTIMATORS, "ukf", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _nominal_ukf(tmp_path / "new")
    assert list((tmp_path / "new").iterdir()) == []
    monkeypatch.setitem(compilation.ESTIMATORS, "ukf", real)
    _nominal_ukf(tmp_path / "old")
    before = {p.name: p.read_bytes() for p in (tmp_path / "old" / "cartpole_nominal_ukf").iterdir()}
    monkeypatch.setitem(compilation.ESTIMATORS, "ukf", interrupted)
    with pytest.raises(KeyboardInterrupt):
        _nominal_ukf(tmp_path / "old")
    after = {p.name: p.read_bytes() for p in (tmp_path / "old" / "cartpole_nominal_ukf").iterdir()}
    assert after == before and [p.name for p in (tmp_path / "old").iterdir()] == ["cartpole_nominal_ukf"]


def _load_in_child(folder):
    """Load the folder and run it in a child process: (exit code, output). A crash stays there."""
    import subprocess
    import sys

    code = ("import sys, numpy as np; from learnest_codegen.pipeline import load_estimator\n"
            "e = load_estimator(sys.argv[1]); e.reset(np.array([0, 0, 0.3, 0.0]))\n"
            "print(repr(e.step(np.zeros(1), np.array([0.01, 0.31])).tolist()))")
    child = subprocess.run([sys.executable, "-c", code, str(folder)], capture_output=True, text=True,
                           timeout=120)
    return child.returncode, child.stdout.strip() or child.stderr.strip()[-300:]


def test_a_recompile_rebuilds_a_damaged_or_foreign_library(tmp_path):
    """Issue 28: after a library was cut short, the same compile "reused" it and blessed it in a
    new manifest (the next load died of SIGBUS); a library swapped for another build of the same
    prefix was blessed and ran the wrong model. The stamp now records what was built."""
    import dataclasses

    from learnest_codegen.compilation import compile_estimators
    from learnest_codegen.export import prior_model

    first = _nominal_ukf(tmp_path / "a")
    folder, library = first.directory, first.library_path
    good = library.read_bytes()
    code, expected = _load_in_child(folder)
    assert code == 0, expected

    library.write_bytes(good[: len(good) // 3])  # cut short
    again = _nominal_ukf(tmp_path / "a")
    assert not again.reused and library.read_bytes() == good
    assert _load_in_child(folder) == (0, expected)

    cartpole = get_system("cartpole")
    longer = dataclasses.replace(cartpole, params={**cartpole.params, "l": 0.6})
    other = compile_estimators(prior_model(longer), tmp_path / "b", model_hash="nominal",
                               estimators=("ukf",))["ukf"]
    assert other.prefix == first.prefix and other.library_path.read_bytes() != good
    library.write_bytes(other.library_path.read_bytes())  # the same prefix, another model
    again = _nominal_ukf(tmp_path / "a")
    assert not again.reused and library.read_bytes() == good
    assert _load_in_child(folder) == (0, expected)
    assert _nominal_ukf(tmp_path / "a").reused  # and an intact one is still reused


def test_no_manifest_is_written_for_a_library_that_was_not_built(tmp_path):
    from learnest_codegen.errors import ModelMismatchError
    from learnest_codegen.runtime.manifest import write_manifest

    result = _nominal_ukf(tmp_path)
    folder = result.directory
    content = json.loads((folder / "manifest.json").read_text())
    content = {k: v for k, v in content.items() if k not in ("library_bytes", "library_sha256")}
    write_manifest(folder, content)  # the built library: fine
    good = result.library_path.read_bytes()
    result.library_path.write_bytes(good[:-1] + bytes([good[-1] ^ 1]))
    with pytest.raises(ModelMismatchError, match="not the library the toolchain built"):
        write_manifest(folder, content)
    (folder / (result.library + ".stamp")).unlink()
    with pytest.raises(ModelMismatchError, match="no build stamp"):
        write_manifest(folder, content)


def test_an_edited_precision_is_named(tmp_path):
    """It said "library sizes (4, 1, 2, 20), manifest says (4, 1, 2, 20)"."""
    from learnest_codegen.compilation import compile_estimators
    from learnest_codegen.errors import ModelMismatchError
    from learnest_codegen.pipeline import load_estimator, resolve

    compile_estimators(resolve("nominal", "cartpole").model, tmp_path, model_hash="nominal",
                       estimators=("ukf", "mhe_rti"))
    for name in ("cartpole_nominal_ukf", "cartpole_nominal_mhe_rti_n20"):
        path = tmp_path / name / "manifest.json"
        manifest = json.loads(path.read_text())
        path.write_text(json.dumps({**manifest, "precision": "float32"}))
        with pytest.raises(ModelMismatchError, match="computes in float64, the manifest says "
                                                     "precision 'float32'"):
            load_estimator(tmp_path / name)
        path.write_text(json.dumps({**manifest, "precision": "float16"}))
        with pytest.raises(ModelMismatchError, match="precision 'float16' is not one of"):
            load_estimator(tmp_path / name)


@pytest.mark.parametrize("bad", [[None, 0.3], ["0.1", 0.3], [0.1 + 2j, 0.3]])
def test_a_sample_that_is_not_real_numbers_is_refused(bad):
    """None would have become NaN (a missing output) and "0.1" a number without a word."""
    from learnest_codegen.errors import DataError
    from learnest_codegen.estimators.validation import measurements

    with pytest.raises(DataError, match="expected real numbers"):
        measurements("UKF.step: y", bad, None, 2)
    y, mask = measurements("UKF.step: y", [np.nan, 0.3], None, 2)
    assert mask.tolist() == [False, True] and y.tolist() == [0.0, 0.3]
