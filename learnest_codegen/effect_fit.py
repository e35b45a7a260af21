"""Fitting an effect library to the one-step residual: sparse, cross-validated, honest.

The one-step residual of a model with effect parameters ``theta`` is a derivative error,

    r_k(theta) = wrap(z_{k+1} - RK4_{dt_k}[f_prior + effects(theta)](z_k, u_k)) / dt_k   (N, nx)

and its features are ``Phi_k = d RK4 / d theta / dt_k`` (N, nx, m), exact CasADi derivatives
through the RK4 step, so ``r(theta + d) ~ r(theta) - Phi d``: a linear least-squares problem in
the library's parameters (with a few Gauss-Newton iterations for effects that are nonlinear in
their parameter, such as a mass). Rows are the residual states only (the kinematic rows are
exact), each weighted by ``1 / sigma_s``, the state's noise floor, so all rows are in units of
"noise standard deviations" and a pure-noise residual has mean square 1 per row.

Selection (:func:`fit_effects`) is forward stepwise over the library with K-fold cross-validation on
contiguous time blocks (the one-step residual of smoothed observations is correlated in time;
random folds would leak). A candidate enters only if all of these hold:

* its held-out improvement is consistent over folds: the t statistic of the K folds' relative
  held-out SSE reductions (each fold's reduction over its own SSE) exceeds ``t_min``. This is
  the cross-validated analogue of a one-standard-error rule, on paired differences (far less
  noisy than the fold errors themselves) and relative ones (a drag that grows with v^2 gains
  very different absolute amounts in slow and fast folds, but a similar fraction in each);
* it explains at least ``min_gain`` of the gap held out;
* its size (RMS of its fitted term, in noise units) exceeds ``min_size`` and ``spurious_factor``
  times what the same feature "explains" on a calibration run of the exact prior through the
  same observer (:attr:`FitData.spurious`). An observer's errors are themselves correlated with
  the state (a smoother lags in hard accelerations), so a feature can be genuinely predictive of
  the residual of a perfect model; only an effect larger than that artefact is a finding.

Parameter uncertainty is a moving-block bootstrap over contiguous time blocks at the final fit,
which accounts for the residual's autocorrelation (an i.i.d. covariance would understate it by
the square root of the correlation length).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import casadi as cs
import numpy as np

from .effects import Effect, corrected_dynamics
from .errors import ShapeError
from .integrators import rk4_step
from .systems import System
from .systems.backends import CasadiOps


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
    gauss_newton: int = 10
    bootstrap: int = 300
    blocks: int = 24
    seed: int = 0

    def __post_init__(self) -> None:
        if self.folds < 3 or self.max_effects < 1 or self.blocks < 4 or self.bootstrap < 10:
            raise ValueError(f"FitSettings: need folds >= 3, max_effects >= 1, blocks >= 4, "
                             f"bootstrap >= 10; got {self}")

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

    @property
    def floor(self) -> float:
        """Expected sum of squares of pure noise (1 per row)."""
        return float(self.R.size)


def weighted(r: np.ndarray, Phi: np.ndarray, rows: Sequence[int], sigma: np.ndarray,
             spurious: np.ndarray | None = None) -> FitData:
    """Select the residual-state ``rows`` and divide by their noise floor ``sigma``."""
    rows = list(rows)
    R = r[:, rows] / sigma
    P = Phi[:, rows, :] / sigma[None, :, None]
    return FitData(R, P, np.asarray(sigma, float),
                   np.zeros(P.shape[2]) if spurious is None else np.asarray(spurious, float))


def single_feature_size(data: FitData) -> np.ndarray:
    """(m,) RMS of each feature's least-squares term alone, in noise units (~|cosine| to R)."""
    Phi = data.Phi.reshape(-1, data.Phi.shape[2])
    R = data.R.ravel()
    norm = np.linalg.norm(Phi, axis=0)
    return np.abs(Phi.T @ R) / np.maximum(norm, 1e-300) / np.sqrt(R.size)


def _grams(data: FitData, labels: np.ndarray, groups: int):
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
    G, b, c = _grams(data, _fold_labels(data.R.shape[0], settings.folds), settings.folds)
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


@dataclass
class EffectFit:
    """Selected effects with their parameters, uncertainty and held-out shares.

    Attributes
    ----------
    chosen : indices into the library, in the order selected.
    theta : (len(chosen),) fitted parameters; ``theta_std`` their block-bootstrap stds.
    explained : (len(chosen),) held-out share of the gap each explains: ``explained_total`` split in
        proportion to the held-out loss when the effect is dropped from the final set.
    scores : (len(chosen),) held-out share each explains alone (at the prior).
    explained_total : held-out share of the gap explained by all of them together.
    gap, total : held-out sums of squares of the prior's residual above the floor, and in all.
    steps, rejected : the selection path (diagnostics).
    aliases : per chosen effect, library indices indistinguishable from it on these data.
    duplicates : library index -> the index it duplicates exactly on these data.
    """

    chosen: list[int]
    theta: np.ndarray
    theta_std: np.ndarray
    explained: np.ndarray
    scores: np.ndarray
    explained_total: float
    gap: float
    total: float
    steps: list[dict]
    rejected: dict | None
    aliases: list[list[int]]
    duplicates: dict[int, int]


def fit_effects(system: System, effects: Sequence[Effect], pairs: Pairs, rows: Sequence[int],
                sigma: np.ndarray, spurious: np.ndarray | None = None,
                settings: FitSettings = FitSettings()) -> EffectFit:
    """Forward selection with relinearisation: after each accepted effect the chosen parameters
    are refined by Gauss-Newton on the full nonlinear one-step residual, and the residual and all
    features are re-evaluated there, so a nonlinear effect (a 50 % mass error) fitted to first
    order does not leave a curvature residual that a spurious second effect would then "explain".
    """
    m = len(effects)
    theta = np.zeros(m)
    r, J = one_step(system, effects, theta, pairs)
    data0 = weighted(r, J, rows, sigma, spurious)
    first = baseline(data0, settings)
    gap, total, pool, duplicates = first.gap, first.total, first.pool, first.duplicates
    groups = _groups(effects)
    # a multi-parameter effect (a group) is a candidate as a whole, through its first column
    pool = [j for j in pool if groups[j][0] == j and all(k in pool for k in groups[j])]
    chosen, steps, rejected, dropped = [], [], None, set()
    data = data0
    while len(chosen) < settings.max_effects:
        sel = _next(data, chosen, [j for j in pool if j not in dropped], gap, settings, groups)
        if sel["accept"] is False:
            rejected = sel
            break
        chosen.extend(groups[sel["index"]])
        steps.append(sel)
        theta = _gauss_newton(system, effects, theta, chosen, pairs, rows, sigma, settings)
        r, J = one_step(system, effects, theta, pairs)
        data = weighted(r, J, rows, sigma, spurious)
        # Backward check: an effect chosen early may be superseded by later ones (on a narrow
        # speed range viscous friction first stands in for drag plus Coulomb friction).
        while (drop := _superseded(data, theta, chosen, gap, settings, groups)) is not None:
            chosen.remove(drop)
            dropped.add(drop)  # never re-entered: no add/drop cycles
            steps = [st for st in steps if st["index"] != drop]
            theta[drop] = 0.0
            theta = _gauss_newton(system, effects, theta, chosen, pairs, rows, sigma, settings)
            r, J = one_step(system, effects, theta, pairs)
            data = weighted(r, J, rows, sigma, spurious)
    labels = _fold_labels(len(pairs), settings.folds)
    G, b, c = _grams(data, labels, settings.folds)
    explained_total = float(np.clip((total - _cv_sse(G, b, c, chosen).sum()) / gap, 0.0, 1.0)) \
        if chosen else 0.0
    # a group's columns share the loss of dropping the whole group
    losses = np.array([max(_drop_loss(data, theta, chosen, groups[j], settings).sum(), 0.0)
                       / len(groups[j]) for j in chosen])
    explained = (losses * explained_total / losses.sum() if losses.sum() > 0
                 else np.full(len(chosen), explained_total / max(len(chosen), 1)))
    sub = FitData(data.R, data.Phi[:, :, chosen], data.sigma, data.spurious[chosen])
    std = block_bootstrap(sub, settings).std(axis=0) if chosen else np.zeros(0)
    return EffectFit(chosen, theta[chosen], std, explained,
                     np.array([first.single.get(j, 0.0) for j in chosen]), explained_total,
                     gap, total, steps, rejected,
                     [aliases(data0, j, pool, settings) + [k for k, v in duplicates.items() if v == j]
                      for j in chosen], duplicates)


def _groups(effects: Sequence[Effect]) -> list[list[int]]:
    """Per library index, the indices selected together with it (itself, or its group's)."""
    by_name: dict[str, list[int]] = {}
    for j, e in enumerate(effects):
        if e.group:
            by_name.setdefault(e.group, []).append(j)
    return [by_name[e.group] if e.group else [j] for j, e in enumerate(effects)]


def _drop_loss(data: FitData, theta: np.ndarray, chosen: list[int], j: int | list[int],
               settings: FitSettings) -> np.ndarray:
    """Per-fold increase of the held-out SSE when effect ``j`` (or the columns ``j``) is dropped
    (linearised at theta)."""
    js = [j] if isinstance(j, (int, np.integer)) else list(j)
    labels = _fold_labels(data.R.shape[0], settings.folds)
    G, b, c = _grams(data, labels, settings.folds)
    without = FitData(data.R + sum(data.Phi[:, :, k] * theta[k] for k in js), data.Phi, data.sigma,
                      data.spurious)
    Gj, bj, cj = _grams(without, labels, settings.folds)
    return _cv_sse(Gj, bj, cj, [i for i in chosen if i not in js]) - _cv_sse(G, b, c, chosen)


def _superseded(data: FitData, theta: np.ndarray, chosen: list[int], gap: float,
                settings: FitSettings, groups: list[list[int]] | None = None) -> int | None:
    """The chosen effect whose removal costs least, if that cost fails the entry tests (the
    columns of a multi-parameter effect stay: they are entered and judged together)."""
    if len(chosen) < 2:
        return None
    full = _cv_sse(*_grams(data, _fold_labels(data.R.shape[0], settings.folds), settings.folds), chosen)
    costs = {}
    for j in chosen:
        if groups is not None and len(groups[j]) > 1:
            continue
        loss = _drop_loss(data, theta, chosen, j, settings)
        rel = loss / np.maximum(full + loss, 1e-300)  # over the smaller model's SSE, as on entry
        t_stat = rel.mean() / max(rel.std(ddof=1) / np.sqrt(len(rel)), 1e-300)
        costs[j] = (loss.sum() / gap, t_stat)
    if not costs:
        return None
    j = min(costs, key=lambda k: costs[k][0])
    gain, t_stat = costs[j]
    return j if (t_stat <= settings.t_min or gain <= settings.min_gain) else None


def _next(data: FitData, chosen: list[int], pool: list[int], gap: float, settings: FitSettings,
          groups: list[list[int]] | None = None) -> dict:
    """The next candidate: of the ``settings.scan`` best by held-out SSE, the first that passes the
    three tests of the module docstring; else the best one, marked not accepted. A candidate
    with a group (``groups[j]``) enters with all its columns."""
    cols = (lambda j: groups[j]) if groups is not None else (lambda j: [j])
    labels = _fold_labels(data.R.shape[0], settings.folds)
    G, b, c = _grams(data, labels, settings.folds)
    base = _cv_sse(G, b, c, chosen)
    trials = {j: _cv_sse(G, b, c, chosen + cols(j)) for j in pool if j not in chosen}
    if not trials:
        return {"accept": False, "index": None, "reason": "library exhausted"}
    ranked = sorted(trials, key=lambda k: trials[k].sum())[:settings.scan]
    steps = [_test(data, chosen, j, base, trials[j], gap, settings, cols(j)) for j in ranked]
    return next((st for st in steps if st["accept"]), steps[0])


def _test(data: FitData, chosen: list[int], j: int, base: np.ndarray, trial: np.ndarray, gap: float,
          settings: FitSettings, cols: list[int] | None = None) -> dict:
    gains = base - trial
    # Fold gains relative to the fold's own residual: a deterministic effect that grows with the
    # regime (drag ~ v^2) gains very different absolute amounts in different folds, but a
    # consistent fraction in each.
    relative = gains / np.maximum(base, 1e-300)
    t_stat = float(relative.mean() / max(relative.std(ddof=1) / np.sqrt(len(relative)), 1e-300))
    cols = cols or [j]
    if len(cols) == 1:
        size = float(_term_size(data, chosen + [j])[-1])
    else:  # the size of the group's combined term (its columns may nearly cancel)
        P = data.Phi[:, :, chosen + cols].reshape(-1, len(chosen) + len(cols))
        th = np.linalg.lstsq(P, data.R.ravel(), rcond=None)[0]
        size = float(np.sqrt(np.mean((P[:, len(chosen):] @ th[len(chosen):]) ** 2)))
    need = max(settings.min_size, settings.spurious_factor * float(max(data.spurious[k] for k in cols)))
    step = {"index": j, "t": t_stat, "gain": float(gains.sum() / gap), "size": size, "size_needed": need}
    reasons = [why for ok, why in ((t_stat > settings.t_min, "not consistent across folds"),
                                   (step["gain"] > settings.min_gain, "explains too little"),
                                   (size > need, "below the noise / observer-artefact level"))
               if not ok]
    step["accept"] = not reasons
    step["reason"] = "; ".join(reasons)
    return step


def _gauss_newton(system: System, effects: Sequence[Effect], theta: np.ndarray, chosen: list[int],
                  pairs: Pairs, rows, sigma, settings: FitSettings) -> np.ndarray:
    """Refine ``theta[chosen]`` (others fixed) on the weighted nonlinear residual."""
    sub = [effects[j] for j in chosen]
    fixed = [j for j in range(len(effects)) if j not in chosen and theta[j] != 0.0]
    if fixed:
        raise ValueError("internal: only chosen effects may have non-zero parameters")
    th = theta[chosen].copy()

    def evaluate(values):
        r, J = one_step(system, sub, values, pairs)
        return weighted(r, J, rows, sigma)

    data = evaluate(th)
    sse = float(np.sum(data.R**2))
    for _ in range(settings.gauss_newton):
        step = least_squares(data)
        for _halving in range(20):
            trial = evaluate(th + step)
            trial_sse = float(np.sum(trial.R**2))
            if trial_sse <= sse:
                break
            step = step / 2
        else:
            break
        th, data, converged = th + step, trial, np.all(np.abs(step) <= 1e-10 + 1e-8 * np.abs(th))
        sse = trial_sse
        if converged:
            break
    out = theta.copy()
    out[chosen] = th
    return out
