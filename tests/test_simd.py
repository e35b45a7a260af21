"""The lane-parallel model (learnest_simd.h, codegen/casadi_c.py's batch copy) against the scalar one.

The batch copy of a model function runs, lane by lane, the same IEEE operations as the scalar
function, so the test is bit equality (the same computation on the same inputs): the vector
routines against the scalar routines of learnest_math.h on special and random arguments, built
for the x86-64 baseline (SSE2) and for AVX2; a generated KNODE model's batch copies (the
UKF's F, the MHE's stage) against its scalar functions; and the UKF built with and without
vectors, step for step.
"""

from __future__ import annotations

import json
import platform
import shutil
import subprocess

import casadi as cs
import numpy as np
import pytest
import torch

from learnest_codegen import get_system, simulation
from learnest_codegen.codegen.casadi_c import BATCH_LANES, BATCH_MAX_INSTRUCTIONS, write_casadi_c
from learnest_codegen.codegen.templates import kit_files
from learnest_codegen.codegen.ukf import generate_ukf
from learnest_codegen.estimators.ukf import UKFSettings
from learnest_codegen.export import hybrid_model
from learnest_codegen.learning.network import ResidualNet
from learnest_codegen.toolchain import CFLAGS

pytestmark = pytest.mark.skipif(shutil.which("gcc") is None or platform.machine() != "x86_64",
                                reason="the vector path is GCC on x86-64")

ROUTINES = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#define LEARNEST_REAL REAL
#include "learnest_simd.h"
#if !LEARNEST_SIMD
#error "no vectors"
#endif
#define L (32 / (int)sizeof(REAL))
static REAL special[] = {0.0, -0.0, 1e-30, -1e-30, 0.125, -0.125, 0.35, -0.35, 9.0, -9.0, 22.0,
  -22.0, 0.7853981633974483, 1.5707963267948966, 3.141592653589793, -3.141592653589793, 4095.9,
  4096.0, -4096.0, 99999.0, 1e5, -1e5, 1e6, 1e30, -1e30, 87.0, 88.0, 44.0, -44.0, 0.5, -0.5,
  1.0 / 0.0, -1.0 / 0.0, 0.0 / 0.0};
int main(void) {
  int n = (int)(sizeof special / sizeof special[0]), k, i, f, checked = 0, bad = 0;
  srand(7);
  for (k = 0; k < 200000; ++k) {
    VEC x, y[3];
    for (i = 0; i < L; ++i) {
      double r = (double)rand() / RAND_MAX, scale = k % 3 == 0 ? 1.0 : k % 3 == 1 ? 30.0 : 5000.0;
      x[i] = k < 64 ? special[(k * L + i) % n] : (REAL)((2 * r - 1) * scale);
      if (k % 5 == 0 && i % 2) x[i] = special[(k + i) % n];
    }
    y[0] = VTANH(x), y[1] = VSIN(x), y[2] = VCOS(x);
    for (i = 0; i < L; ++i) {
      REAL s[3];
      s[0] = STANH(x[i]), s[1] = SSINCOS(x[i], 0), s[2] = SSINCOS(x[i], 1);
      for (f = 0; f < 3; ++f) {
        REAL v = y[f][i];
        bad += memcmp(&v, &s[f], sizeof v) != 0;
        ++checked;
      }
    }
  }
  printf("%d %d\n", checked, bad);
  return 0;
}
"""

KINDS = {"double": ("learnest_v4d", "learnest_vtanh_d", "learnest_vsin_d", "learnest_vcos_d",
                    "learnest_tanhd_", "learnest_sincosd_"),
         "float": ("learnest_v8f", "learnest_vtanh_f", "learnest_vsin_f", "learnest_vcos_f",
                   "learnest_tanhf_", "learnest_sincosf_")}


@pytest.mark.parametrize("isa", [(), ("-mavx2",)], ids=["sse2", "avx2"])
@pytest.mark.parametrize("real", ["double", "float"])
def test_vector_routines_equal_scalar_routines_bit_for_bit(real, isa, tmp_path):
    for path in kit_files():
        shutil.copy(path, tmp_path / path.name)
    (tmp_path / "main.c").write_text(ROUTINES)
    names = dict(zip(("VEC", "VTANH", "VSIN", "VCOS", "STANH", "SSINCOS"), KINDS[real]))
    exe = tmp_path / "main"
    subprocess.run(["gcc", *CFLAGS, "-Werror", *isa, f"-DREAL={real}",
                    *(f"-D{k}={v}" for k, v in names.items()), f"-I{tmp_path}",
                    str(tmp_path / "main.c"), "-lm", "-o", str(exe)], check=True)
    checked, bad = map(int, subprocess.run([str(exe)], capture_output=True, text=True,
                                           check=True).stdout.split())
    assert checked == 200000 * (32 // (8 if real == "double" else 4)) * 3
    assert bad == 0


MODEL_MAIN = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "@M@.h"
#define L @M@_@F@_BATCH_LANES
#define NF @NF@
int main(void) {
  REAL xs[4 * L], us[L], Fs[NF * L], x[4], u[1], F[NF];
  const REAL* arg[2];
  REAL* res[2];
  int k, l, i, bad = 0;
  srand(3);
  for (k = 0; k < 5000; ++k) {
    for (l = 0; l < L; ++l) {
      for (i = 0; i < 4; ++i) xs[i * L + l] = (REAL)(((double)rand() / RAND_MAX - 0.5) * (k % 4 ? 4 : 60));
      us[l] = (REAL)(((double)rand() / RAND_MAX - 0.5) * 20);
    }
    arg[0] = xs, arg[1] = us, res[0] = Fs, res[1] = Fs + 4 * L;
    @M@_@F@_batch(arg, res);
    for (l = 0; l < L; ++l) {
      for (i = 0; i < 4; ++i) x[i] = xs[i * L + l];
      u[0] = us[l], arg[0] = x, arg[1] = u, res[0] = F, res[1] = F + 4;
      @M@_@F@(arg, res, 0, 0, 0);
      for (i = 0; i < NF; ++i) bad += memcmp(&F[i], &Fs[i * L + l], sizeof F[i]) != 0;
    }
  }
  printf("%d\n", bad);
  return 0;
}
"""


@pytest.fixture(scope="module")
def knode():
    torch.manual_seed(0)
    system = get_system("cartpole")
    return hybrid_model(system, ResidualNet(4, 1))


@pytest.mark.parametrize("function", ["F", "stage"])
@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_batch_model_equals_scalar_model_bit_for_bit(knode, precision, function, tmp_path):
    """The UKF's F and the MHE's stage (F and its Jacobian A, 4 + 16 outputs)."""
    from learnest_codegen.codegen.mhe_gn import model_functions

    name = "m_model"
    if function == "F":
        x, u = cs.SX.sym("x", 4), cs.SX.sym("u", 1)
        f = cs.Function(f"{name}_F", [x, u], [cs.cse(knode.F(x, u))], ["x", "u"], ["F"])
    else:
        f = model_functions(knode, name)[0]
    source, header = write_casadi_c([f], tmp_path, name, precision, batch=(f.name(),))
    assert f"#define {f.name()}_BATCH_LANES {BATCH_LANES[precision]}" in header.read_text()
    for path in kit_files():
        shutil.copy(path, tmp_path / path.name)
    real = "double" if precision == "float64" else "float"
    main = MODEL_MAIN.replace("@M@", name).replace("@F@", function).replace("REAL", real)
    (tmp_path / "main.c").write_text(main.replace("@NF@", "4" if function == "F" else "20"))
    exe = tmp_path / "main"
    subprocess.run(["gcc", *CFLAGS, "-Werror", f"-I{tmp_path}", str(tmp_path / "main.c"),
                    str(source), "-lm", "-o", str(exe)], check=True)
    assert subprocess.run([str(exe)], capture_output=True, text=True, check=True).stdout.split() == ["0"]


def test_unsupported_operation_gets_no_batch(tmp_path):
    """exp in double is the C library's (not the kit's): no vector copy, the scalar code only."""
    x = cs.SX.sym("x", 2)
    F = cs.Function("e_model_F", [x], [cs.exp(x) * x[0]], ["x"], ["F"])
    _, header = write_casadi_c([F], tmp_path, "e_model", "float64", batch=(F.name(),))
    assert "_BATCH" not in header.read_text()


def test_large_function_gets_no_batch(tmp_path):
    """Above BATCH_MAX_INSTRUCTIONS operations the vector builds' compile time is not worth it."""
    x = cs.SX.sym("x", 4)
    y = x
    while True:
        y = cs.tanh(y * 1.1 + 0.1)
        f = cs.Function("big_model_F", [x], [y], ["x"], ["F"])
        if f.n_instructions() > BATCH_MAX_INSTRUCTIONS:
            break
    _, header = write_casadi_c([f], tmp_path, "big_model", "float64", batch=(f.name(),))
    assert "_BATCH" not in header.read_text()


def test_ukf_with_vectors_equals_ukf_without_step_for_step(knode, tmp_path):
    """The generated UKF's library against its sources rebuilt with -DLEARNEST_NO_SIMD."""
    from learnest_codegen.runtime.manifest import library_digest
    from learnest_codegen.runtime.ukf import CompiledUKF

    system = knode.system
    gen = generate_ukf(knode, UKFSettings.from_system(system), tmp_path / "ukf", model_hash="simd")
    assert "LEARNEST_MODEL_F_BATCH" in (gen.directory / f"{gen.prefix}.c").read_text()
    run = simulation.simulate(system, seed=4, duration=0.6)
    X = CompiledUKF(gen.directory).run(run.u, run.y, system.x0)
    scalar = tmp_path / "scalar"
    shutil.copytree(gen.directory, scalar)
    library = scalar / gen.library
    subprocess.run(["gcc", *CFLAGS, "-fPIC", "-shared", "-DLEARNEST_NO_SIMD", f"-I{scalar}",
                    *(str(scalar / s) for s in gen.sources), "-lm", "-o", str(library)], check=True)
    assert library.stat().st_size < (gen.directory / gen.library).stat().st_size  # no batch copy
    manifest = json.loads((scalar / "manifest.json").read_text())  # the rebuilt library's digest
    (scalar / "manifest.json").write_text(json.dumps({**manifest, **library_digest(library)}))
    X_scalar = CompiledUKF(scalar).run(run.u, run.y, system.x0)
    np.testing.assert_array_equal(X, X_scalar)
    assert np.all(np.isfinite(X))
