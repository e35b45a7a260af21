"""The UKF as CasADi functions and as generated C with a small hand-written C API.

:func:`ukf_step_function` writes FilterPy 2.0.0's predict + update as one SX graph, operation
for operation (Merwe sigma points from the upper Cholesky factor of ``(lambda + n) P``, the
unscented transform, re-drawing the sigma points from the prior, an explicit ``S^-1`` and
``P - K S K^T``), so the compiled filter matches the reference to rounding.
:func:`generate_ukf` has CasADi write the C of the model alone (``F`` and ``h``, one copy each)
into an estimator folder whose C kit (``learnest_ukf.h``) runs the same predict and masked
update operation for operation through a loop over the sigma points, and the samples, missing
outputs, gate, covariance guards and API around them (``codegen/emit.py``, docs/guide/c_kit.md);
the CasADi functions here are its tested reference.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import casadi as cs
import numpy as np

from ..errors import SettingsError
from ..estimators.precision import check_precision
from ..estimators.ukf import FLOAT32_MIN_ALPHA, UKFSettings
from ..export import DiscreteModel
from ..runtime.manifest import GeneratedEstimator
from .emit import emit, resolve_prefix
from .kalman import kalman_design

ARG_NAMES = ["x", "P", "u", "y", "Q", "R"]
RES_NAMES = ["x_post", "P_post"]
PREDICT_ARGS, PREDICT_RES = ["x", "P", "u", "Q"], ["x_prior", "P_prior"]
UPDATE_ARGS, UPDATE_RES = ["x", "P", "u", "y", "R", "mask"], ["x_post", "P_post", "d2"]


def default_prefix(model: DiscreteModel) -> str:
    """``<system>_<kind>_ukf``: the default name of the generated functions."""
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


def generate_ukf(model: DiscreteModel, settings: UKFSettings, out_dir: Path, *,
                 prefix: str | None = None, model_hash: str = "",
                 force: bool = False, precision: str = "float64",
                 name: str = "ukf") -> GeneratedEstimator:
    """Write, compile and describe a C UKF for ``model`` in ``out_dir`` (``codegen/emit.py``).

    ``precision`` (``"float64"`` or ``"float32"``) is the C real type; ``name`` the estimator's
    (its entry in ``compilation.ESTIMATORS``: the manifest's ``estimator``, the default
    prefix's). Unchanged inputs reuse the library unless ``force``. Raises
    :class:`BuildError` with the compiler's stderr on failure.
    """
    check_precision(precision, "generate_ukf")
    if precision == "float32" and settings.alpha < FLOAT32_MIN_ALPHA:
        raise SettingsError(f"generate_ukf: a float32 UKF needs alpha >= {FLOAT32_MIN_ALPHA}, got "
                         f"{settings.alpha}: with a small alpha the sigma-point weights cancel "
                         "(W0 = -99 at alpha 0.1, nx 4) and single precision loses the covariance "
                         "(cartpole: +12 % MSE); alpha 0.5 costs +0.14 %")
    prefix = resolve_prefix(prefix, model, name, precision)
    settings.validate_for(model)
    x, u = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    functions = (cs.Function(f"{prefix}_model_F", [x, u], [cs.cse(model.F(x, u))], ["x", "u"], ["F"]),
                 cs.Function(f"{prefix}_model_h", [x, u], [cs.cse(model.h(x, u))], ["x", "u"], ["h"]))
    design = kalman_design(
        model, settings, estimator=name, title="Unscented Kalman Filter", kit="learnest_ukf.h",
        functions=functions,
        hooks={"LEARNEST_MODEL_F": functions[0].name(), "LEARNEST_MODEL_H": functions[1].name(),
               "LEARNEST_UKF_ALPHA": repr(float(settings.alpha)),
               "LEARNEST_UKF_BETA": repr(float(settings.beta)),
               "LEARNEST_UKF_KAPPA": repr(float(settings.kappa))},
        precision=precision,
        description="The filter: FilterPy 2.0.0's predict and update on Merwe scaled sigma points "
                    f"(alpha {settings.alpha}, beta {settings.beta}, kappa {settings.kappa}), "
                    "generated operation for operation by the C kit (learnest_ukf.h) over the "
                    "model's generated code (<prefix>_model.c, one call per sigma point, or one per "
                    "4 (double) or 8 (float) points where the compiler vectors: the same bits), so it "
                    "equals FilterPy to rounding (tests/test_ukf.py)",
        predicted=("zp", "zp and S = P_zz + R the predicted output and its covariance"))
    # F also as a batch over the sigma points where its code allows (learnest_simd.h).
    design = dataclasses.replace(design, batch=(functions[0].name(),))
    return emit(model, design, Path(out_dir), prefix=prefix, model_hash=model_hash, force=force)

