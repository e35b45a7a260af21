"""Cross-validated, bounded least squares on the weighted one-step residual.

:class:`FitData` holds the residual ``R (N, S)`` and the features ``Phi (N, S, m)`` of the
residual states, each divided by the state's noise floor (so a pure-noise residual has mean
square 1 per row), each row's cross-validation fold and run, and each column's admissible
*step* ``[lo, hi]`` from the current parameters to the edge of its physical range (see
:class:`~learnest_codegen.diagnosis.effects.Effect`). Every fit here is a bounded least-squares
problem: an unconstrained solve when it lands inside the box, else ``scipy.optimize.lsq_linear``
(``bvls``) on the Cholesky factor of the normal equations. Folds come from :func:`fold_labels`:
contiguous time blocks within each run (the one-step residual of smoothed observations is
correlated in time; random folds would leak).

Parameter uncertainty is a moving-block bootstrap over contiguous time blocks at the final fit,
which accounts for the residual's autocorrelation (an i.i.d. covariance would understate it by
the square root of the correlation length).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.linalg import cho_factor, solve_triangular
from scipy.optimize import lsq_linear

from .fit import FitSettings, Pairs


@dataclass
class FitData:
    """Weighted residual and features on the residual states, ready for selection.

    ``R (N, S)`` and ``Phi (N, S, m)`` are divided by ``sigma (S,)``. ``spurious (m,)`` is what
    each feature alone explains of a calibration run of the exact prior (noise units; 0 when no
    calibration). ``lo, hi (m,)``: the admissible step of each column from the current
    parameters (``-inf, inf`` when unbounded). ``runs (N,)``: the run of each row.
    """

    R: np.ndarray
    Phi: np.ndarray
    sigma: np.ndarray
    spurious: np.ndarray
    labels: np.ndarray | None = None  # (N,) cross-validation fold of each row
    lo: np.ndarray | None = None
    hi: np.ndarray | None = None
    runs: np.ndarray | None = None

    def __post_init__(self) -> None:
        m = self.Phi.shape[2]
        self.lo = np.full(m, -np.inf) if self.lo is None else np.asarray(self.lo, float)
        self.hi = np.full(m, np.inf) if self.hi is None else np.asarray(self.hi, float)

    def folds(self, k: int) -> tuple[np.ndarray, int]:
        """Fold label per row and the number of folds (``k`` contiguous blocks unless given)."""
        if self.labels is not None:
            return self.labels, int(self.labels.max()) + 1
        return _fold_labels(self.R.shape[0], k), k

    def with_R(self, R: np.ndarray) -> "FitData":
        return FitData(R, self.Phi, self.sigma, self.spurious, self.labels, self.lo, self.hi, self.runs)

    def columns(self, idx: Sequence[int]) -> "FitData":
        idx = list(idx)
        return FitData(self.R, self.Phi[:, :, idx], self.sigma, self.spurious[idx], self.labels,
                       self.lo[idx], self.hi[idx], self.runs)

    @property
    def floor(self) -> float:
        """Expected sum of squares of pure noise (1 per row)."""
        return float(self.R.size)


def weighted(r: np.ndarray, Phi: np.ndarray, rows: Sequence[int], sigma: np.ndarray,
             spurious: np.ndarray | None = None, labels: np.ndarray | None = None,
             lo: np.ndarray | None = None, hi: np.ndarray | None = None,
             runs: np.ndarray | None = None) -> FitData:
    """Select the residual-state ``rows`` and divide by their noise floor ``sigma``."""
    rows = list(rows)
    R = r[:, rows] / sigma
    P = Phi[:, rows, :] / sigma[None, :, None]
    return FitData(R, P, np.asarray(sigma, float),
                   np.zeros(P.shape[2]) if spurious is None else np.asarray(spurious, float), labels,
                   lo, hi, runs)


def fold_labels(pairs: Pairs, folds: int) -> tuple[np.ndarray, str]:
    """Cross-validation folds: contiguous blocks of time within each run, never across runs;
    ``folds`` in all for one run, else ``ceil(folds / runs)`` (at least 2) per run. A fold is a
    stretch of one run, so a held-out gain must carry over in time and, the folds of every run
    together, across runs (whether each effect is the same on every run is tested apart)."""
    runs = np.unique(pairs.segment)
    per = folds if len(runs) == 1 else max(int(np.ceil(folds / len(runs))), 2)
    labels = np.empty(len(pairs), dtype=int)
    for i, s in enumerate(runs):
        rows = np.flatnonzero(pairs.segment == s)
        labels[rows] = i * per + _fold_labels(len(rows), per)
    if len(runs) == 1:
        return labels, f"{per} contiguous time blocks"
    return labels, f"{per} contiguous time blocks in each of {len(runs)} runs"


def single_feature_size(data: FitData) -> np.ndarray:
    """(m,) RMS of each feature's least-squares term alone, in noise units (~|cosine| to R)."""
    Phi = data.Phi.reshape(-1, data.Phi.shape[2])
    R = data.R.ravel()
    norm = np.linalg.norm(Phi, axis=0)
    return np.abs(Phi.T @ R) / np.maximum(norm, 1e-300) / np.sqrt(R.size)


def grams(data: FitData, labels: np.ndarray | None = None, groups: int | None = None,
          settings: FitSettings | None = None):
    """Per group of rows (default: the folds): ``G (g, m, m)``, ``b (g, m)``, ``c (g,)``."""
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


def box_solve(A: np.ndarray, rhs: np.ndarray, lo: np.ndarray | None = None,
              hi: np.ndarray | None = None) -> np.ndarray:
    """``argmin theta' A theta - 2 rhs' theta`` over ``lo <= theta <= hi`` (``A`` symmetric PSD).

    The unconstrained solution when it lies in the box, else bounded least squares on the
    Cholesky factor ``A = L L'``: ``|| L' theta - L^-1 rhs ||^2`` is the same objective. Solved
    in units where every column has unit norm (``A``'s diagonal scaled to 1): a delay in seconds
    and an inertia change in kg m^2 differ in scale by 1e8, and a solve in raw units would lose
    the small columns to the large one's rounding."""
    scale = np.sqrt(np.clip(np.diag(np.asarray(A, float)), 0.0, None))
    scale[~(scale > 0)] = 1.0
    A = np.asarray(A, float) / scale[:, None] / scale[None, :]
    rhs = np.asarray(rhs, float) / scale
    if lo is not None:
        lo, hi = np.asarray(lo, float) * scale, np.asarray(hi, float) * scale
    return _box_solve(A, rhs, lo, hi) / scale


def _box_solve(A: np.ndarray, rhs: np.ndarray, lo: np.ndarray | None, hi: np.ndarray | None) -> np.ndarray:
    n = len(rhs)
    ridge = 1e-12 * max(float(np.trace(A)) / max(n, 1), 1e-300)
    theta = np.linalg.lstsq(A + ridge * np.eye(n), rhs, rcond=None)[0]
    inside = lo is None or (np.all(theta >= lo - 1e-12 * (1 + np.abs(lo)))
                            and np.all(theta <= hi + 1e-12 * (1 + np.abs(hi))))
    if inside:
        return theta
    for scale in (1.0, 1e3, 1e6):
        try:
            L, _ = cho_factor(A + scale * ridge * np.eye(n), lower=True)
            break
        except np.linalg.LinAlgError:
            continue
    else:  # not even a ridge makes it definite: clip the unconstrained solution
        return np.clip(theta, lo, hi)
    L = np.tril(L)
    lo_f = np.where(np.isfinite(lo), lo, 0.0)
    upper = np.where(np.isfinite(lo), np.maximum(hi, lo_f + 1e-15 * (1 + np.abs(lo_f))), hi)
    return lsq_linear(L.T, solve_triangular(L, rhs, lower=True), bounds=(lo, upper), method="bvls").x


def cv_sse(G, b, c, idx: Sequence[int], lo: np.ndarray | None = None,
           hi: np.ndarray | None = None) -> np.ndarray:
    """Held-out SSE per fold of bounded least squares on the columns ``idx``; ``lo, hi`` are the
    full-length step bounds (sliced here)."""
    idx = list(idx)
    if not idx:
        return c.copy()
    Gt, bt = G.sum(0), b.sum(0)
    box = (lo[idx], hi[idx]) if lo is not None else (None, None)
    out = np.empty(len(c))
    for f in range(len(c)):
        theta = box_solve((Gt - G[f])[np.ix_(idx, idx)], (bt - b[f])[idx], *box)
        out[f] = c[f] - 2 * theta @ b[f][idx] + theta @ G[f][np.ix_(idx, idx)] @ theta
    return out


def fit_step(data: FitData, idx: Sequence[int], G=None, b=None) -> np.ndarray:
    """In-sample bounded least-squares step on the columns ``idx`` (all rows)."""
    idx = list(idx)
    if G is None:
        P = data.Phi[:, :, idx].reshape(-1, len(idx))
        return box_solve(P.T @ P, P.T @ data.R.ravel(), data.lo[idx], data.hi[idx])
    return box_solve(G[np.ix_(idx, idx)], b[idx], data.lo[idx], data.hi[idx])


def term_size(data: FitData, idx: Sequence[int]) -> np.ndarray:
    """RMS (noise units) of each term of the in-sample bounded fit on columns ``idx``."""
    idx = list(idx)
    P = data.Phi[:, :, idx].reshape(-1, len(idx))
    theta = fit_step(data, idx)
    return np.sqrt(np.mean((P * theta) ** 2, axis=0))


def deduplicate(data: FitData, settings: FitSettings,
                keep_all: Sequence[int] = ()) -> tuple[list[int], dict[int, int]]:
    """Drop all-zero features and exact duplicates (|cos| > duplicate_cos) of earlier ones with
    the same admissible range (a Coulomb friction >= 0 and an actuator offset of either sign have
    the same feature on a robot that never reverses, but only the offset can push); the columns
    ``keep_all`` (effects also linearised elsewhere, at their starts) are kept."""
    Phi = data.Phi.reshape(-1, data.Phi.shape[2])
    norm = np.linalg.norm(Phi, axis=0)
    keep, dup = [], {}
    for j in range(Phi.shape[1]):
        if j in keep_all:
            keep.append(j)
            continue
        if not norm[j] > 1e-12 * max(norm.max(), 1e-300):
            continue
        for i in keep:
            if i in keep_all:
                continue
            cos = Phi[:, i] @ Phi[:, j] / (norm[i] * norm[j])
            if abs(cos) > settings.duplicate_cos and _covers(data, i, j, cos):
                dup[j] = i
                break
        else:
            keep.append(j)
    return keep, dup


def _covers(data: FitData, i: int, j: int, cos: float) -> bool:
    """Whether column ``i`` can stand for column ``j``: every sign ``j``'s parameter may take,
    ``i``'s may take too (mirrored when ``cos < 0``)."""
    lo_j, hi_j = (data.lo[j], data.hi[j]) if cos > 0 else (-data.hi[j], -data.lo[j])
    return bool((lo_j >= 0 or data.lo[i] < 0) and (hi_j <= 0 or data.hi[i] > 0))


def aliases(data: FitData, j: int, candidates: Sequence[int], settings: FitSettings) -> list[int]:
    """Candidates whose weighted feature is nearly collinear with feature ``j`` on these data."""
    Phi = data.Phi.reshape(-1, data.Phi.shape[2])
    norm = np.linalg.norm(Phi, axis=0)
    if not norm[j] > 0:
        return []
    return [i for i in candidates if i != j and norm[i] > 0 and
            abs(Phi[:, i] @ Phi[:, j]) / (norm[i] * norm[j]) > settings.alias_cos]


@dataclass(frozen=True)
class Baseline:
    """The prior's held-out residual and each candidate's held-out score alone (noise units).

    ``gap`` is the held-out sum of squares above the floor (at least 1 % of the floor: a smaller
    "gap" is none), ``total`` the held-out sum of squares, ``single`` each candidate's held-out
    share of the gap when fitted alone (within its physical range), ``pool`` the candidates left
    after :func:`deduplicate`.
    """

    gap: float
    total: float
    single: dict[int, float]
    pool: list[int]
    duplicates: dict[int, int]


def baseline(data: FitData, settings: FitSettings = FitSettings(), keep_all: Sequence[int] = ()) -> Baseline:
    """Held-out statistics of the prior's residual and of each candidate alone (``keep_all``: see
    :func:`deduplicate`)."""
    G, b, c = grams(data, settings=settings)
    pool, dup = deduplicate(data, settings, keep_all)
    total = float(c.sum())
    gap = max(total - data.floor, 0.01 * data.floor)
    # A score above 1 means the feature also explains part of the floor (observer artefacts).
    single = {j: float(np.clip((total - cv_sse(G, b, c, [j], data.lo, data.hi).sum()) / gap, 0.0, 1.0))
              for j in pool}
    return Baseline(gap, total, single, pool, dup)


def block_bootstrap(data: FitData, settings: FitSettings) -> np.ndarray:
    """(B, m) bootstrap draws of the bounded least-squares step over contiguous time blocks."""
    n, m = data.R.shape[0], data.Phi.shape[2]
    blocks = min(settings.blocks, n)
    G, b, _ = grams(data, _fold_labels(n, blocks), blocks)
    rng = np.random.default_rng(settings.seed)
    draws = np.empty((settings.bootstrap, m))
    for i in range(settings.bootstrap):
        pick = rng.integers(0, blocks, size=blocks)
        draws[i] = box_solve(G[pick].sum(0), b[pick].sum(0), data.lo, data.hi)
    return draws
