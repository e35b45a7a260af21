"""The one-step residual of a prior with effects, its exact features, and cross-validation sums.

The one-step residual of a model with effect parameters ``theta`` is a derivative error,

    r_k(theta) = wrap(z_{k+1} - RK4_{dt_k}[f_prior + effects(theta)](z_k, u_k)) / dt_k   (N, nx)

and its features are ``Phi_k = d RK4 / d theta / dt_k`` (N, nx, m), exact CasADi derivatives
through the RK4 step, so ``r(theta + d) ~ r(theta) - Phi d``: a linear least-squares problem in
the library's parameters (with a damped, bounded refinement, :mod:`.refine`, for effects that
are nonlinear in their parameter, such as a mass). Rows are the residual states only (the
kinematic rows are exact), each weighted by ``1 / sigma_s``, the state's noise floor, so all
rows are in units of "noise standard deviations" and a pure-noise residual has mean square 1 per row.
:class:`FitData` carries the weighted residual, the features and each row's cross-validation fold
(:func:`fold_labels`: one fold per run when runs are pooled, else contiguous time blocks: the
one-step residual of smoothed observations is correlated in time, random folds would leak). The
selection that uses these is in :mod:`~learnest_codegen.diagnosis.selection`.

Parameter uncertainty is a moving-block bootstrap over contiguous time blocks at the final fit,
which accounts for the residual's autocorrelation (an i.i.d. covariance would understate it by
the square root of the correlation length).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import casadi as cs
import numpy as np

from ..errors import ShapeError
from ..integrators import rk4_step
from ..systems import System
from ..systems.backends import CasadiOps
from .effects import Effect, corrected_dynamics


@dataclass(frozen=True)
class FitSettings:
    """Settings of the sparse cross-validated selection (see the module docstring)."""

    folds: int = 10
    max_effects: int = 6
    t_min: float = 2.5
    min_gain: float = 0.01
    min_size: float = 0.1
    spurious_factor: float = 2.0
    alias_cos: float = 0.95  # |cosine| of weighted features above which two effects are aliases
    duplicate_cos: float = 0.99999  # ... above which the later one is dropped as a duplicate
    scan: int = 3  # candidates tested per step, best held-out SSE first
    gap_noise: float = 2.0  # entry also needs a gain above this many stds of a pure-noise SSE
    swap_tol: float = 1e-6  # relative SSE change within which two effect sets are equivalent
    refine_iterations: int = 20  # Levenberg-Marquardt iterations (see refine.py)
    max_step: float = 0.5  # per-step limit, relative to a parameter's value (or its scale)
    bound: float = 100.0  # a prior parameter stays within [p / bound, p * bound]
    by_run: int = 3  # with this many runs or more, cross-validation folds are the runs
    bootstrap: int = 300
    blocks: int = 24
    seed: int = 0

    def __post_init__(self) -> None:
        if self.folds < 3 or self.max_effects < 1 or self.blocks < 4 or self.bootstrap < 10 \
                or not self.bound > 1 or not 0 < self.max_step <= 10 or self.by_run < 2:
            raise ValueError(f"FitSettings: need folds >= 3, max_effects >= 1, blocks >= 4, "
                             f"bootstrap >= 10, bound > 1, 0 < max_step <= 10, by_run >= 2; got {self}")

    def to_json(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Pairs:
    """Consecutive sample pairs of one or more runs (pairs never cross runs).

    Attributes
    ----------
    x, x_next : (N, nx) states at ``t_k`` and ``t_{k+1}``.
    u : (N, nu) input held over the step.
    dt : (N,) step [s].
    t : (N,) time of ``x`` [s], from the start of its run.
    segment : (N,) index of the run each pair comes from.
    """

    x: np.ndarray
    u: np.ndarray
    x_next: np.ndarray
    dt: np.ndarray
    t: np.ndarray
    segment: np.ndarray

    def __len__(self) -> int:
        return self.x.shape[0]

    @classmethod
    def from_states(cls, segments: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> "Pairs":
        """From ``(t (T,), z (T, nx), u (T, nu))`` per run."""
        parts = []
        for i, (t, z, u) in enumerate(segments):
            t, z, u = np.asarray(t, float), np.asarray(z, float), np.asarray(u, float)
            if z.ndim != 2 or u.ndim != 2 or len(t) != len(z) or len(u) != len(z) or len(z) < 2:
                raise ShapeError(f"run {i}: expected t (T,), z (T, nx), u (T, nu) with T >= 2, "
                                 f"got {t.shape}, {z.shape}, {u.shape}")
            if not (np.isfinite(z).all() and np.isfinite(u).all()):
                raise ShapeError(f"run {i}: states and inputs must be finite")
            parts.append((z[:-1], u[:-1], z[1:], np.diff(t), t[:-1] - t[0], np.full(len(t) - 1, i)))
        return cls(*(np.concatenate(a) for a in zip(*parts)))

    def subset(self, mask: np.ndarray) -> "Pairs":
        return Pairs(self.x[mask], self.u[mask], self.x_next[mask], self.dt[mask], self.t[mask],
                     self.segment[mask])


def one_step(system: System, effects: Sequence[Effect], theta: Sequence[float], pairs: Pairs,
             with_features: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Residual ``r (N, nx)`` [state unit / s] and features ``Phi (N, nx, m)`` at ``theta``."""
    m, nx = len(effects), system.nx
    x, u = cs.SX.sym("x", nx), cs.SX.sym("u", system.nu)
    dt, th = cs.SX.sym("dt"), cs.SX.sym("theta", max(m, 1))
    fn = corrected_dynamics(system, effects, [th[i] for i in range(m)])
    f = lambda xx, uu: cs.vertcat(*fn(CasadiOps, [xx[i] for i in range(nx)],  # noqa: E731
                                      [uu[j] for j in range(system.nu)], system.params))
    x_next = rk4_step(f, x, u, dt)
    outs = [x_next] + ([cs.reshape(cs.jacobian(x_next, th)[:, :m], nx * m, 1)] if with_features else [])
    step = cs.Function("step", [x, u, dt, th], outs)
    N = len(pairs)
    theta_col = np.zeros((max(m, 1), 1))
    theta_col[:m, 0] = np.asarray(theta, float)
    res = step.map(N)(pairs.x.T, pairs.u.T, pairs.dt[None, :], np.repeat(theta_col, N, axis=1))
    res = res if isinstance(res, (list, tuple)) else [res]
    predicted = np.asarray(res[0]).T
    diff = pairs.x_next - predicted
    for name in system.periodic_states:
        i = system.state_names.index(name)
        diff[:, i] = np.angle(np.exp(1j * diff[:, i]))
    r = diff / pairs.dt[:, None]
    if not with_features:
        return r, np.zeros((N, nx, 0))
    J = np.asarray(res[1]).T.reshape(N, m, nx).transpose(0, 2, 1)  # column-major reshape
    return r, J / pairs.dt[:, None, None]


@dataclass
class FitData:
    """Weighted residual and features on the residual states, ready for selection.

    ``R (N, S)`` and ``Phi (N, S, m)`` are divided by ``sigma (S,)``. ``spurious (m,)`` is what
    each feature alone explains of a calibration run of the exact prior (noise units; 0 when no
    calibration).
    """

    R: np.ndarray
    Phi: np.ndarray
    sigma: np.ndarray
    spurious: np.ndarray
    labels: np.ndarray | None = None  # (N,) cross-validation fold of each row

    def folds(self, k: int) -> tuple[np.ndarray, int]:
        """Fold label per row and the number of folds (``k`` contiguous blocks unless given)."""
        if self.labels is not None:
            return self.labels, int(self.labels.max()) + 1
        return _fold_labels(self.R.shape[0], k), k

    def with_R(self, R: np.ndarray) -> "FitData":
        return FitData(R, self.Phi, self.sigma, self.spurious, self.labels)

    def columns(self, idx: Sequence[int]) -> "FitData":
        idx = list(idx)
        return FitData(self.R, self.Phi[:, :, idx], self.sigma, self.spurious[idx], self.labels)

    @property
    def floor(self) -> float:
        """Expected sum of squares of pure noise (1 per row)."""
        return float(self.R.size)


def weighted(r: np.ndarray, Phi: np.ndarray, rows: Sequence[int], sigma: np.ndarray,
             spurious: np.ndarray | None = None, labels: np.ndarray | None = None) -> FitData:
    """Select the residual-state ``rows`` and divide by their noise floor ``sigma``."""
    rows = list(rows)
    R = r[:, rows] / sigma
    P = Phi[:, rows, :] / sigma[None, :, None]
    return FitData(R, P, np.asarray(sigma, float),
                   np.zeros(P.shape[2]) if spurious is None else np.asarray(spurious, float), labels)


def fold_labels(pairs: "Pairs", folds: int, by_run: int = 3) -> tuple[np.ndarray, str]:
    """Cross-validation folds: one per run when there are at least ``by_run`` runs (a held-out
    run is the honest test of a pooled fit), else ``folds`` contiguous time blocks."""
    runs = np.unique(pairs.segment)
    if len(runs) >= by_run:
        return np.searchsorted(runs, pairs.segment), f"by run ({len(runs)} runs)"
    return _fold_labels(len(pairs), folds), f"{folds} contiguous time blocks"


def single_feature_size(data: FitData) -> np.ndarray:
    """(m,) RMS of each feature's least-squares term alone, in noise units (~|cosine| to R)."""
    Phi = data.Phi.reshape(-1, data.Phi.shape[2])
    R = data.R.ravel()
    norm = np.linalg.norm(Phi, axis=0)
    return np.abs(Phi.T @ R) / np.maximum(norm, 1e-300) / np.sqrt(R.size)


def _grams(data: FitData, labels: np.ndarray | None = None, groups: int | None = None,
           settings: "FitSettings | None" = None):
    if labels is None:
        labels, groups = data.folds((settings or FitSettings()).folds)
    m = data.Phi.shape[2]
    G, b, c = np.zeros((groups, m, m)), np.zeros((groups, m)), np.zeros(groups)
    for g in range(groups):
        P, R = data.Phi[labels == g], data.R[labels == g]
        G[g] = np.einsum("ksi,ksj->ij", P, P)
        b[g] = np.einsum("ksi,ks->i", P, R)
        c[g] = float(np.sum(R**2))
    return G, b, c


def _fold_labels(n: int, k: int) -> np.ndarray:
    return np.minimum((np.arange(n) * k) // max(n, 1), k - 1)


def _cv_sse(G, b, c, idx: list[int]) -> np.ndarray:
    """Held-out SSE per fold of least squares on the columns ``idx``."""
    if not idx:
        return c.copy()
    Gt, bt = G.sum(0), b.sum(0)
    out = np.empty(len(c))
    for f in range(len(c)):
        A = (Gt - G[f])[np.ix_(idx, idx)]
        rhs = (bt - b[f])[idx]
        theta = np.linalg.lstsq(A + 1e-12 * np.trace(A) / len(idx) * np.eye(len(idx)), rhs, rcond=None)[0]
        out[f] = c[f] - 2 * theta @ b[f][idx] + theta @ G[f][np.ix_(idx, idx)] @ theta
    return out


def deduplicate(data: FitData, settings: FitSettings) -> tuple[list[int], dict[int, int]]:
    """Drop all-zero features and exact duplicates (|cos| > duplicate_cos) of earlier ones."""
    Phi = data.Phi.reshape(-1, data.Phi.shape[2])
    norm = np.linalg.norm(Phi, axis=0)
    keep, dup = [], {}
    for j in range(Phi.shape[1]):
        if not norm[j] > 1e-12 * max(norm.max(), 1e-300):
            continue
        for i in keep:
            if abs(Phi[:, i] @ Phi[:, j]) / (norm[i] * norm[j]) > settings.duplicate_cos:
                dup[j] = i
                break
        else:
            keep.append(j)
    return keep, dup


def aliases(data: FitData, j: int, candidates: Sequence[int], settings: FitSettings) -> list[int]:
    """Candidates whose weighted feature is nearly collinear with feature ``j`` on these data."""
    Phi = data.Phi.reshape(-1, data.Phi.shape[2])
    norm = np.linalg.norm(Phi, axis=0)
    return [i for i in candidates if i != j and norm[i] > 0 and
            abs(Phi[:, i] @ Phi[:, j]) / (norm[i] * norm[j]) > settings.alias_cos]


@dataclass(frozen=True)
class Baseline:
    """The prior's held-out residual and each candidate's held-out score alone (noise units).

    ``gap`` is the held-out sum of squares above the floor (at least 1 % of the floor: a smaller
    "gap" is none), ``total`` the held-out sum of squares, ``single`` each candidate's held-out
    share of the gap when fitted alone, ``pool`` the candidates left after :func:`deduplicate`.
    """

    gap: float
    total: float
    single: dict[int, float]
    pool: list[int]
    duplicates: dict[int, int]


def baseline(data: FitData, settings: FitSettings = FitSettings()) -> Baseline:
    """Held-out statistics of the prior's residual and of each candidate alone."""
    G, b, c = _grams(data, settings=settings)
    pool, dup = deduplicate(data, settings)
    total = float(c.sum())
    gap = max(total - data.floor, 0.01 * data.floor)
    # A score above 1 means the feature also explains part of the floor (observer artefacts).
    single = {j: float(np.clip((total - _cv_sse(G, b, c, [j]).sum()) / gap, 0.0, 1.0)) for j in pool}
    return Baseline(gap, total, single, pool, dup)


def _term_size(data: FitData, idx: list[int]) -> np.ndarray:
    """RMS (noise units) of each term of the in-sample least-squares fit on columns ``idx``."""
    P = data.Phi[:, :, idx].reshape(-1, len(idx))
    theta = np.linalg.lstsq(P, data.R.ravel(), rcond=None)[0]
    return np.sqrt(np.mean((P * theta) ** 2, axis=0))


def least_squares(data: FitData) -> np.ndarray:
    """Parameter step ``d`` minimising ``||R - Phi d||``."""
    P = data.Phi.reshape(-1, data.Phi.shape[2])
    return np.linalg.lstsq(P, data.R.ravel(), rcond=None)[0]


def block_bootstrap(data: FitData, settings: FitSettings) -> np.ndarray:
    """(B, m) bootstrap draws of the least-squares step over contiguous time blocks."""
    n, m = data.R.shape[0], data.Phi.shape[2]
    blocks = min(settings.blocks, n)
    G, b, _ = _grams(data, _fold_labels(n, blocks), blocks)
    rng = np.random.default_rng(settings.seed)
    draws = np.empty((settings.bootstrap, m))
    for i in range(settings.bootstrap):
        pick = rng.integers(0, blocks, size=blocks)
        draws[i] = np.linalg.lstsq(G[pick].sum(0), b[pick].sum(0), rcond=None)[0]
    return draws
