"""docs/guide/firmware.md, followed step by step: generate with learnest-compile, copy the folder
without the Python parts, build the page's main.c with its Makefile and with its CMake file,
run them on a simulated run with missing outputs, and compare with the Python binding.

Also: every generated folder (each estimator, both precisions) compiles clean under
``-Wall -Wextra -Werror -pedantic`` with gcc, clang and g++ without per-file flags, and its
public header is C++-clean.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import learnest_codegen as ln
from learnest_codegen.cli import compile_cmd
from learnest_codegen.pipeline import load_estimator
from learnest_codegen.runtime.manifest import GeneratedEstimator
from learnest_codegen.toolchain import CFLAGS, casadi_dirs

DOC = Path(__file__).resolve().parents[1] / "docs" / "guide" / "firmware.md"
PREFIX = "cartpole_nominal_mhe_rti_n20_float32"
WARNINGS = ["-Wall", "-Wextra", "-Werror", "-pedantic"]

# The board of the test: samples from stdin ("u y0 y1 v0 v1" per line), estimates to stdout.
BOARD_C = r"""
#include <stdio.h>
#include <stdlib.h>
#include "board.h"
int board_next_sample(float* u, float* y, unsigned char* valid) {
  double uu, y0, y1;
  int v0, v1;
  if (scanf("%lf %lf %lf %d %d", &uu, &y0, &y1, &v0, &v1) != 5) return 0;
  u[0] = (float)uu, y[0] = (float)y0, y[1] = (float)y1;
  valid[0] = (unsigned char)v0, valid[1] = (unsigned char)v1;
  return 1;
}
void board_publish(const float* x, int status) {
  printf("%d %.9g %.9g %.9g %.9g\n", status, (double)x[0], (double)x[1], (double)x[2], (double)x[3]);
}
int board_fail(int status) { fprintf(stderr, "estimator status %d\n", status); return 1; }
"""


def doc_files() -> dict[str, str]:
    """The page's files: each fenced block after a ``<!-- file: NAME -->`` line."""
    text = DOC.read_text()
    blocks = re.findall(r"<!-- file: (\S+) -->\n```\w*\n(.*?)```", text, re.S)
    return {name: body for name, body in blocks}


@pytest.fixture(scope="module")
def handoff(tmp_path_factory):
    """Step 1 (generate) and 2 (copy without the Python parts) of the page."""
    root = tmp_path_factory.mktemp("handoff")
    result = CliRunner().invoke(compile_cmd, ["--nominal", "--system", "cartpole", "--estimator",
                                                     "mhe_rti", "--precision", "float32", "--out",
                                                     str(root / "generated")])
    assert result.exit_code == 0, result.output
    generated = root / "generated" / PREFIX
    firmware = root / "firmware"
    shutil.copytree(generated, firmware / PREFIX,
                    ignore=shutil.ignore_patterns("*.so", "*.stamp", "*.json"))
    for name, body in doc_files().items():
        (firmware / name).write_text(body)
    (firmware / "board.c").write_text(BOARD_C)
    return generated, firmware


@pytest.fixture(scope="module")
def samples(cartpole):
    run = ln.simulate(cartpole, seed=7, duration=200 * cartpole.dt)
    valid = np.random.default_rng(1).random(run.y.shape) < 0.7
    U = np.vstack([run.u[:1], run.u[:-1]])  # the input applied since the previous sample
    lines = "".join(f"{float(u[0])!r} {float(y[0])!r} {float(y[1])!r} {int(v[0])} {int(v[1])}\n"
                    for u, y, v in zip(U, run.y, valid))
    return run, valid, lines


def check_output(stdout: str, generated: Path, run, valid, cartpole) -> None:
    out = np.loadtxt(stdout.splitlines())
    assert len(out) == len(run.y) and np.all(out[:, 0] >= 0)
    Y = np.where(valid, run.y, np.nan)
    expected = load_estimator(generated).run(run.u, Y, cartpole.x0, valid=valid)
    # the firmware prints floats with 9 digits: float32's every bit
    np.testing.assert_array_equal(out[:, 1:].astype(np.float32), expected.astype(np.float32))


def test_the_page_names_its_files():
    assert set(doc_files()) == {"main.c", "board.h", "Makefile", "CMakeLists.txt"}
    assert " ".join(CFLAGS) in DOC.read_text().replace("\n", " ").replace("`", "") or \
        all(flag in DOC.read_text() for flag in CFLAGS)


def test_the_copied_folder_holds_no_python(handoff):
    _, firmware = handoff
    names = {p.name for p in (firmware / PREFIX).iterdir()}
    assert f"{PREFIX}.mk" in names and "CMakeLists.txt" in names and "learnest_kit.h" in names
    assert not any(n.endswith((".so", ".json", ".py")) for n in names)
    fragment = (firmware / PREFIX / f"{PREFIX}.mk").read_text()
    assert "python" not in fragment.lower() and ".venv" not in fragment


def test_make_builds_the_page_and_equals_the_binding(handoff, samples, cartpole):
    generated, firmware = handoff
    run, valid, lines = samples
    proc = subprocess.run(["make", "-C", str(firmware), "firmware"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    out = subprocess.run([str(firmware / "firmware")], input=lines, capture_output=True, text=True,
                         check=True).stdout
    check_output(out, generated, run, valid, cartpole)


@pytest.mark.skipif(shutil.which("cmake") is None, reason="cmake not installed")
def test_cmake_builds_the_page_and_equals_the_binding(handoff, samples, cartpole, tmp_path):
    generated, firmware = handoff
    run, valid, lines = samples
    build = tmp_path / "build"
    for command in (["cmake", "-S", str(firmware), "-B", str(build), "-DCMAKE_BUILD_TYPE=Release"],
                    ["cmake", "--build", str(build)]):
        proc = subprocess.run(command, capture_output=True, text=True)
        assert proc.returncode == 0, proc.stdout + proc.stderr
    out = subprocess.run([str(build / "firmware")], input=lines, capture_output=True, text=True,
                         check=True).stdout
    check_output(out, generated, run, valid, cartpole)


@pytest.fixture(scope="module")
def every_folder(cartpole, tmp_path_factory):
    """Each estimator in each precision it is generated in, of the cartpole's nominal model."""
    from learnest_codegen.compilation import compile_estimators
    from learnest_codegen.export import prior_model

    root, model = tmp_path_factory.mktemp("every"), prior_model(cartpole)
    folders = []
    for names, precision in ((("ukf", "mhe", "mhe_gn", "mhe_rti"), "float64"),
                             (("ukf", "mhe_gn"), "float32")):
        folders += [r.directory for r in compile_estimators(model, root, model_hash="nominal",
                                                            estimators=names, precision=precision).values()]
    return folders


def compile_clean(folder: Path, compiler: str) -> None:
    """-Wall -Wextra -Werror -pedantic on every C source of ``folder``, CasADi's included (g++
    compiles them as C++)."""
    if shutil.which(compiler) is None:
        pytest.skip(f"{compiler} not installed")
    include, _ = casadi_dirs()
    language = ["-x", "c++", "-std=c++11"] if compiler == "g++" else ["-std=c99"]
    for source in GeneratedEstimator.read(folder).source_paths:
        proc = subprocess.run([compiler, *language, "-O2", *WARNINGS, f"-I{folder}", f"-I{include}",
                               "-c", str(source), "-o", "/dev/null"], capture_output=True, text=True)
        assert proc.returncode == 0, f"{source}:\n{proc.stderr}"


@pytest.mark.parametrize("compiler", ["gcc", "clang", "g++"])
def test_the_generated_sources_are_warning_free_without_per_file_flags(handoff, compiler):
    compile_clean(handoff[0], compiler)


@pytest.fixture(scope="module")
def grouped_folder(tmp_path_factory):
    """The nominal quadrotor's mhe_rti: its three axes are solved one by one
    (learnest_gn_groups.h), C the cartpole's folders never compile."""
    root = tmp_path_factory.mktemp("grouped")
    result = CliRunner().invoke(compile_cmd, ["--nominal", "--system", "quadrotor", "--estimator",
                                                     "mhe_rti", "--precision", "float32", "--out",
                                                     str(root)])
    assert result.exit_code == 0, result.output
    (folder,) = root.iterdir()
    assert "#define LEARNEST_NCOMP 3" in (folder / f"{folder.name}.c").read_text()
    return folder


@pytest.mark.parametrize("compiler", ["gcc", "clang", "g++"])
def test_the_group_by_group_path_is_warning_free(grouped_folder, compiler):
    compile_clean(grouped_folder, compiler)


@pytest.mark.slow
@pytest.mark.parametrize("compiler", ["gcc", "clang", "g++"])
def test_every_generated_source_is_warning_free_without_per_file_flags(every_folder, compiler):
    """Every estimator in both precisions (the Ipopt MHE in float64)."""
    for folder in every_folder:
        compile_clean(folder, compiler)
