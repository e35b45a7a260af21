"""The table of estimators (``compilation.ESTIMATORS``) is the only list: an entry added to it
reaches every face (the CLI's choices, the pipeline, the compiled folder's manifest, the docs'
table, the Crazyflie target, the studies' labels, the diagnosis summary, the benchmarks, the
fuzzer and the Cortex-M example), and every entry has each part an estimator needs.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import learnest_codegen as ln
from learnest_codegen import compilation
from learnest_codegen.cli import cli, compile_cmd
from learnest_codegen.codegen.templates import KIT
from learnest_codegen.runtime.base import CompiledEstimator
from learnest_codegen.runtime.ekf import CompiledEKF
from learnest_codegen.runtime.manifest import read_manifest

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = ROOT / "scripts"
PAGE = ROOT / "docs" / "guide" / "python_api.md"
BLOCK = re.compile(r"<!-- estimators -->\n(.*?)\n<!-- /estimators -->", re.S)


class CompiledDummy(CompiledEKF):
    """A binding for the test's entry: the EKF's, loading folders named ``dummy``."""

    ESTIMATORS = ("dummy",)


@pytest.fixture
def dummy(monkeypatch):
    """A new table entry: the EKF's parts under the name ``dummy``, with its own binding."""
    entry = dataclasses.replace(compilation.ESTIMATORS["ekf"], name="dummy",
                                summary="a test entry", compiled=CompiledDummy, label="DUMMY")
    monkeypatch.setitem(compilation.ESTIMATORS, "dummy", entry)
    return entry


def test_an_added_entry_reaches_every_face(dummy, tmp_path, cartpole):
    assert "dummy" in compilation.ESTIMATOR_NAMES
    assert "dummy" not in compilation.MHE_NAMES and "dummy" not in compilation.DEFAULT_ESTIMATORS
    # the CLI: learnest-compile and learnest compile/estimate/evaluate offer it and build it
    for command in (cli.commands["compile"], cli.commands["estimate"],
                    cli.commands["evaluate"]):
        assert "dummy" in CliRunner().invoke(command, ["--help"]).output
    r = CliRunner().invoke(compile_cmd, ["--nominal", "--estimator", "dummy", "--out",
                                                str(tmp_path / "cli")], catch_exceptions=False)
    assert r.exit_code == 0, r.output
    folder = tmp_path / "cli" / "cartpole_nominal_dummy"
    # the manifest names it, and the pipeline loads it with its binding
    assert read_manifest(folder)["estimator"] == "dummy"
    assert isinstance(ln.load_estimator(folder), CompiledDummy)
    est = ln.make_estimator("nominal", "dummy", system=cartpole, out=tmp_path / "py",
                            precision="float32")
    assert isinstance(est, CompiledDummy) and est.manifest["prefix"] == "cartpole_nominal_dummy_float32"
    run = ln.simulate(cartpole, seed=2, duration=0.2)
    ref = ln.make_estimator("nominal", "dummy", backend="python", system=cartpole)
    X_r = ref.run(run.u, run.y, cartpole.x0)
    assert np.abs(est.run(run.u, run.y, cartpole.x0) - X_r).max() < 2e-3 * np.abs(X_r).max()
    # the docs' table
    assert "| `dummy` | a test entry |" in compilation.estimator_table()


def _load(path: Path):
    """A script or example as a module (its folder on the path, as when it runs)."""
    sys.path.insert(0, str(path.parent))
    try:
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[path.stem] = module  # dataclasses look their module up there
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(path.parent))


def test_an_added_entry_reaches_the_targets_studies_benchmarks_and_fuzzer(dummy, monkeypatch):
    from learnest_codegen.diagnosis.findings import summary
    from learnest_codegen.experiments.quadrotor import methods, pairs

    # the Crazyflie target runs what the table marks, and nothing else
    with pytest.raises(ln.errors.SettingsError, match="dummy"):
        compilation.check_crazyflie("dummy")
    monkeypatch.setitem(compilation.ESTIMATORS, "dummy", dataclasses.replace(dummy, crazyflie=True))
    compilation.check_crazyflie("dummy")
    assert "dummy" in compilation.CRAZYFLIE_NAMES and compilation.crazyflie_default() == "ukf"
    # the flights study's labels, the diagnosis summary
    assert ("DUMMY", "dummy", "nominal") in methods(["dummy"])
    assert pairs(["dummy"]) == [("KNODE-DUMMY", "DUMMY")]
    report = {"system": "s", "verdict": "v", "heldout_gap_closed": None, "explained_in_sample": 0.5,
              "source": "x", "verdict_reason": "r", "basis": "b", "where": [],
              "shrink": {"one_step": {"before": 1.0, "after": 0.5},
                         "dummy": {"before": 2.0, "after": 1.0, "verdict": "smaller"}}}
    assert "DUMMY held-out MSE 2 -> 1: smaller" in summary(report)
    # the benchmarks, the fuzzer and the Cortex-M example
    for name in ("bench_outlier_recovery", "bench_streams"):
        assert _load(SCRIPTS / f"{name}.py").estimator_backends()["dummy"] == ("c",), name
    assert ("dummy", "float32") in _load(SCRIPTS / "bench_reliability.py").build_pairs()
    assert ("dummy", None) in _load(SCRIPTS / "bench_callgrind.py").plan()
    assert "dummy" in _load(SCRIPTS / "bench_cost_curves.py").estimators()
    fuzz = _load(SCRIPTS / "fuzz_c_api.py")
    assert "dummy" in fuzz.table_estimators() and fuzz.api("dummy") == fuzz.api("ekf")
    assert "dummy" in _load(ROOT / "examples" / "cortex_m" / "build_and_compare.py").ESTIMATORS


def test_an_unknown_name_is_refused_with_the_table_as_remedy(dummy):
    with pytest.raises(ln.errors.UnknownNameError, match="dummy"):
        compilation.estimator_kind("nope")
    r = CliRunner().invoke(compile_cmd, ["--nominal", "--estimator", "nope"])
    assert r.exit_code == 2 and "dummy" in r.output


def test_every_entry_has_its_parts():
    """Each estimator: a kit header, a generator that exists, a binding that loads its name, a
    settings type its defaults make, and a reference in the table."""
    model = ln.resolve("nominal", "cartpole").model
    for name, kind in compilation.ESTIMATORS.items():
        assert (KIT / kind.kit).is_file(), name
        module, function = kind.generator.split(":")
        assert callable(getattr(__import__(f"learnest_codegen.codegen.{module}",
                                           fromlist=[function]), function)), name
        assert issubclass(kind.compiled, CompiledEstimator) and name in kind.compiled.ESTIMATORS
        assert isinstance(kind.default_settings(model), kind.settings), name
        assert kind.reference is not None and kind.reference[0] in compilation.ESTIMATORS
        assert kind.python is not None or kind.reference[0] != name


def test_the_docs_table_is_the_table():
    """docs/guide/python_api.md shows the table as ``compilation.estimator_table()`` renders
    it (paste its output between the page's ``<!-- estimators -->`` markers)."""
    match = BLOCK.search(PAGE.read_text())
    assert match is not None and match.group(1) == compilation.estimator_table()
