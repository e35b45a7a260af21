"""The C kit's math routines (learnest_math.h) against numpy, and the generated model's calls.

learnest_math.h gives every build its routines in the build's precision; tanh (both
precisions), sin, cos and exp (float) are the kit's own. Their error bounds are the ones its
comment states: tanh, sin and cos within 2.3e-16 absolute in double, and the float routines within 3 ulp of
the correctly rounded result (the float routines use + - * / only, so a float32 build computes
the same bits on the host and on the Cortex-M4F: tests/test_cortex_m.py).
"""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

from learnest_codegen.codegen.casadi_c import MATH_ROUTINES, clean
from learnest_codegen.codegen.templates import kit_files

MAIN = r"""
#include <stdio.h>
#define LEARNEST_REAL REAL
#include "learnest_math.h"
int main(void) {
  double x;
  for (x = -30.0; x < 30.0; x += 0.000731) {
    REAL v = (REAL)x;
    printf("%.17g %.17g %.17g %.17g %.17g\n", (double)v, (double)learnest_tanh(v),
           (double)learnest_sin(v), (double)learnest_cos(v), (double)learnest_exp(v));
  }
  return 0;
}
"""


@pytest.fixture(scope="module", params=["double", "float"])
def table(request, tmp_path_factory):
    if shutil.which("gcc") is None:
        pytest.skip("gcc not found")
    tmp = tmp_path_factory.mktemp(f"math_{request.param}")
    for path in kit_files():
        shutil.copy(path, tmp / path.name)
    (tmp / "main.c").write_text(MAIN)
    exe = tmp / "main"
    subprocess.run(["gcc", "-O2", "-std=c99", "-ffp-contract=off", "-fno-math-errno", "-Wall",
                    "-Wextra", "-Werror", "-pedantic", f"-DREAL={request.param}", f"-I{tmp}",
                    str(tmp / "main.c"), "-lm", "-o", str(exe)], check=True)
    out = subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout
    return request.param, np.loadtxt(out.splitlines())


def ulps(value, reference):
    """|value - reference| in units of the float spacing at the reference."""
    spacing = np.spacing(np.abs(reference).astype(np.float32)).astype(float)
    return np.abs(value - reference) / spacing


def test_routines_against_numpy(table):
    real, t = table
    x = t[:, 0]
    if real == "double":
        assert np.max(np.abs(t[:, 1] - np.tanh(x))) <= 2.3e-16
        assert np.max(np.abs(t[:, 2] - np.sin(x))) <= 2.3e-16
        assert np.max(np.abs(t[:, 3] - np.cos(x))) <= 2.3e-16
        assert np.array_equal(t[:, 4], np.exp(x)) or np.max(np.abs(t[:, 4] / np.exp(x) - 1)) < 1e-15
        return
    # float: the inputs are floats, numpy evaluates in double, the routines must be within 3 ulp
    assert ulps(t[:, 1], np.tanh(x)).max() <= 3
    assert ulps(t[:, 2], np.sin(x)).max() <= 2
    assert ulps(t[:, 3], np.cos(x)).max() <= 2
    small = x < 88
    assert ulps(t[small, 4], np.exp(x[small])).max() <= 2
    # tanh is odd, saturates at +-1 and keeps NaN out of finite inputs
    assert np.all(np.abs(t[:, 1]) <= 1) and np.all(np.isfinite(t[:, 1]))


def test_generated_model_calls_the_kit_routines():
    text = ("#include <math.h>\n#define casadi_real float\n/* Add prefix to internal symbols */\n"
            "static int f(const casadi_real** arg) {\n"
            "  a0=sin(a1); a2=tanh(a0); a3=casadi_sq(a2); a4=atan2(a0,a1); a5=sqrt(a4);\n"
            "  return 0;\n}\n")
    out = clean(text)
    for name in ("sin", "tanh", "atan2", "sqrt"):
        assert f"learnest_{name}(" in out and f"={name}(" not in out
    assert "casadi_sq(a2)" in out  # CasADi's own helpers stay
    assert out.index('#include "learnest_math.h"') < out.index("static int f")
    assert {"sin", "cos", "tanh", "exp", "sqrt", "fabs"} <= set(MATH_ROUTINES)
