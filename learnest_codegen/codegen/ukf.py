"""The UKF as CasADi functions and as generated C with a small hand-written C API.

:func:`ukf_step_function` writes FilterPy 2.0.0's predict + update as one SX graph, operation
for operation (Merwe sigma points from the upper Cholesky factor of ``(lambda + n) P``, the
unscented transform, re-drawing the sigma points from the prior, an explicit ``S^-1`` and
``P - K S K^T``), so the compiled filter matches the reference to rounding.
:func:`generate_ukf` writes the C of both functions plus ``<prefix>_api.{c,h}`` (from the
templates ``templates/ukf_api.{h,c}.in``: a handle-based API on caller-provided memory) into one
folder, compiles it and writes the folder's ``manifest.json``.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass
from pathlib import Path

import casadi as cs
import numpy as np

from ..errors import SettingsError
from ..estimators.gate import MAX_INFLATION
from ..estimators.precision import PRECISIONS, check_precision
from ..estimators.ukf import UKFSettings
from ..export import DiscreteModel
from ..runtime.manifest import settings_hash, write_manifest
from ..runtime.status import STATUS_NAMES
from ..toolchain import BuildResult, build_shared, file_hash
from . import templates

# The smallest sigma-point spread a float32 UKF accepts (docs/embedded_mhe.md, float32 table).
FLOAT32_MIN_ALPHA = 0.5
ARG_NAMES = ["x", "P", "u", "y", "Q", "R"]
RES_NAMES = ["x_post", "P_post"]
PREDICT_ARGS, PREDICT_RES = ["x", "P", "u", "Q"], ["x_prior", "P_prior"]
UPDATE_ARGS, UPDATE_RES = ["x", "P", "u", "y", "R", "mask"], ["x_post", "P_post", "d2"]
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


def _update(model, x, P, u, y, R, Wm, Wc, scale, mask=None) -> tuple[cs.SX, cs.SX, cs.SX]:
    """FilterPy ``update``: sigma points of ``(x, P)`` through ``h``, explicit ``S^-1``.

    ``mask (ny)`` of 0/1 keeps the outputs marked 1: with ``M = diag(mask)`` the update uses
    ``M S M + (I - M)``, ``Pxz M`` and ``M (y - zp)``, i.e. exactly FilterPy's update on the kept
    outputs alone (the dropped ones get a unit block that couples to nothing). Also returns
    ``d2 (ny)``, each output's normalised innovation ``(y - zp)_j^2 / S_jj`` (unmasked).
    """
    sig_f = sigma_points(x, P, scale)
    sig_h = [model.h(s, u) for s in sig_f]
    zp, S = unscented_transform(sig_h, Wm, Wc, R)
    Pxz = sum((Wc[i] * cs.mtimes(sig_f[i] - x, (sig_h[i] - zp).T) for i in range(len(sig_f))),
              cs.SX.zeros(model.nx, model.ny))
    nu_ = y - zp
    d2 = nu_ * nu_ / cs.diag(S)
    if mask is not None:
        M = cs.diag(mask)
        S = cs.mtimes(M, cs.mtimes(S, M)) + cs.diag(1 - mask)
        Pxz, nu_ = cs.mtimes(Pxz, M), mask * nu_
    K = cs.mtimes(Pxz, inv_spd(S))
    return x + cs.mtimes(K, nu_), P - cs.mtimes(K, cs.mtimes(S, K.T)), d2


def ukf_predict_function(model: DiscreteModel, settings: UKFSettings, *,
                         name: str | None = None) -> cs.Function:
    """FilterPy ``predict``: ``Function(name, [x, P, u, Q], [x_prior, P_prior])``."""
    settings.validate_for(model)
    Wm, Wc, scale = merwe_weights(model.nx, settings)
    x, P, u, _, Q, _ = _symbols(model)
    x_prior, P_prior = unscented_transform([model.F(s, u) for s in sigma_points(x, P, scale)],
                                           Wm, Wc, Q)
    return cs.Function(name or f"{default_prefix(model)}_predict", [x, P, u, Q],
                       [x_prior, P_prior], PREDICT_ARGS, PREDICT_RES)


def ukf_gated_update_function(model: DiscreteModel, settings: UKFSettings, *,
                              name: str | None = None) -> cs.Function:
    """The update on the outputs a mask keeps, and every output's normalised innovation.

    ``Function(name, [x, P, u, y, R, mask (ny)], [x_post, P_post, d2 (ny)])`` (see
    :func:`_update`); the compiled filter calls it once with ``mask = 1`` and, when the gate
    rejects an output, again with that output's mask entry 0.
    """
    settings.validate_for(model)
    Wm, Wc, scale = merwe_weights(model.nx, settings)
    x, P, u, y, _, R = _symbols(model)
    mask = cs.SX.sym("mask", model.ny)
    outputs = _update(model, x, P, u, y, R, Wm, Wc, scale, mask)
    return cs.Function(name or f"{default_prefix(model)}_gated_update", [x, P, u, y, R, mask],
                       list(outputs), UPDATE_ARGS, UPDATE_RES)


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
    outputs = _update(model, x_prior, P_prior, u, y, R, Wm, Wc, scale)[:2]
    return cs.Function(name or f"{default_prefix(model)}_predict_update", args, list(outputs),
                       ARG_NAMES, RES_NAMES)


def ukf_update_function(model: DiscreteModel, settings: UKFSettings, *,
                        name: str | None = None) -> cs.Function:
    """The update alone (sample 0), with the same named inputs and outputs (``Q`` unused)."""
    settings.validate_for(model)
    Wm, Wc, scale = merwe_weights(model.nx, settings)
    x, P, u, y, _, R = args = _symbols(model)
    outputs = _update(model, x, P, u, y, R, Wm, Wc, scale)[:2]
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
                 force: bool = False, precision: str = "float64") -> GeneratedUKF:
    """Write, compile and describe a C UKF for ``model`` in ``out_dir``.

    Writes ``<prefix>_casadi.{c,h}`` (CasADi), ``<prefix>_api.{c,h}`` (the C API documented in
    the header, from ``templates/ukf_api.*.in``), ``learnest_status.h``, ``lib<prefix>.so`` and
    ``manifest.json``. ``precision`` (``"float64"`` or ``"float32"``) is the C real type.
    Unchanged inputs reuse the library unless ``force``. Raises :class:`BuildError` with the
    compiler's stderr on failure.
    """
    check_precision(precision, "generate_ukf")
    if precision == "float32" and settings.alpha < FLOAT32_MIN_ALPHA:
        raise SettingsError(f"generate_ukf: a float32 UKF needs alpha >= {FLOAT32_MIN_ALPHA}, got "
                            f"{settings.alpha}: with a small alpha the sigma-point weights cancel "
                            "(W0 = -99 at alpha 0.1, nx 4) and single precision loses the covariance "
                            "(cartpole: +12 % MSE); alpha 0.5 costs +0.14 %")
    prefix = prefix or default_prefix(model)
    if not _C_IDENTIFIER.fullmatch(prefix):
        raise SettingsError(f"generate_ukf: prefix must be a C identifier, got {prefix!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    functions = (ukf_predict_function(model, settings, name=f"{prefix}_predict"),
                 ukf_gated_update_function(model, settings, name=f"{prefix}_update"))
    sources = _write_sources(model, settings, functions, out_dir, prefix, PRECISIONS[precision])
    generate_seconds = time.perf_counter() - start
    library = out_dir / f"lib{prefix}.so"
    build = build_shared([p for p in sources if p.suffix == ".c"], library,
                         include_dirs=[out_dir], cflags=CFLAGS, force=force)
    code_bytes = sum(p.stat().st_size for p in sources)
    manifest = write_manifest(out_dir, {
        "estimator": "ukf", "system": model.system.name, "model_kind": model.kind,
        "system_fingerprint": model.system.fingerprint(),
        "prefix": prefix, "nx": model.nx, "nu": model.nu, "ny": model.ny, "dt": model.dt,
        "settings": settings.to_json(), "settings_hash": settings_hash(settings.to_json()),
        "model_hash": model_hash,
        "code_hash": file_hash(*sources), "casadi_version": cs.__version__,
        "library": library.name, "generate_seconds": generate_seconds,
        "build_seconds": build.seconds, "build_reused": build.reused, "code_bytes": code_bytes,
        "matrix_layout": "row-major", "precision": precision,
        "status_codes": {str(k): v for k, v in STATUS_NAMES.items()},
    })
    return GeneratedUKF(out_dir, library, manifest, sources, prefix, generate_seconds, build,
                        code_bytes)


def _write_sources(model: DiscreteModel, settings: UKFSettings, functions, out_dir: Path, prefix: str,
                   real: str) -> tuple[Path, ...]:
    """CasADi's C for ``functions`` and the API around them; returns the file paths."""
    casadi_c = f"{prefix}_casadi.c"
    gen = cs.CodeGenerator(casadi_c, {"with_header": True, "casadi_real": real})
    for fn in functions:
        gen.add(fn)
    gen.generate(str(out_dir) + "/")
    # Work arrays in the filter's struct, sized for whichever function needs more; C forbids
    # size-0 arrays.
    work = {key: max(1, *(int(getattr(fn, f"sz_{key}")()) for fn in functions))
            for key in ("arg", "res", "iw", "w")}
    real_bytes = 4 if real == "float" else 8
    bound = (128 + 8 * (work["arg"] + work["res"] + work["iw"]) + 4 * model.ny
             + real_bytes * (model.nx + 2 * model.nx**2 + model.ny**2 + work["w"] + 4))
    gate = settings.gate
    values = dict(prefix=prefix, PREFIX=prefix.upper(), casadi_header=f"{prefix}_casadi.h",
                  predict_fn=functions[0].name(), update_fn=functions[1].name(), nx=model.nx,
                  nu=model.nu, ny=model.ny, dt=repr(float(model.dt)), real=real,
                  gate_threshold=repr(gate.c_threshold()), gate_recover_after=gate.recover_after,
                  gate_inflation=repr(gate.inflation),
                  max_inflation=repr(MAX_INFLATION["float32" if real == "float" else "float64"]),
                  gate_header_sha256=templates.gate_header_digest(),
                  workspace_bound=bound, **{f"sz_{k}": v for k, v in work.items()})
    status_h = templates.write_status_header(out_dir)
    gate_h = templates.write_gate_header(out_dir)
    api_h = templates.write(out_dir, "ukf_api.h.in", f"{prefix}_api.h", values)
    api_c = templates.write(out_dir, "ukf_api.c.in", f"{prefix}_api.c", values)
    return (out_dir / casadi_c, out_dir / f"{prefix}_casadi.h", api_c, api_h, status_h, gate_h)
