"""Every code block of README.md and docs/**/*.md runs as written; every link resolves; the docs
site (with its API reference) builds strictly, and its nav lists every page.

How a block runs, by its fence's language:

* ``python``: executed; a block whose first line is ``# <name>.py`` is a file the page asks the
  reader to write: it is written under that name (every later block of the page sees it) and
  loaded as a system file when it defines ``SYSTEM``.
* ``bash``: each line is a ``learnest`` or ``learnest-compile`` command (comments and ``\\``
  continuations as in a shell), run in-process; any other command needs the ``shell`` marker.
* ``c``: compiled (not run) against the generated estimators its ``#include "<prefix>.h"``
  lines name (``<system>_<nominal|true|knode>_<estimator>``, ``_n<N>`` for an MHE of horizon N;
  knode: the model in tests/data).
* ``json``: parsed. ``text``, ``console`` and ``csv`` are listings, not code.

Every block runs in a fresh folder holding the page's files so far. An HTML comment on the line
before a fence changes that: ``<!-- test: skip REASON -->`` (not run; the reason is required
and shown; a block after ``<!-- file: NAME -->`` is a file of the firmware page, which
tests/test_handoff.py writes, builds and runs as a whole), ``<!-- test: slow -->`` (only with
``-m slow``), ``<!-- test: shell -->`` (a bash block run by bash in that folder) and
``<!-- test: continue -->`` (run in the previous block's folder, with what it wrote). A block
in another language, or a bash line that is not a command of the package, fails the test until
it is given a language or a marker.

To keep the default suite short, the built-in systems are registered with 1 s runs while the
blocks run (in-process, so the commands see it): every other argument is the reader's.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = ["README.md", *sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").rglob("*.md"))]
MARKER = re.compile(r"<!--\s*test:\s*(.*?)\s*-->")
#: A block written as a file of the firmware page (tests/test_handoff.py follows that page).
HANDOFF_FILE = re.compile(r"<!--\s*file:\s*(\S+)\s*-->")
FENCE = re.compile(r"^(\s*)```(\S*)\s*$")
LISTINGS = {"text", "console", "csv", "output"}
SHORT_RUNS_S = 1.0  # duration of every built-in system's runs while the blocks run


@dataclass
class Block:
    page: str
    line: int  # 1-based line of the opening fence
    language: str
    code: str
    markers: dict[str, str] = field(default_factory=dict)

    @property
    def id(self) -> str:
        return f"{self.page}:{self.line}"

    @property
    def file_name(self) -> str | None:
        """``name.py`` when the block is a file to write (first line ``# name.py``)."""
        first = self.code.lstrip().splitlines()[0] if self.code.strip() else ""
        m = re.fullmatch(r"#\s*([\w./-]+\.py)\s*", first)
        return m.group(1) if self.language == "python" and m else None


def blocks(page: str) -> list[Block]:
    """The fenced blocks of a page, with the markers of the comment line just before each."""
    lines = (ROOT / page).read_text().splitlines()
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, language, start = m.group(1), m.group(2).lower(), i
        body = []
        i += 1
        while i < len(lines) and not re.match(rf"^{re.escape(indent)}```\s*$", lines[i]):
            body.append(lines[i][len(indent):] if lines[i].startswith(indent) else lines[i])
            i += 1
        markers: dict[str, str] = {}
        j = start - 1
        while j >= 0 and not lines[j].strip():
            j -= 1
        if j >= 0 and (mm := MARKER.search(lines[j])):
            words = mm.group(1).split(None, 1)
            if words and words[0] == "skip":
                markers["skip"] = words[1] if len(words) > 1 else ""
            else:
                markers.update(dict.fromkeys(mm.group(1).split(), ""))
        elif j >= 0 and (mm := HANDOFF_FILE.search(lines[j])):
            markers["handoff"] = mm.group(1)
        out.append(Block(page, start + 1, language, "\n".join(body) + "\n", markers))
        i += 1
    return out


ALL_BLOCKS = [b for page in PAGES for b in blocks(page)]


def _param(block: Block):
    marks = [pytest.mark.slow] if "slow" in block.markers else []
    return pytest.param(block, id=block.id, marks=marks)


def commands(code: str) -> list[list[str]]:
    """The shell lines of a bash block as argument lists (comments and continuations removed)."""
    joined = re.sub(r"\\\n", " ", code)
    return [args for line in joined.splitlines() if (args := shlex.split(line, comments=True))]


# -- the environment the blocks run in --------------------------------------------------------------


@pytest.fixture(scope="module")
def short_systems():
    """The built-in systems with short runs, registered for the duration of the module."""
    from learnest_codegen.systems import SYSTEMS

    saved = dict(SYSTEMS)
    for name, system in saved.items():
        SYSTEMS[name] = dataclasses.replace(system, duration=max(SHORT_RUNS_S, 5 * system.dt))
    yield
    SYSTEMS.clear()
    SYSTEMS.update(saved)


@pytest.fixture(scope="module")
def page_state(tmp_path_factory):
    """Per page: the files it asked the reader to write, and the folder of its last block."""
    return {"root": tmp_path_factory.mktemp("docs"), "files": {}, "last": {}}


@pytest.fixture(scope="module")
def compiled(tmp_path_factory):
    """``prefix -> folder`` of generated estimators, made on demand for the C blocks."""
    folder = tmp_path_factory.mktemp("c_blocks")
    made: dict[str, Path] = {}

    def get(prefix: str) -> Path:
        if prefix not in made:
            import learnest_codegen as ln

            system, kind, estimator, horizon = _split_prefix(prefix)
            model = (ROOT / "tests" / "data" / "model_b12bfa1") if kind == "knode" else kind
            built = ln.make_estimator(model, estimator, system=system, out=folder, horizon=horizon)
            made[prefix] = folder / prefix
            assert built.directory == made[prefix], (built.directory, prefix)
        return made[prefix]

    return get


def _split_prefix(prefix: str) -> tuple[str, str, str, int | None]:
    """``(system, kind, estimator, horizon)`` of ``<system>_<kind>_<estimator>[_n<N>]``."""
    from learnest_codegen.compilation import ESTIMATOR_NAMES
    from learnest_codegen.systems import SYSTEMS

    for estimator in sorted(ESTIMATOR_NAMES, key=len, reverse=True):
        for kind in ("nominal", "true", "knode"):
            for system in SYSTEMS:
                if m := re.fullmatch(rf"{system}_{kind}_{estimator}(?:_n(\d+))?", prefix):
                    return system, kind, estimator, None if m.group(1) is None else int(m.group(1))
    raise AssertionError(f"C block includes {prefix}.h: not <system>_<kind>_<estimator>[_n<N>]")


def _folder(block: Block, state) -> Path:
    if "continue" in block.markers and block.page in state["last"]:
        return state["last"][block.page]
    folder = state["root"] / re.sub(r"\W", "_", block.id)
    folder.mkdir()
    for name, text in state["files"].get(block.page, {}).items():
        (folder / name).write_text(text)
    return folder


# -- the test ------------------------------------------------------------------------------------


@pytest.mark.parametrize("block", [_param(b) for b in ALL_BLOCKS])
def test_block_runs_as_written(block: Block, short_systems, page_state, compiled, monkeypatch, capsys):
    if "skip" in block.markers:
        assert block.markers["skip"].strip(), f"{block.id}: a skip marker needs a reason"
        pytest.skip(f"{block.id}: {block.markers['skip']}")
    if "handoff" in block.markers:  # tested, as a whole page, elsewhere
        pytest.skip(f"{block.id}: {block.markers['handoff']} of the firmware page: written, built "
                    "and run with the page's other files by tests/test_handoff.py")
    if block.language in LISTINGS:
        return
    folder = _folder(block, page_state)
    page_state["last"][block.page] = folder
    monkeypatch.chdir(folder)
    if block.language == "python":
        _run_python(block, folder, page_state)
    elif block.language in ("bash", "sh", "shell"):
        _run_bash(block, folder, capsys)
    elif block.language == "c":
        _compile_c(block, folder, compiled)
    elif block.language == "json":
        json.loads(block.code)
    else:
        pytest.fail(f"{block.id}: a ```{block.language or '(no language)'} block: give it a language "
                    "this test runs, or a <!-- test: skip REASON --> marker")


def _run_python(block: Block, folder: Path, state) -> None:
    name = block.file_name
    if name is not None:  # a file the reader writes; a system file must load
        (folder / name).write_text(block.code)
        state["files"].setdefault(block.page, {})[name] = block.code
        if "SYSTEM" in block.code:
            import learnest_codegen as ln

            assert ln.get_system(str(folder / name)).name
        return
    namespace: dict = {"__name__": "__docs__"}
    with contextlib.redirect_stdout(io.StringIO()):  # what it prints is the reader's to see
        exec(compile(block.code, block.id, "exec"), namespace)  # noqa: S102 - the docs' own code


def _run_bash(block: Block, folder: Path, capsys) -> None:
    if "shell" in block.markers:
        result = subprocess.run(["bash", "-e", "-c", block.code], cwd=folder, capture_output=True,
                                text=True, timeout=1800, env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert result.returncode == 0, f"{block.id}:\n{result.stdout[-2000:]}\n{result.stderr[-2000:]}"
        return
    from click.testing import CliRunner

    from learnest_codegen.cli import cli, compile_cmd

    entry = {"learnest": cli, "learnest-compile": compile_cmd}
    for args in commands(block.code):
        assert args[0] in entry, (f"{block.id}: `{' '.join(args)}` is not a learnest command; mark the "
                                  "block <!-- test: shell --> or <!-- test: skip REASON -->")
        result = CliRunner().invoke(entry[args[0]], args[1:], catch_exceptions=False)
        assert result.exit_code == 0, f"{block.id}: `{' '.join(args)}` failed:\n{result.output[-3000:]}"


def _compile_c(block: Block, folder: Path, compiled) -> None:
    headers = [h for h in re.findall(r'#include\s+"(\w+)\.h"', block.code)
               if not h.startswith("learnest_")]
    assert headers, f"{block.id}: a C block includes the generated <prefix>.h it uses"
    include = [f"-I{compiled(prefix)}" for prefix in headers]
    source = folder / "block.c"
    source.write_text(block.code)
    cmd = ["gcc", "-std=c99", "-c", str(source), "-o", str(folder / "block.o"), *include,
           "-Werror=implicit-function-declaration", "-Werror=incompatible-pointer-types",
           "-Werror=int-conversion"]
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, f"{block.id}: does not compile:\n{result.stderr[-3000:]}"


def test_every_page_is_read_and_markers_have_reasons():
    """The extractor sees the blocks (a page of unclosed fences would hide every later one), and
    the skipped blocks stay few and say why."""
    assert "README.md" in PAGES and len(PAGES) >= 10
    assert any(b.page == "README.md" and b.language == "python" for b in ALL_BLOCKS)
    skipped = [b for b in ALL_BLOCKS if "skip" in b.markers]
    assert all(b.markers["skip"].strip() for b in skipped), [b.id for b in skipped]
    assert len(skipped) <= len(ALL_BLOCKS) // 2, [b.id for b in skipped]


def test_the_readme_quick_start_prints_what_it_computes(short_systems, tmp_path, monkeypatch):
    """The quick start's printed MSEs are those of its estimators, and KNODE beats the prior.

    On runs of 2 s: trained on 1 s (500 samples) the default's KNODE-UKF is worse than the
    prior's (MSE 2.1e-2 against 1.6e-2); on 2 s it is 15x better (1.6e-3 against 2.4e-2)."""
    from learnest_codegen.systems import SYSTEMS

    monkeypatch.setitem(SYSTEMS, "cartpole", dataclasses.replace(SYSTEMS["cartpole"], duration=2.0))
    block = next(b for b in blocks("README.md") if b.language == "python" and "ln.train" in b.code)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    with contextlib.redirect_stdout(io.StringIO()) as printed:
        exec(compile(block.code, block.id, "exec"), namespace)  # noqa: S102
    lines = printed.getvalue().splitlines()
    assert [line.split(":")[0] for line in lines] == ["UKF", "KNODE-UKF"]
    mses = [float(re.search(r"MSE (\S+),", line).group(1)) for line in lines]
    ln, test_run = namespace["ln"], namespace["test_run"]
    assert mses[1] == pytest.approx(ln.evaluate(namespace["knode"], test_run).mse(test_run.x), rel=1e-3)
    assert mses[1] < mses[0]


def test_the_replay_loop_fails_when_u_and_y_are_paired_wrongly(short_systems, tmp_path, monkeypatch):
    """The quick start's replay loop (``step(u[k-1], y[k])``) checks itself against ``run``: as
    written it passes (test_block_runs_as_written), and with ``u[k]`` paired with ``y[k]`` its
    check fails, so the example can tell the two pairings apart."""
    (block,) = [b for b in blocks("docs/guide/quick_start.md") if "u_applied" in b.code]
    right = "run.u[k - 1] if k > 0 else run.u[0]"
    assert right in block.code
    monkeypatch.chdir(tmp_path)
    with contextlib.redirect_stdout(io.StringIO()):
        exec(compile(block.code, block.id, "exec"), {"__name__": "__docs__"})  # noqa: S102
        with pytest.raises(AssertionError, match="not equal"):
            exec(compile(block.code.replace(right, "run.u[k]"), block.id, "exec"),  # noqa: S102
                 {"__name__": "__docs__"})


def _links(path: Path):
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", path.read_text()):
        if not re.match(r"[a-z]+:", target):
            yield target


@pytest.mark.parametrize("page", PAGES)
def test_links_resolve(page):
    path = ROOT / page
    missing = [t for t in _links(path) if not (path.parent / t).exists()]
    assert not missing, f"{page} links to missing files: {missing}"


def _mkdocs_build(tmp_path: Path, with_api: bool) -> Path:
    mkdocs = shutil.which("mkdocs") or str(Path(sys.executable).parent / "mkdocs")
    if not Path(mkdocs).exists():
        pytest.skip("mkdocs is not installed (pip install -e .[test])")
    config = ROOT / "mkdocs.yml"
    if not with_api:  # the site without the API reference's plugin
        plain = tmp_path / "mkdocs.yml"
        text = re.sub(r"(?ms)^plugins:.*?(?=^\S|\Z)", "", config.read_text())
        plain.write_text(text.replace("docs_dir: docs", f"docs_dir: {ROOT / 'docs'}"))
        config = plain
    site = tmp_path / "site"
    result = subprocess.run([mkdocs, "build", "--strict", "-f", str(config), "--site-dir", str(site)],
                            cwd=ROOT, capture_output=True, text=True, timeout=600,
                            env={**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *sys.path])})
    assert result.returncode == 0, result.stderr[-3000:]
    return site


def test_docs_site_builds_strictly(tmp_path):
    """``mkdocs build --strict`` of the pages: a broken link or anchor, or a page left out of
    the nav, fails."""
    site = _mkdocs_build(tmp_path, with_api=False)
    assert (site / "reports" / "results" / "index.html").is_file()
    assert (site / "guide" / "quick_start" / "index.html").is_file()


def _nav_pages(node) -> list[str]:
    """Every page a mkdocs ``nav`` (lists of ``{title: page or list}``) names."""
    if isinstance(node, str):
        return [node]
    if isinstance(node, dict):
        return [page for value in node.values() for page in _nav_pages(value)]
    return [page for item in node for page in _nav_pages(item)]


def test_the_nav_lists_every_page_of_docs():
    """The site's navigation reaches every page: each .md under docs/ is in mkdocs.yml's nav,
    once, and the nav names no page that does not exist."""
    yaml = pytest.importorskip("yaml")
    config = yaml.safe_load(re.sub(r"(?ms)^plugins:.*?(?=^\S|\Z)", "", (ROOT / "mkdocs.yml").read_text()))
    listed = _nav_pages(config["nav"])
    pages = sorted(p.relative_to(ROOT / "docs").as_posix() for p in (ROOT / "docs").rglob("*.md"))
    assert sorted(set(listed)) == pages, {"not in the nav": sorted(set(pages) - set(listed)),
                                          "not a page": sorted(set(listed) - set(pages))}
    assert len(listed) == len(set(listed)), "a page is listed twice"
    assert {"guide", "reports"} <= {page.split("/")[0] for page in listed}


def test_api_reference_builds_from_the_docstrings(tmp_path):
    """The API reference page (docs/guide/python_api.md, mkdocstrings) builds strictly and documents the
    public calls and settings."""
    try:
        import mkdocstrings  # noqa: F401
    except ImportError:
        pytest.skip("the API reference needs mkdocstrings-python (pip install -e .[test])")
    page = (_mkdocs_build(tmp_path, with_api=True) / "guide" / "python_api" / "index.html").read_text()
    for name in ("pipeline.train", "pipeline.make_estimator", "pipeline.evaluate",
                 "config.TrainingSettings", "systems.base.System", "data.read_run", "errors.SettingsError"):
        assert f'id="learnest_codegen.{name}"' in page, name
