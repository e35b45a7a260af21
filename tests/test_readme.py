"""The README's Python quick start runs as written, every link of the README and docs/ resolves,
and docs/ builds as a site (mkdocs, strict: a broken link or anchor fails)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
# The quick start trains for minutes on 10 s runs; the test keeps every line and shortens these.
FASTER = {
    "ln.simulate(system, seed=0)": "ln.simulate(system, seed=0, duration=0.6)",
    "ln.simulate(system, seed=1)": "ln.simulate(system, seed=1, duration=0.4)",
    "ln.train(train_run, system)": ("ln.train(train_run, system, ln.TrainingSettings(epochs=3, refine=0, "
                                    "validation_fraction=0), progress=False)"),
}


def quick_start() -> str:
    readme = (ROOT / "README.md").read_text()
    section = readme.split("## Quick start", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_quick_start_runs(tmp_path, monkeypatch, capsys):
    code = quick_start()
    for old, new in FASTER.items():
        assert old in code, f"the README's quick start no longer says {old!r}"
        code = code.replace(old, new)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, "README.md quick start", "exec"), namespace)  # noqa: S102
    printed = capsys.readouterr().out.splitlines()
    assert [line.split(":")[0] for line in printed] == ["UKF", "KNODE-UKF"]
    mses = [float(re.search(r"MSE (\S+),", line).group(1)) for line in printed]
    assert all(np.isfinite(mses))
    assert (tmp_path / "model" / "weights.pt").is_file()
    assert (tmp_path / "generated" / "cartpole_knode_ukf" / "manifest.json").is_file()
    # what the block printed is what the compiled estimator computes
    ln, test_run = namespace["ln"], namespace["test_run"]
    assert mses[1] == pytest.approx(ln.evaluate(namespace["knode"], test_run).mse(test_run.x), rel=1e-3)


def _links(path: Path):
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text()):
        if not re.match(r"[a-z]+:", target):
            yield target


@pytest.mark.parametrize("page", ["README.md", *sorted(p.relative_to(ROOT).as_posix()
                                                       for p in (ROOT / "docs").glob("*.md"))])
def test_links_resolve(page):
    path = ROOT / page
    missing = [t for t in _links(path) if not (path.parent / t).exists()]
    assert not missing, f"{page} links to missing files: {missing}"


def test_docs_site_builds_strictly(tmp_path):
    if shutil.which("mkdocs") is None and not (Path(sys.executable).parent / "mkdocs").exists():
        pytest.skip("mkdocs is not installed (pip install -e .[test])")
    mkdocs = shutil.which("mkdocs") or str(Path(sys.executable).parent / "mkdocs")
    result = subprocess.run([mkdocs, "build", "--strict", "--site-dir", str(tmp_path / "site")],
                            cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-3000:]
    assert (tmp_path / "site" / "results" / "index.html").is_file()
