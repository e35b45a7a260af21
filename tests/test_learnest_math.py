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
from scipy import special

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


EXP_POS = r"""
#include <stdio.h>
#include <string.h>
#define LEARNEST_REAL float
#include "learnest_math.h"
int main(void) {
  /* every float in [0.5, 32): tanh's exp argument 2|x| lies in [0.7, 18] */
  unsigned int bits, lo, hi, differ = 0, count = 0;
  float y = 0.5f, e, p;
  memcpy(&lo, &y, sizeof lo);
  y = 32.0f;
  memcpy(&hi, &y, sizeof hi);
  for (bits = lo; bits < hi; ++bits, ++count) {
    memcpy(&y, &bits, sizeof y);
    e = learnest_expf_(y);
    p = learnest_expf_pos_(y);
    differ += memcmp(&e, &p, sizeof e) != 0;
  }
  printf("%u %u\n", count, differ);
  return 0;
}
"""


def test_tanh_exp_equals_the_general_exp_bit_for_bit(tmp_path):
    """tanh's exp (learnest_expf_pos_: no range test, no sign) returns learnest_expf_'s bits on
    every float tanh can give it."""
    if shutil.which("gcc") is None:
        pytest.skip("gcc not found")
    for path in kit_files():
        shutil.copy(path, tmp_path / path.name)
    (tmp_path / "main.c").write_text(EXP_POS)
    subprocess.run(["gcc", "-O2", "-std=c99", "-ffp-contract=off", "-fno-math-errno", "-Wall",
                    "-Wextra", "-Werror", "-pedantic", f"-I{tmp_path}", str(tmp_path / "main.c"),
                    "-lm", "-o", str(tmp_path / "main")], check=True)
    out = subprocess.run([str(tmp_path / "main")], capture_output=True, text=True, check=True).stdout
    count, differ = map(int, out.split())
    assert count == 6 * 2**23 and differ == 0


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


#: The C library's routines behind learnest_<name> (learnest_math.h's LEARNEST_LIBM_1 and _2),
#: numpy's (scipy's erf) twins and a domain on which both are finite.
LIBM = {"sqrt": (np.sqrt, (0, 50)), "fabs": (np.abs, (-50, 50)), "tan": (np.tan, (-1.5, 1.5)),
        "asin": (np.arcsin, (-1, 1)), "acos": (np.arccos, (-1, 1)), "atan": (np.arctan, (-50, 50)),
        "sinh": (np.sinh, (-20, 20)), "cosh": (np.cosh, (-20, 20)), "asinh": (np.arcsinh, (-50, 50)),
        "acosh": (np.arccosh, (1, 50)), "atanh": (np.arctanh, (-0.99, 0.99)), "log": (np.log, (1e-3, 50)),
        "log1p": (np.log1p, (-0.99, 50)), "expm1": (np.expm1, (-20, 20)), "floor": (np.floor, (-50, 50)),
        "ceil": (np.ceil, (-50, 50)), "erf": (special.erf, (-5, 5)),
        "atan2": (np.arctan2, (-50, 50)), "pow": (np.power, (0.1, 5)), "fmod": (np.fmod, (0.5, 50)),
        "fmin": (np.fmin, (-50, 50)), "fmax": (np.fmax, (-50, 50)), "hypot": (np.hypot, (-50, 50)),
        "copysign": (np.copysign, (-50, 50))}

LIBM_MAIN = r"""
#include <stdio.h>
#define LEARNEST_REAL REAL
#include "learnest_math.h"
static const double args[][2] = {ARGS};
int main(void) {
  int i;
  for (i = 0; i < (int)(sizeof args / sizeof args[0]); ++i) {
    REAL x = (REAL)args[i][0], y = (REAL)args[i][1];
    (void)y;
    printf("%.17g %.17g %.17g\n", (double)x, (double)y, (double)CALL);
  }
  return 0;
}
"""


@pytest.mark.parametrize("real", ["double", "float"])
def test_library_routines_run_in_the_builds_precision(real, tmp_path):
    """Every learnest_<name> that is the C library's (the generated model's other math calls)
    on 64 arguments of its domain: a float build calls no double routine and a double build no
    float one (the program's undefined symbols; the compiler inlines some, such as sqrt and
    fabs), and each result is within 2 ulp of its precision of numpy's (the C library's
    routines are within 1 ulp of the exact result: two implementations differ by at most 2)."""
    if shutil.which("gcc") is None:
        pytest.skip("gcc not found")
    assert set(LIBM) == set(MATH_ROUTINES) - {"sin", "cos", "tanh", "exp"}  # the kit's own: above
    for path in kit_files():
        shutil.copy(path, tmp_path / path.name)
    rng = np.random.default_rng(2)
    dtype = np.float32 if real == "float" else np.float64
    for name, (twin, (lo, hi)) in LIBM.items():
        two = twin in (np.arctan2, np.power, np.fmod, np.fmin, np.fmax, np.hypot, np.copysign)
        args = rng.uniform(lo, hi, (64, 2)).astype(dtype).astype(float).tolist()
        source = tmp_path / f"{name}.c"
        call = f"learnest_{name}(x, y)" if two else f"learnest_{name}(x)"
        source.write_text(LIBM_MAIN.replace("ARGS", ", ".join(f"{{{a.hex()}, {b.hex()}}}" for a, b in args))
                          .replace("CALL", call))
        exe = tmp_path / name
        subprocess.run(["gcc", "-O2", "-std=c99", "-ffp-contract=off", "-fno-math-errno", "-Wall",
                        "-Wextra", "-Werror", "-pedantic", f"-DREAL={real}", f"-I{tmp_path}",
                        str(source), "-lm", "-o", str(exe)], check=True)
        out = np.loadtxt(subprocess.run([str(exe)], capture_output=True, text=True,
                                        check=True).stdout.splitlines())
        x, y, value = out[:, 0], out[:, 1], out[:, 2]
        reference = twin(x, y) if two else twin(x)
        calls = {line.split()[-1].split("@")[0] for line in subprocess.run(
            ["nm", "-u", str(exe)], capture_output=True, text=True, check=True).stdout.splitlines()}
        assert (name if real == "float" else f"{name}f") not in calls, name  # the build's precision
        spacing = np.spacing(np.abs(reference).astype(dtype)).astype(float)
        assert np.all(np.abs(value - reference) <= 2 * spacing), name
