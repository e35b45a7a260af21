"""The UKF as CasADi functions and as generated C with a small hand-written C API.

:func:`ukf_step_function` writes FilterPy 2.0.0's predict + update as one SX graph, operation
for operation (Merwe sigma points from the upper Cholesky factor of ``(lambda + n) P``, the
unscented transform, re-drawing the sigma points from the prior, an explicit ``S^-1`` and
``P - K S K^T``), so the compiled filter matches the reference to rounding.
:func:`generate_ukf` writes the C of both functions plus ``<prefix>_api.{c,h}`` into one folder,
compiles it and writes the folder's ``manifest.json``.
"""

from __future__ import annotations

import re
import string
import time
from dataclasses import dataclass
from pathlib import Path

import casadi as cs
import numpy as np

from ..estimators.ukf import UKFSettings
from ..export import DiscreteModel
from ..runtime.manifest import write_manifest
from ..toolchain import BuildResult, build_shared, file_hash

ARG_NAMES = ["x", "P", "u", "y", "Q", "R"]
RES_NAMES = ["x_post", "P_post"]
_C_IDENTIFIER = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
# -Wall -Wextra keep the hand-written API honest; CasADi's own code may still warn.
CFLAGS = ("-O2", "-fPIC", "-fno-math-errno", "-std=c99", "-Wall", "-Wextra")


def default_prefix(model: DiscreteModel) -> str:
    """``<system>_<kind>_ukf``: the prefix of every exported C symbol and file."""
    return f"{model.system.name}_{model.kind}_ukf"


def merwe_weights(n: int, settings: UKFSettings) -> tuple[np.ndarray, np.ndarray, float]:
    """``(Wm (2n+1,), Wc (2n+1,), lambda + n)`` with FilterPy's formulas, term for term."""
    alpha, beta, kappa = settings.alpha, settings.beta, settings.kappa
    lambda_ = alpha**2 * (n + kappa) - n
    c = 0.5 / (n + lambda_)
    Wm, Wc = np.full(2 * n + 1, c), np.full(2 * n + 1, c)
    Wc[0] = lambda_ / (n + lambda_) + (1 - alpha**2 + beta)
    Wm[0] = lambda_ / (n + lambda_)
    return Wm, Wc, lambda_ + n


def chol_upper(A: cs.SX) -> cs.SX:
    """Upper ``U`` with ``A = U^T U``, reading only A's upper triangle like LAPACK ``potrf('U')``.

    A non-positive pivot gives ``sqrt`` of a negative number, i.e. NaN, which the C API reports.
    """
    n = A.shape[0]
    U = cs.SX.zeros(n, n)
    for j in range(n):
        U[j, j] = cs.sqrt(A[j, j] - sum((U[k, j] ** 2 for k in range(j)), cs.SX(0)))
        for i in range(j + 1, n):
            dot = sum((U[k, j] * U[k, i] for k in range(j)), cs.SX(0))
            U[j, i] = (A[j, i] - dot) / U[j, j]
    return U


def inv_spd(S: cs.SX) -> cs.SX:
    """``S^-1`` for symmetric positive definite ``S`` as ``U^-1 U^-T`` (``S = U^T U``).

    FilterPy calls ``numpy.linalg.inv`` (LU); for an SPD ``S`` both agree to rounding, and a
    Cholesky needs no pivoting, which a symbolic graph cannot express.
    """
    n = S.shape[0]
    U = chol_upper(S)
    V = cs.SX.zeros(n, n)  # V = U^-1, upper triangular, by back substitution
    for j in range(n):
        V[j, j] = 1 / U[j, j]
        for i in range(j - 1, -1, -1):
            V[i, j] = -sum((U[i, k] * V[k, j] for k in range(i + 1, j + 1)), cs.SX(0)) / U[i, i]
    return cs.mtimes(V, V.T)


def sigma_points(x: cs.SX, P: cs.SX, scale: float) -> list[cs.SX]:
    """Merwe sigma points ``[x, x + U[k], ..., x - U[k], ...]`` with ``U = chol((lambda+n) P)``."""
    U = chol_upper(scale * P)
    n = x.shape[0]
    return [x] + [x + U[k, :].T for k in range(n)] + [x - U[k, :].T for k in range(n)]


def unscented_transform(sigmas: list[cs.SX], Wm, Wc, noise_cov: cs.SX) -> tuple[cs.SX, cs.SX]:
    """Weighted mean and ``sum Wc_i d_i d_i^T + noise_cov`` of the transformed sigma points."""
    mean = sum((Wm[i] * s for i, s in enumerate(sigmas)), cs.SX.zeros(sigmas[0].shape))
    cov = sum((Wc[i] * cs.mtimes(s - mean, (s - mean).T) for i, s in enumerate(sigmas)),
              cs.SX.zeros(mean.shape[0], mean.shape[0]))
    return mean, cov + noise_cov


def _symbols(model: DiscreteModel) -> list[cs.SX]:
    nx, nu, ny = model.nx, model.nu, model.ny
    return [cs.SX.sym("x", nx), cs.SX.sym("P", nx, nx), cs.SX.sym("u", nu), cs.SX.sym("y", ny),
            cs.SX.sym("Q", nx, nx), cs.SX.sym("R", ny, ny)]


def _update(model, x, P, u, y, R, Wm, Wc, scale) -> tuple[cs.SX, cs.SX]:
    """FilterPy ``update``: sigma points of ``(x, P)`` through ``h``, explicit ``S^-1``."""
    sig_f = sigma_points(x, P, scale)
    sig_h = [model.h(s, u) for s in sig_f]
    zp, S = unscented_transform(sig_h, Wm, Wc, R)
    Pxz = sum((Wc[i] * cs.mtimes(sig_f[i] - x, (sig_h[i] - zp).T) for i in range(len(sig_f))),
              cs.SX.zeros(model.nx, model.ny))
    K = cs.mtimes(Pxz, inv_spd(S))
    return x + cs.mtimes(K, y - zp), P - cs.mtimes(K, cs.mtimes(S, K.T))


def ukf_step_function(model: DiscreteModel, settings: UKFSettings, *,
                      name: str | None = None) -> cs.Function:
    """One UKF sample: predict with ``u`` then update with ``y`` (``h`` evaluated with ``u``).

    Returns ``Function(name, [x (nx), P (nx,nx), u (nu), y (ny), Q (nx,nx), R (ny,ny)],
    [x_post (nx), P_post (nx,nx)])``, default name ``<prefix>_predict_update``.
    """
    settings.validate_for(model)
    Wm, Wc, scale = merwe_weights(model.nx, settings)
    x, P, u, y, Q, R = args = _symbols(model)
    x_prior, P_prior = unscented_transform([model.F(s, u) for s in sigma_points(x, P, scale)],
                                           Wm, Wc, Q)
    outputs = _update(model, x_prior, P_prior, u, y, R, Wm, Wc, scale)
    return cs.Function(name or f"{default_prefix(model)}_predict_update", args, list(outputs),
                       ARG_NAMES, RES_NAMES)


def ukf_update_function(model: DiscreteModel, settings: UKFSettings, *,
                        name: str | None = None) -> cs.Function:
    """The update alone (sample 0), with the same named inputs and outputs (``Q`` unused)."""
    settings.validate_for(model)
    Wm, Wc, scale = merwe_weights(model.nx, settings)
    x, P, u, y, _, R = args = _symbols(model)
    outputs = _update(model, x, P, u, y, R, Wm, Wc, scale)
    return cs.Function(name or f"{default_prefix(model)}_update", args, list(outputs),
                       ARG_NAMES, RES_NAMES)


@dataclass(frozen=True)
class GeneratedUKF:
    """A generated and compiled UKF folder.

    Attributes
    ----------
    directory, library, manifest : the folder, its shared library and ``manifest.json``.
    sources : the C and header files written (CasADi's and the API).
    prefix : prefix of every exported C symbol.
    generate_seconds : time to build the SX graphs and write the C.
    build : the compiler call (its ``seconds``; ``reused`` when nothing changed).
    code_bytes : total size of ``sources``.
    """

    directory: Path
    library: Path
    manifest: Path
    sources: tuple[Path, ...]
    prefix: str
    generate_seconds: float
    build: BuildResult
    code_bytes: int

    @property
    def build_seconds(self) -> float:
        """Compile time [s]; 0 when the library was reused."""
        return self.build.seconds


def generate_ukf(model: DiscreteModel, settings: UKFSettings, out_dir: Path, *,
                 prefix: str | None = None, model_hash: str = "",
                 force: bool = False) -> GeneratedUKF:
    """Write, compile and describe a C UKF for ``model`` in ``out_dir``.

    Writes ``<prefix>_casadi.{c,h}`` (CasADi), ``<prefix>_api.{c,h}`` (the C API documented in
    the header), ``lib<prefix>.so`` and ``manifest.json``. Unchanged inputs reuse the library
    unless ``force``. Raises :class:`BuildError` with the compiler's stderr on failure.
    """
    prefix = prefix or default_prefix(model)
    if not _C_IDENTIFIER.fullmatch(prefix):
        raise ValueError(f"generate_ukf: prefix must be a C identifier, got {prefix!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    functions = (ukf_step_function(model, settings, name=f"{prefix}_predict_update"),
                 ukf_update_function(model, settings, name=f"{prefix}_update"))
    sources = _write_sources(model, functions, out_dir, prefix)
    generate_seconds = time.perf_counter() - start
    library = out_dir / f"lib{prefix}.so"
    build = build_shared([p for p in sources if p.suffix == ".c"], library,
                         include_dirs=[out_dir], cflags=CFLAGS, force=force)
    code_bytes = sum(p.stat().st_size for p in sources)
    manifest = write_manifest(out_dir, {
        "estimator": "ukf", "system": model.system.name, "model_kind": model.kind,
        "prefix": prefix, "nx": model.nx, "nu": model.nu, "ny": model.ny, "dt": model.dt,
        "settings": settings.to_json(), "model_hash": model_hash,
        "code_hash": file_hash(*sources), "casadi_version": cs.__version__,
        "library": library.name, "generate_seconds": generate_seconds,
        "build_seconds": build.seconds, "build_reused": build.reused, "code_bytes": code_bytes,
        "matrix_layout": "row-major",
    })
    return GeneratedUKF(out_dir, library, manifest, sources, prefix, generate_seconds, build,
                        code_bytes)


def _write_sources(model: DiscreteModel, functions, out_dir: Path, prefix: str) -> tuple[Path, ...]:
    """CasADi's C for ``functions`` and the API around them; returns the four file paths."""
    casadi_c = f"{prefix}_casadi.c"
    gen = cs.CodeGenerator(casadi_c, {"with_header": True})
    for fn in functions:
        gen.add(fn)
    gen.generate(str(out_dir) + "/")
    # Static work arrays sized for whichever function needs more; C forbids size-0 arrays.
    work = {key: max(1, *(int(getattr(fn, f"sz_{key}")()) for fn in functions))
            for key in ("arg", "res", "iw", "w")}
    api_h, api_c = render_api(prefix=prefix, casadi_header=f"{prefix}_casadi.h",
                              step_fn=functions[0].name(), update_fn=functions[1].name(),
                              nx=model.nx, nu=model.nu, ny=model.ny, dt=model.dt, work=work)
    (out_dir / f"{prefix}_api.h").write_text(api_h)
    (out_dir / f"{prefix}_api.c").write_text(api_c)
    return tuple(out_dir / name for name in (casadi_c, f"{prefix}_casadi.h", f"{prefix}_api.c",
                                             f"{prefix}_api.h"))


def render_api(*, prefix: str, casadi_header: str, step_fn: str, update_fn: str, nx: int, nu: int,
               ny: int, dt: float, work: dict[str, int]) -> tuple[str, str]:
    """The text of ``<prefix>_api.h`` and ``<prefix>_api.c`` for the given sizes."""
    values = dict(prefix=prefix, PREFIX=prefix.upper(), casadi_header=casadi_header,
                  step_fn=step_fn, update_fn=update_fn, nx=nx, nu=nu, ny=ny, dt=repr(float(dt)),
                  **{f"sz_{k}": v for k, v in work.items()})
    return (string.Template(_API_H).substitute(values),
            string.Template(_API_C).substitute(values))


_API_H = """\
/* ${prefix}_api.h: C API of a compiled Unscented Kalman Filter (generated by learnest_codegen).
 *
 * Sizes: nx = ${nx} states, nu = ${nu} inputs, ny = ${ny} outputs; sampling period dt = ${dt} s.
 *
 * Conventions
 * - Vectors are arrays of double; matrices are row-major (C order): P[i * nx + j] = P_ij.
 * - Every int function returns ${PREFIX}_OK (0) or one of the error codes below; a failed call
 *   leaves the filter state as it was.
 * - Samples follow the Python UKF.run: the first step() after init() is an update only; every
 *   later step(u, y) predicts with u, the input applied since the previous sample, then updates
 *   with y, evaluating the measurement function at that same u.
 * - There is one filter per process: its state lives in static storage (no dynamic memory), so
 *   the functions are not reentrant.
 *
 * Example (link with -l${prefix} -lm):
 *
 *     #include "${prefix}_api.h"
 *
 *     double x[${PREFIX}_NX];
 *     if (${prefix}_init(x0, P0, Q, R) != ${PREFIX}_OK) return 1;
 *     for (int k = 0; k < T; ++k) {
 *         const double* u = &U[(k > 0 ? k - 1 : 0) * ${PREFIX}_NU];
 *         if (${prefix}_step(u, &Y[k * ${PREFIX}_NY]) != ${PREFIX}_OK) return 1;
 *         ${prefix}_get_state(x);
 *     }
 */
#ifndef ${PREFIX}_API_H
#define ${PREFIX}_API_H

#ifdef __cplusplus
extern "C" {
#endif

#define ${PREFIX}_NX ${nx}
#define ${PREFIX}_NU ${nu}
#define ${PREFIX}_NY ${ny}

#define ${PREFIX}_OK 0
#define ${PREFIX}_ERR_NOT_INITIALISED 1 /* step() or run() before init() */
#define ${PREFIX}_ERR_ARGUMENT 2        /* a NULL pointer, or T < 0 */
#define ${PREFIX}_ERR_NONFINITE_INPUT 3 /* NaN or Inf in an argument */
#define ${PREFIX}_ERR_NUMERIC 4         /* NaN or Inf in the result, e.g. a covariance that is
                                           not positive definite (failed Cholesky) */

int ${prefix}_nx(void);
int ${prefix}_nu(void);
int ${prefix}_ny(void);
double ${prefix}_dt(void); /* [s] */

/* Start from mean x0 (nx) and covariance P0 (nx x nx) with process-noise covariance Q
 * (nx x nx) and measurement-noise covariance R (ny x ny). */
int ${prefix}_init(const double* x0, const double* P0, const double* Q, const double* R);

/* Filter one sample: input u (nu) held since the previous sample, measurement y (ny). */
int ${prefix}_step(const double* u, const double* y);

void ${prefix}_get_state(double* x);      /* x (nx): the current posterior mean */
void ${prefix}_get_covariance(double* P); /* P (nx x nx, row-major): its covariance */

/* Filter T samples from the current state: sample k is step(&U[max(k-1, 0) * nu], &Y[k * ny])
 * and row k of Xhat (T x nx) receives the state. U is T x nu, Y is T x ny, all row-major.
 * Called right after init() it reproduces the Python UKF.run. On failure the rows before the
 * failing sample are filled and the error code is returned. */
int ${prefix}_run(int T, const double* U, const double* Y, double* Xhat);

#ifdef __cplusplus
} /* extern "C" */
#endif

#endif /* ${PREFIX}_API_H */
"""

_API_C = """\
/* ${prefix}_api.c: see ${prefix}_api.h (generated by learnest_codegen). */
#include <math.h>
#include <string.h>

#include "${casadi_header}"
#include "${prefix}_api.h"

#define NX ${PREFIX}_NX
#define NU ${PREFIX}_NU
#define NY ${PREFIX}_NY

/* CasADi work arrays, sized at generation time for the larger of the two functions. */
static const casadi_real* g_arg[${sz_arg}];
static casadi_real* g_res[${sz_res}];
static casadi_int g_iw[${sz_iw}];
static casadi_real g_w[${sz_w}];

/* Filter state; CasADi reads matrices column-major, the API speaks row-major. */
static casadi_real g_x[NX], g_P[NX * NX], g_Q[NX * NX], g_R[NY * NY];
static int g_initialised = 0;
static int g_first = 1; /* the next step is sample 0: update only */

static int all_finite(const double* v, int n) {
    int i;
    for (i = 0; i < n; ++i) {
        if (!isfinite(v[i])) return 0;
    }
    return 1;
}

/* dst = src^T for n x n matrices: converts between row- and column-major storage. */
static void transpose(double* dst, const double* src, int n) {
    int i, j;
    for (i = 0; i < n; ++i) {
        for (j = 0; j < n; ++j) dst[j * n + i] = src[i * n + j];
    }
}

int ${prefix}_nx(void) { return NX; }
int ${prefix}_nu(void) { return NU; }
int ${prefix}_ny(void) { return NY; }
double ${prefix}_dt(void) { return ${dt}; }

int ${prefix}_init(const double* x0, const double* P0, const double* Q, const double* R) {
    if (!x0 || !P0 || !Q || !R) return ${PREFIX}_ERR_ARGUMENT;
    if (!all_finite(x0, NX) || !all_finite(P0, NX * NX) || !all_finite(Q, NX * NX)
        || !all_finite(R, NY * NY)) {
        return ${PREFIX}_ERR_NONFINITE_INPUT;
    }
    memcpy(g_x, x0, sizeof g_x);
    transpose(g_P, P0, NX);
    transpose(g_Q, Q, NX);
    transpose(g_R, R, NY);
    g_initialised = 1;
    g_first = 1;
    return ${PREFIX}_OK;
}

int ${prefix}_step(const double* u, const double* y) {
    casadi_real x_post[NX], P_post[NX * NX];
    int rc;
    if (!g_initialised) return ${PREFIX}_ERR_NOT_INITIALISED;
    if (!u || !y) return ${PREFIX}_ERR_ARGUMENT;
    if (!all_finite(u, NU) || !all_finite(y, NY)) return ${PREFIX}_ERR_NONFINITE_INPUT;
    g_arg[0] = g_x;
    g_arg[1] = g_P;
    g_arg[2] = u;
    g_arg[3] = y;
    g_arg[4] = g_Q;
    g_arg[5] = g_R;
    g_res[0] = x_post;
    g_res[1] = P_post;
    rc = g_first ? ${update_fn}(g_arg, g_res, g_iw, g_w, 0)
                 : ${step_fn}(g_arg, g_res, g_iw, g_w, 0);
    /* A failed Cholesky shows up as NaN (sqrt of a negative pivot): commit finite results only. */
    if (rc != 0 || !all_finite(x_post, NX) || !all_finite(P_post, NX * NX)) {
        return ${PREFIX}_ERR_NUMERIC;
    }
    memcpy(g_x, x_post, sizeof g_x);
    memcpy(g_P, P_post, sizeof g_P);
    g_first = 0;
    return ${PREFIX}_OK;
}

void ${prefix}_get_state(double* x) { memcpy(x, g_x, sizeof g_x); }

void ${prefix}_get_covariance(double* P) { transpose(P, g_P, NX); }

int ${prefix}_run(int T, const double* U, const double* Y, double* Xhat) {
    int k, rc;
    if (T < 0 || (T > 0 && (!U || !Y || !Xhat))) return ${PREFIX}_ERR_ARGUMENT;
    for (k = 0; k < T; ++k) {
        rc = ${prefix}_step(&U[(k > 0 ? k - 1 : 0) * NU], &Y[k * NY]);
        if (rc != ${PREFIX}_OK) return rc;
        ${prefix}_get_state(&Xhat[k * NX]);
    }
    return ${PREFIX}_OK;
}
"""
