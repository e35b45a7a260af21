"""Generate the MHE as C: the whole Ipopt nlpsol (CasADi codegen) plus a small hand-written API.

Stages, acados-style: :func:`build_problem` describes the NLP (shared with the Python
reference), CasADi writes ``<prefix>.c/.h`` (the solver and the model ``F`` used for the warm
start), this module writes ``<prefix>_api.c/.h`` (window bookkeeping, see the header text
below), gcc links them against the casadi wheel's ``libipopt.so`` into ``lib<prefix>.so``, and
``manifest.json`` records what was built. An unchanged build is reused (toolchain stamp).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from string import Template

import casadi as cs

from .. import toolchain
from ..estimators.mhe_problem import IPOPT_OPTIONS, MHESettings, ParamLayout, build_problem
from ..export import DiscreteModel
from ..runtime.manifest import MANIFEST, read_manifest, write_manifest

API_CFLAGS = (*toolchain.DEFAULT_CFLAGS, "-Wall", "-Wextra")
# Return codes of the C API; 1 and 2 are CasADi's unified Ipopt status (error_on_fail).
STATUS = {0: "OK", 1: "IPOPT_FAILED", 2: "IPOPT_MAX_ITER", 3: "NONFINITE_SOLUTION",
          -1: "NOT_INITIALISED", -2: "NONFINITE_INPUT", -3: "NO_MEMORY", -4: "BAD_ARGUMENT"}


@dataclass(frozen=True)
class GeneratedMHE:
    """What :func:`generate_mhe` produced.

    Attributes
    ----------
    directory, library, sources (generated solver .c, API .c), header (API .h), manifest.
    build_seconds : compile time of this call (0.0 when the build was reused).
    code_bytes : size of the C sources and headers.
    reused : True when the library was up to date and not recompiled.
    """

    directory: Path
    prefix: str
    library: Path
    sources: tuple[Path, ...]
    header: Path
    manifest: Path
    build_seconds: float
    code_bytes: int
    reused: bool


def generate_mhe(model: DiscreteModel, settings: MHESettings | None, out_dir: Path, *,
                 prefix: str | None = None, model_hash: str = "") -> GeneratedMHE:
    """Generate, compile and describe the MHE of ``model`` in ``out_dir``.

    Parameters
    ----------
    model : the discrete model the estimator uses.
    settings : horizon and default weights (weights stay settable at run time);
        default ``MHESettings.from_system(model.system)``.
    out_dir : the folder for this estimator (created).
    prefix : C symbol prefix, default ``"<system>_<kind>_mhe"``; also names the CasADi solver.
    model_hash : hash of the model's weights, recorded in the manifest.
    """
    settings = settings or MHESettings.from_system(model.system)
    prefix = prefix or f"{model.system.name}_{model.kind}_mhe"
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9]*(_[A-Za-z0-9]+)*", prefix):
        raise ValueError(f"generate_mhe: prefix {prefix!r} is not a C identifier without "
                         "leading/trailing/double underscores (CasADi's rule for names)")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    problem = build_problem(model, settings, prefix)
    solver_c = _generate_solver(problem.solver, _renamed_F(model, prefix), out, prefix)
    api_h, api_c = _write_api(out, prefix, problem.layout)
    include, lib = toolchain.casadi_dirs()
    build = toolchain.build_shared([solver_c, api_c], out / f"lib{prefix}.so",
                                   include_dirs=[out, include], lib_dirs=[lib], libs=["ipopt"],
                                   cflags=API_CFLAGS)
    files = (solver_c, solver_c.with_suffix(".h"), api_c, api_h)
    code_bytes = sum(f.stat().st_size for f in files)
    manifest = write_manifest(out, {
        "estimator": "mhe", "system": model.system.name, "model_kind": model.kind,
        "prefix": prefix, "nx": model.nx, "nu": model.nu, "ny": model.ny, "dt": model.dt,
        "horizon": settings.horizon, "settings": settings.to_json(), "model_hash": model_hash,
        "code_hash": toolchain.file_hash(*files), "casadi_version": cs.__version__,
        "ipopt_options": dict(IPOPT_OPTIONS), "library": build.library.name,
        "build_seconds": _build_seconds(out, build), "code_bytes": code_bytes,
        "status_codes": {str(k): v for k, v in STATUS.items()},
    })
    return GeneratedMHE(out, prefix, build.library, (solver_c, api_c), api_h, manifest,
                        build.seconds, code_bytes, build.reused)


def _renamed_F(model: DiscreteModel, prefix: str) -> cs.Function:
    """``F`` under a prefixed name, so its exported C symbol is unique."""
    x, u = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    return cs.Function(f"{prefix}_F", [x, u], [model.F(x, u)], ["x", "u"], ["x_next"])


def _generate_solver(solver: cs.Function, F: cs.Function, out: Path, prefix: str) -> Path:
    cg = cs.CodeGenerator(f"{prefix}.c", {"with_header": True})
    cg.add(solver)
    cg.add(F)
    cg.generate(f"{out}/")
    return out / f"{prefix}.c"


def _build_seconds(out: Path, build: toolchain.BuildResult) -> float:
    """This build's seconds, or, for a reused library, those recorded when it was built."""
    if build.reused and (out / MANIFEST).is_file():
        return float(read_manifest(out).get("build_seconds", 0.0))
    return round(build.seconds, 3)


def _write_api(out: Path, prefix: str, layout: ParamLayout) -> tuple[Path, Path]:
    offsets = layout.offsets()
    values = {"p": prefix, "P": prefix.upper(), "nx": layout.nx, "nu": layout.nu,
              "ny": layout.ny, "horizon": layout.horizon, "np": layout.size,
              "off_xbar": offsets["xbar"], "off_u": offsets["U"], "off_y": offsets["Y"],
              "off_mask": offsets["mask"], "off_q": offsets["Q"], "off_r": offsets["R"],
              "off_pw": offsets["P"],
              "codes": "\n".join(f"#define {prefix.upper()}_{name} {code}"
                                 for code, name in STATUS.items()),
              "cases": "\n".join(f'    case {code}: return "{name}";' for code, name in STATUS.items())}
    header, source = out / f"{prefix}_api.h", out / f"{prefix}_api.c"
    header.write_text(Template(_API_H).substitute(values))
    source.write_text(Template(_API_C).substitute(values))
    return header, source


_API_H = """\
/* ${p}_api.h -- C API of a moving horizon estimator, generated by learnest_codegen.
 *
 * The estimator solves the MHE NLP of learnest_codegen/estimators/mhe_problem.py with the
 * Ipopt solver that CasADi generated in ${p}.c, and keeps the window bookkeeping of the
 * Python reference (learnest_codegen/estimators/mhe.py) exactly:
 *   - init(x0, Q, R, P): prior x0 (the first arrival xbar) and the weights, all inverse
 *     covariances, row-major: Q (NX x NX) process noise, R (NY x NY) measurement noise,
 *     P (NX x NX) arrival cost.
 *   - step(u, y): the first step after init takes sample 0 (u only enters h); later steps
 *     take the next sample, u being the input applied since the previous one. The window
 *     moves by one stage, the arrival xbar becomes the previous solution's estimate of the
 *     new first state once the window is full, Ipopt is warm-started from the previous
 *     solution shifted by one stage (last state predicted by F).
 *   - a step that fails returns its nonzero code and leaves the estimator unchanged.
 *   - run(T, U, Y, Xhat) after init: sample 0 is step(0, Y[0]), sample k >= 1 is
 *     step(U[k-1], Y[k]); U (T x NU), Y (T x NY), Xhat (T x NX) row-major. On failure it
 *     returns the code; ${p}_samples() then says how many samples were taken.
 *
 * Memory: the window, the parameters and CasADi's work vectors are static arrays, so there
 * is one estimator per loaded library and it is not thread-safe. Ipopt itself allocates
 * and frees its problem on every step (CreateIpoptProblem/IpoptSolve/FreeIpoptProblem in
 * the generated solver): the library is fast but not allocation-free.
 */
#ifndef ${P}_API_H
#define ${P}_API_H

#ifdef __cplusplus
extern "C" {
#endif

#define ${P}_NX ${nx}
#define ${P}_NU ${nu}
#define ${P}_NY ${ny}
#define ${P}_HORIZON ${horizon}  /* N: the window holds N+1 states */

/* Return codes. 1, 2: Ipopt did not succeed (CasADi's unified status); 3: Ipopt succeeded
 * but the solution is not finite; negative: the call was refused before solving. */
${codes}

int ${p}_init(const double* x0, const double* Q, const double* R, const double* P);
int ${p}_step(const double* u, const double* y);
void ${p}_get_state(double* x);   /* x (NX): the estimate, last window state */
void ${p}_get_window(double* X);  /* X ((N+1) x NX) row-major, oldest state first */
int ${p}_run(int T, const double* U, const double* Y, double* Xhat);
int ${p}_samples(void);           /* samples taken since init; -1 before init */
void ${p}_sizes(int* nx, int* nu, int* ny, int* horizon);
const char* ${p}_status_name(int code);

#ifdef __cplusplus
}
#endif
#endif
"""

_API_C = """\
/* ${p}_api.c -- generated by learnest_codegen; see ${p}_api.h. */
#include <math.h>
#include <string.h>

#include "${p}.h"
#include "${p}_api.h"

#define NX ${nx}
#define NU ${nu}
#define NY ${ny}
#define N ${horizon}
#define NW ((N + 1) * NX)
/* Layout of the NLP parameter vector (ParamLayout in mhe_problem.py): stage-contiguous
 * windows, column-major weights. */
#define NP ${np}
#define OFF_XBAR ${off_xbar}
#define OFF_U ${off_u}
#define OFF_Y ${off_y}
#define OFF_MASK ${off_mask}
#define OFF_Q ${off_q}
#define OFF_R ${off_r}
#define OFF_P ${off_pw}

static casadi_real p_now[NP], window[NW];        /* the last solved problem and solution */
static casadi_real p_next[NP], guess[NW], solution[NW];  /* the step being solved */
static int samples = -1, mem = -1;
/* CasADi work vectors; + 1 because a size may be 0 and ISO C has no zero-size arrays. */
static const casadi_real* arg[${p}_SZ_ARG + 1];
static casadi_real* res[${p}_SZ_RES + 1];
static casadi_int iw[${p}_SZ_IW + 1];
static casadi_real w[${p}_SZ_W + 1];
static const casadi_real* f_arg[${p}_F_SZ_ARG + 1];
static casadi_real* f_res[${p}_F_SZ_RES + 1];
static casadi_int f_iw[${p}_F_SZ_IW + 1];
static casadi_real f_w[${p}_F_SZ_W + 1];

static int all_finite(const double* v, int n) {
  int i;
  for (i = 0; i < n; ++i) {
    if (!isfinite(v[i])) return 0;
  }
  return 1;
}

/* Row-major n x n in, column-major out (CasADi's order). */
static void put_matrix(const double* M, int n, casadi_real* dst) {
  int i, j;
  for (i = 0; i < n; ++i) {
    for (j = 0; j < n; ++j) dst[j * n + i] = M[i * n + j];
  }
}

/* Drop stage 0 of a window of N+1 stages of `width` values; the last stage keeps its value. */
static void shift(casadi_real* block, int width) {
  memmove(block, block + width, (size_t)(N * width) * sizeof(casadi_real));
}

int ${p}_init(const double* x0, const double* Q, const double* R, const double* P) {
  int i;
  if (!x0 || !Q || !R || !P) return ${P}_BAD_ARGUMENT;
  if (!all_finite(x0, NX) || !all_finite(Q, NX * NX) || !all_finite(R, NY * NY)
      || !all_finite(P, NX * NX)) return ${P}_NONFINITE_INPUT;
  if (mem < 0) mem = ${p}_checkout();
  if (mem < 0) return ${P}_NO_MEMORY;
  memset(p_now, 0, sizeof p_now);
  memcpy(p_now + OFF_XBAR, x0, NX * sizeof(double));
  put_matrix(Q, NX, p_now + OFF_Q);
  put_matrix(R, NY, p_now + OFF_R);
  put_matrix(P, NX, p_now + OFF_P);
  for (i = 0; i <= N; ++i) memcpy(window + i * NX, x0, NX * sizeof(double));
  samples = 0;
  return ${P}_OK;
}

/* p_next, guess <- the problem of the next sample (MHE._advance in the Python reference). */
static void advance(const double* u, const double* y) {
  memcpy(p_next, p_now, sizeof p_now);
  memcpy(guess, window, sizeof window);
  if (samples > 0) {
    if (p_now[OFF_MASK] == 1.0) {  /* window was full: the arrival moves on one sample */
      memcpy(p_next + OFF_XBAR, window + NX, NX * sizeof(casadi_real));
    }
    shift(p_next + OFF_U, NU);
    shift(p_next + OFF_Y, NY);
    shift(p_next + OFF_MASK, 1);
    shift(guess, NX);
    f_arg[0] = window + N * NX;
    f_arg[1] = u;
    f_res[0] = guess + N * NX;
    (void)${p}_F(f_arg, f_res, f_iw, f_w, 0);  /* SX code: always returns 0 */
  }
  memcpy(p_next + OFF_U + N * NU, u, NU * sizeof(double));
  memcpy(p_next + OFF_Y + N * NY, y, NY * sizeof(double));
  p_next[OFF_MASK + N] = 1.0;
}

static int solve(void) {
  int i, flag;
  for (i = 0; i < 8; ++i) arg[i] = 0;  /* no bounds, no multiplier guesses */
  for (i = 0; i < 6; ++i) res[i] = 0;
  arg[0] = guess;
  arg[1] = p_next;
  res[0] = solution;
  flag = ${p}(arg, res, iw, w, mem);
  if (flag) return flag == 2 ? ${P}_IPOPT_MAX_ITER : ${P}_IPOPT_FAILED;
  return all_finite(solution, NW) ? ${P}_OK : ${P}_NONFINITE_SOLUTION;
}

int ${p}_step(const double* u, const double* y) {
  int code;
  if (samples < 0) return ${P}_NOT_INITIALISED;
  if (!u || !y) return ${P}_BAD_ARGUMENT;
  if (!all_finite(u, NU) || !all_finite(y, NY)) return ${P}_NONFINITE_INPUT;
  advance(u, y);
  code = solve();
  if (code != ${P}_OK) return code;
  memcpy(p_now, p_next, sizeof p_now);
  memcpy(window, solution, sizeof window);
  ++samples;
  return ${P}_OK;
}

void ${p}_get_state(double* x) { memcpy(x, window + N * NX, NX * sizeof(double)); }

void ${p}_get_window(double* X) { memcpy(X, window, sizeof window); }

int ${p}_run(int T, const double* U, const double* Y, double* Xhat) {
  static const double no_input[NU] = {0};
  int k, code;
  if (samples < 0) return ${P}_NOT_INITIALISED;
  if (T < 1 || !U || !Y || !Xhat || samples != 0) return ${P}_BAD_ARGUMENT;
  for (k = 0; k < T; ++k) {
    code = ${p}_step(k ? U + (k - 1) * NU : no_input, Y + k * NY);
    if (code != ${P}_OK) return code;
    ${p}_get_state(Xhat + k * NX);
  }
  return ${P}_OK;
}

int ${p}_samples(void) { return samples; }

void ${p}_sizes(int* nx, int* nu, int* ny, int* horizon) {
  *nx = NX;
  *nu = NU;
  *ny = NY;
  *horizon = N;
}

const char* ${p}_status_name(int code) {
  switch (code) {
${cases}
    default: return "UNKNOWN";
  }
}
"""
