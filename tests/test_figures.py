"""Every figure the README and docs quote is rendered from its benchmark's JSON
(docs/figures/, written by ``python scripts/bench.py``), and says what it measured and how."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
sys.path.insert(0, str(SCRIPTS))
import figures  # noqa: E402
import render_docs  # noqa: E402

JSONS = sorted(figures.FIGURES.glob("*.json"))


def test_every_quoted_figure_equals_its_json():
    changed, missing = render_docs.stale_pages()
    assert missing == [], "a page quotes a benchmark whose JSON is missing: run it"
    stale = [str(page.relative_to(figures.ROOT)) for page, _ in changed]
    assert stale == [], "run python scripts/render_docs.py (or the benchmark that changed)"


@pytest.mark.parametrize("path", JSONS, ids=[p.stem for p in JSONS])
def test_every_figure_file_names_its_model_run_and_conditions(path):
    data = json.loads(path.read_text())
    assert data["schema"] == figures.SCHEMA and data["name"] == path.stem
    assert data["command"].startswith(f"python scripts/bench.py {path.stem}")
    cond = data["conditions"]
    for key in ("model", "run", "commit", "date", "machine", "versions"):
        assert cond.get(key), f"{path.name}: conditions.{key} missing"
    assert {"cpu", "cores", "load_1min", "load_1min_at_end"} <= set(cond["machine"])
    assert (SCRIPTS / f"bench_{path.stem}.py").exists(), "a figure file without its benchmark"


DEMO_MODEL_BENCHES = ("callgrind", "cortex_m", "streams")  # they measure build/bench/demo/model


@pytest.mark.parametrize("name", DEMO_MODEL_BENCHES)
def test_figures_of_the_demos_model_measured_the_model_the_demo_quotes(name):
    """The instruction counts, M4F figures and streams are of the model whose accuracy the demo's
    table gives: the same hash of its weights and settings (a model left in build/ by an older
    checkout is not)."""
    demo = json.loads((figures.FIGURES / "demo.json").read_text())["conditions"]
    assert demo.get("model_hash"), "demo.json records no model hash: run python scripts/bench.py demo"
    cond = json.loads((figures.FIGURES / f"{name}.json").read_text())["conditions"]
    assert cond.get("model_hash") == demo["model_hash"], (
        f"{name}.json measured another model than demo.json's: run python scripts/bench.py {name}")


def test_every_page_block_names_an_existing_view():
    for page in figures.PAGES:
        for m in figures.BLOCK.finditer(page.read_text()):
            bench, view = m.group("name").split(".", 1)
            module = figures.bench_module(bench)
            assert hasattr(module, f"render_{view}"), f"{page.name}: {m.group('name')}"


def test_a_changed_figure_is_caught(tmp_path, monkeypatch):
    """The check is not vacuous: a page quoting a value that differs from the JSON is stale."""
    (tmp_path / "figures").mkdir()
    (tmp_path / "figures" / "toy.json").write_text(json.dumps({"figures": {"x": 2.5}}))
    monkeypatch.setattr(figures, "FIGURES", tmp_path / "figures")
    page = "MSE <!-- value: toy figures.x .2f -->2.40<!-- /value --> here"
    assert figures.render_page(page) == "MSE <!-- value: toy figures.x .2f -->2.50<!-- /value --> here"


def test_an_option_no_named_benchmark_has_is_refused_before_any_work(capsys, monkeypatch):
    import bench

    monkeypatch.setattr(bench.figures, "write", lambda *a, **k: pytest.fail("a benchmark ran"))
    assert bench.main(["demo", "training", "--variants", "x"]) == 2
    assert "--variants: not an option of demo, training" in capsys.readouterr().err
    assert bench.main(["nonesuch"]) == 2
