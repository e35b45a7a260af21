"""The moves of the effect selection and the tests every move must pass.

A :class:`Search` holds the chosen set, its parameters and the data linearised there, and moves
it: ``enter`` (forward), ``drop`` (backward), ``exchange`` (one chosen effect for one not chosen),
``restart`` (select again without an effect whose parameter is pinned at the edge of its range,
such as an actuator gain of -0.996 that switches a drive off and stands for a drive curve; the
new set is kept if it fits held out as well) and ``swap`` (a generic effect for an exactly
equivalent parameter of the prior). Each move is
scored by cross-validated, bounded least squares (:mod:`~learnest_codegen.diagnosis.cv`) and
followed by a joint nonlinear refit. The tests a candidate must pass to enter (or an exchange to
be made), with ``base`` the held-out SSE per fold of the set it joins and ``trial`` that with it:

* **consistent over folds**: the t statistic of the folds' relative gains ``(base - trial) /
  base`` exceeds ``t_min``, over the folds in which the candidate is excited at all (at least 1 %
  of its mean energy per fold: a saturation says nothing in a fold that never reaches it);
* **large against what is left**: the held-out gain exceeds ``min_gain`` of the remaining gap and
  ``gap_noise`` standard deviations of a pure-noise sum of squares (``sqrt(2 n)`` for ``n``
  weighted rows);
* **large against the prior's gap**, while what remains is far above the floor (more than the
  floor itself): the gain exceeds ``min_share`` of the prior's held-out gap (with noise-free
  states the remaining gap after the right effects is a mismatch of form, such as a Coulomb
  friction's smoothing; a cascade of small terms fitting it is not a finding). Once the rest is
  within the floor's own size, the noise tests decide alone: a weak effect (a sub-sample input
  delay through an observer) is judged against the noise, not against a prior that was off by a
  factor of three;
* **above the noise**: its term's RMS exceeds ``min_size`` and ``spurious_factor`` times what the
  same feature explains of pure observer error;
* **causal** (a delay or a lag): it must fit significantly better than its time mirror (the same
  filter run backwards in time, an advance): a smoother blurs an input's steps symmetrically in
  time, which a delay bounded to be >= 0 would otherwise half fit;
* a delay or a lag is seen only where its input changes, so its held-out gain is uneven over the
  folds and small against a pure-noise sum of squares by nature: for these, once what is left is
  within the floor's size, the whole data's Wald statistic (:func:`wald`, by generalised least
  squares) above ``z_min`` stands for the fold consistency and the gain thresholds (held out it
  must still fit no worse than the spread of a pure-noise sum of squares), and the Wald statistic
  of the filter minus its mirror fitted with it for significantly better than the mirror, and
  the filter's parameter ``z_min`` joint standard errors above the same whitened fit on the
  calibration's pure observer error for the observer-artefact test (a raw RMS is dominated by
  the slow scatter the whitened fit discounts); a chosen filter keeps its place on the same
  statistic; every filter of the library is tested at each step, whatever its held-out rank;
* **adds something**: a candidate whose features lie in the span of the chosen ones (within
  the exact-duplicate tolerance) is no candidate (:meth:`Search._spanned`);
* **jointly** (small subsets): when no candidate passes alone, or a pair fits significantly
  better than the best single one, two candidates enter together, each passing the tests
  against the other alone;
* **the same on every run** (two runs or more): fitted with the others on each run alone, every
  parameter's per-run intervals (the value +- 3 standard errors of that run's fit, a sandwich
  over stretches of the run, widened by half the pooled value) share a value of the
  pooled sign (:func:`consistent`): a poorly excited run has a wide interval and cannot block an
  effect that the others fix. A candidate failing only this is *blocked*, and the report says so.

Every parameter stays in its physical range throughout (the bounds of the effects), so no move
can select a friction with the wrong sign. An effect nonlinear in its parameter (a delay) is also
linearised at its ``starts``; per fold, the start that fits the training folds best is scored.

Length: the moves share one state (the chosen set, its parameters, the linearised data and the
sets already seen, which keep moves from cycling) and one set of entry tests; split across
modules they would pass that state back and forth.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from .cv import FitData, _fold_labels, box_solve, cv_sse, grams, term_size
from .fit import FitSettings


def _t(rel: np.ndarray) -> float:
    return float(rel.mean() / max(rel.std(ddof=1) / np.sqrt(len(rel)), 1e-300))


def _rel(gain: np.ndarray, base: np.ndarray) -> np.ndarray:
    """``gain / base`` per fold, a fold without residual (an empty one) counting as no gain."""
    live = base > 1e-12 * max(float(base.max()), 1e-300)
    return np.divide(gain, base, out=np.zeros_like(gain, dtype=float), where=live)


def excited(data: FitData, cols: list[int], settings: FitSettings, share: float = 0.01) -> np.ndarray:
    """(folds,) whether the columns ``cols`` carry at least ``share`` of the mean energy per fold
    (a saturation is silent in a fold where the input stays below it: no evidence either way)."""
    labels, k = data.folds(settings.folds)
    energy = np.bincount(labels, weights=np.sum(data.Phi[:, :, cols] ** 2, axis=(1, 2)), minlength=k)
    return energy >= share * max(float(energy.mean()), 1e-300)


def cv_detail(G, b, c, idx, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Held-out SSE and training objective per fold of bounded least squares on ``idx``."""
    idx = list(idx)
    Gt, bt, ct = G.sum(0), b.sum(0), c.sum()
    held, train = np.empty(len(c)), np.empty(len(c))
    for f in range(len(c)):
        A, rhs = (Gt - G[f])[np.ix_(idx, idx)], (bt - b[f])[idx]
        th = box_solve(A, rhs, lo[idx], hi[idx])
        held[f] = c[f] - 2 * th @ b[f][idx] + th @ G[f][np.ix_(idx, idx)] @ th
        train[f] = (ct - c[f]) - 2 * th @ rhs + th @ A @ th
    return held, train


def per_run_values(data: FitData, cols: list[int], theta_cols: np.ndarray,
                   blocks: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """``(values, se)``, each ``(runs, len(cols))``: the parameters of ``cols`` fitted on each run
    alone (bounded, linearised) and their standard errors from that fit.

    The errors are a sandwich over ``blocks`` contiguous stretches of the run (``G^-1 (sum_b s_b
    s_b') G^-1``, ``s_b`` the stretch's score ``Phi_b' e_b``): the one-step residual is correlated
    in time, and a run that barely excites an effect (a swing-up that never stops, for a static
    friction) gets the wide interval it has, not a value as sure as the others'."""
    runs = np.unique(data.runs)
    values, se = np.empty((len(runs), len(cols))), np.empty((len(runs), len(cols)))
    for r, run in enumerate(runs):
        rows = np.flatnonzero(data.runs == run)
        P, R = data.Phi[rows][:, :, cols], data.R[rows]
        G = np.einsum("ksi,ksj->ij", P, P)
        step = box_solve(G, np.einsum("ksi,ks->i", P, R), data.lo[cols], data.hi[cols])
        e = R - np.einsum("ksi,i->ks", P, step)
        label = _fold_labels(len(rows), min(blocks, len(rows)))
        cov = sandwich(P, e, G, label)
        values[r] = theta_cols + step
        se[r] = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    return values, se


def sandwich(P: np.ndarray, e: np.ndarray, G: np.ndarray, label: np.ndarray) -> np.ndarray:
    """The covariance of a least-squares step on features ``P (N, S, m)`` with residual ``e (N,
    S)`` and normal matrix ``G``, robust to a residual correlated in time: ``G^-1 (sum_b s_b
    s_b') G^-1`` over the contiguous stretches ``label (N,)``, ``s_b = P_b' e_b``."""
    scores = np.stack([np.einsum("ksi,ks->i", P[label == b], e[label == b]) for b in np.unique(label)])
    n_b = len(scores)
    inv = np.linalg.pinv(G)
    return inv @ (scores.T @ scores) @ inv * n_b / max(n_b - 1, 1)


def wald(data: FitData, idx: list[int], at: np.ndarray, weights: np.ndarray, blocks: int,
         order: int = 0) -> float:
    """The Wald statistic of ``weights' theta`` over the columns ``idx``: ``theta`` the parameters
    (``at`` at the data's linearisation plus the step fitted with all of them, bounded), divided by
    its standard error (both from :func:`estimate`).

    It weighs the evidence for a parameter where it lies: a sub-sample input delay is seen only
    where the input changes (a swing-up's torque switches a few times a swing), so its held-out
    gain is large in a few folds and nil in the others, and a t statistic over the folds' gains
    counts that unevenness of excitation as inconsistency.

    With ``order`` > 0 (the selection's default) the fit is generalised least squares: features
    and residual whitened by the residual's own autoregression (:func:`whiten`), the standard
    error from :func:`newey_west` on the whitened rows. The one-step residual of a smoothing
    observer's states is correlated over many samples; plain least squares weighs every sample
    alike, so an effect seen in a few sharp events (a late torque step) is judged against a slow
    scatter it does not share, and whitened the same data fix it several times more precisely.
    With ``order`` 0: plain least squares, the standard error from :func:`sandwich` on ``blocks``
    contiguous stretches."""
    value, se = estimate(data, idx, at, weights, blocks, order)
    return value / max(se, 1e-300)


def estimate(data: FitData, idx: list[int], at: np.ndarray, weights: np.ndarray, blocks: int,
             order: int = 0) -> tuple[float, float]:
    """``(weights' theta, its standard error)`` of :func:`wald`'s fit."""
    P, R = data.Phi[:, :, idx], data.R
    G = np.einsum("ksi,ksj->ij", P, P)
    step = box_solve(G, np.einsum("ksi,ks->i", P, R), data.lo[idx], data.hi[idx])
    if order > 0:
        P, R, runs = whiten(P, R, R - np.einsum("ksi,i->ks", P, step), data.runs, order)
        G = np.einsum("ksi,ksj->ij", P, P)
        step = box_solve(G, np.einsum("ksi,ks->i", P, R), data.lo[idx], data.hi[idx])
        cov = newey_west(P, R - np.einsum("ksi,i->ks", P, step), G, runs)
    else:
        e = R - np.einsum("ksi,i->ks", P, step)
        cov = sandwich(P, e, G, _fold_labels(len(R), min(blocks, len(R))))
    return float(weights @ (at + step)), float(np.sqrt(max(weights @ cov @ weights, 0.0)))


def newey_west(P: np.ndarray, e: np.ndarray, G: np.ndarray, runs: np.ndarray) -> np.ndarray:
    """The covariance of a least-squares step on features ``P (N, S, m)`` with a residual ``e (N,
    S)`` that is nearly white (after :func:`whiten`): ``G^-1 Omega G^-1``, ``Omega`` the
    Newey-West sum of the per-row scores' autocovariances within each run, Bartlett weights up to
    ``floor(4 (n / 100)^(2/9))`` lags (their rule of thumb). It keeps what whitening leaves
    (a residual whose size changes along the run, a short correlation) while its tails stay
    close to the normal's: a sandwich over a few blocks is dominated, where the feature is
    nonzero only at a few instants, by the blocks that hold one."""
    scores = np.einsum("ksi,ks->ki", P, e)
    omega = np.zeros((P.shape[2], P.shape[2]))
    for run in np.unique(runs):
        sc = scores[runs == run]
        omega += sc.T @ sc
        width = int(4 * (len(sc) / 100) ** (2 / 9))
        for lag in range(1, width + 1):
            c = sc[lag:].T @ sc[:-lag]
            omega += (1 - lag / (width + 1)) * (c + c.T)
    inv = np.linalg.pinv(G)
    return inv @ omega @ inv


def whiten(P: np.ndarray, R: np.ndarray, e: np.ndarray, runs: np.ndarray | None,
           order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features ``P (N, S, m)`` and residual ``R (N, S)`` filtered by the autoregressive
    polynomial of the residual ``e (N, S)``, and the run of each row kept: per run and residual
    state, an AR(p) fitted to ``e`` by least squares, ``p <= order`` chosen by Akaike's
    criterion, and ``x_k - sum_i a_i x_{k-1-i}`` applied to every column (the first ``order``
    rows of each run dropped; a run too short to fit is left out). A white residual gives
    ``a ~ 0``: the data unchanged."""
    return apply_ar(P, R, ar_filters(e, runs, order), runs, order)


def ar_filters(e: np.ndarray, runs: np.ndarray | None, order: int) -> dict:
    """Per run and residual state of ``e (N, S)``, the coefficients of :func:`_ar_fit` (``p <=
    order`` by Akaike's criterion); a run too short to fit has none."""
    runs = np.zeros(len(e), int) if runs is None else np.asarray(runs)
    out = {}
    for run in np.unique(runs):
        rows = np.flatnonzero(runs == run)
        if len(rows) > 4 * order + 2:
            out[run] = [_ar_fit(e[rows, s], order) for s in range(e.shape[1])]
    return out


def apply_ar(P: np.ndarray, R: np.ndarray, filters: dict, runs: np.ndarray | None,
             order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Features and residual filtered by :func:`ar_filters`' polynomials (see :func:`whiten`)."""
    runs = np.zeros(len(R), int) if runs is None else np.asarray(runs)
    keep_P, keep_R, keep_run = [], [], []
    for run in np.unique(runs):
        rows = np.flatnonzero(runs == run)
        n = len(rows)
        if run not in filters:
            continue
        Pr, Rr = np.empty((n - order,) + P.shape[1:]), np.empty((n - order, R.shape[1]))
        for s in range(R.shape[1]):
            a = filters[run][s]
            lag = [rows[order - i - 1:n - i - 1] for i in range(len(a))]
            Pr[:, s] = P[rows[order:], s] - sum(a[i] * P[lag[i], s] for i in range(len(a)))
            Rr[:, s] = R[rows[order:], s] - sum(a[i] * R[lag[i], s] for i in range(len(a)))
        keep_P.append(Pr)
        keep_R.append(Rr)
        keep_run.append(np.full(n - order, run))
    if not keep_R:
        return P, R, runs
    return np.concatenate(keep_P), np.concatenate(keep_R), np.concatenate(keep_run)


def _ar_fit(x: np.ndarray, order: int) -> np.ndarray:
    """The coefficients ``a (p,)`` of the AR(p) least-squares fit ``x_k ~ sum_i a_i x_{k-1-i}``,
    ``0 <= p <= order`` by Akaike's criterion (every order fitted on the same samples, from one
    normal matrix)."""
    n = len(x)
    lags = np.stack([x[order - i - 1:n - i - 1] for i in range(order)], axis=1)
    y = x[order:]
    G, g, yy = lags.T @ lags, lags.T @ y, float(y @ y)
    best, coef = len(y) * np.log(max(yy / len(y), 1e-300)), np.zeros(0)
    for p in range(1, order + 1):
        try:
            a = np.linalg.solve(G[:p, :p], g[:p])
        except np.linalg.LinAlgError:
            break
        aic = len(y) * np.log(max((yy - float(a @ g[:p])) / len(y), 1e-300)) + 2 * p
        if aic < best:
            best, coef = aic, a
    return coef


def consistent(values: np.ndarray, pooled: float, se: np.ndarray | None = None, z: float = 3.0,
               relative: float = 0.5) -> dict:
    """Whether one parameter is the same on every run: each run's interval, its value +- ``z``
    standard errors widened by ``relative`` of the pooled value's size (runs of a real robot
    differ by a battery or a surface), must share a common value of the pooled value's sign. A
    run whose data hardly fix the parameter has a wide interval and cannot block it; runs that
    each fix it well and disagree do (a steering map that differs between recordings). ``se``
    ``None``: the values alone (no interval beyond ``relative``)."""
    values = np.asarray(values, float)
    se = np.zeros_like(values) if se is None else np.asarray(se, float)
    width = z * se + relative * abs(pooled)
    lo, hi = float(np.max(values - width)), float(np.min(values + width))
    same_sign = (hi > 0) if pooled > 0 else (lo < 0) if pooled < 0 else False
    median = float(np.median(values))
    tiny = 1e-6 * max(abs(pooled), 1e-300)
    agree = float(np.mean(values * np.sign(pooled) > tiny)) if pooled != 0 else 0.0
    return {"per_run": [float(v) for v in values], "se": [float(v) for v in se], "median": median,
            "spread": float(1.4826 * np.median(np.abs(values - median))), "sign_agreement": agree,
            "common": [lo, hi], "consistent": bool(lo <= hi and same_sign)}


class Search:
    """The state of a selection (see the module docstring).

    ``local(cols, values)`` evaluates the weighted data of the library columns ``cols`` alone with
    their parameters at ``values`` (for a candidate linearised at one of its starts);
    ``refit(theta, chosen)`` refines the chosen parameters jointly on the nonlinear residual and
    returns ``(theta, status)``; ``data(theta)`` linearises every column at ``theta``.
    """

    def __init__(self, effects, data: Callable, local: Callable, refit: Callable, pool: list[int],
                 groups: list[list[int]], first, settings: FitSettings, error: FitData | None = None):
        self.effects, self._data, self._local, self._refit = effects, data, local, refit
        self.error = error  # the observer's own error (calibration), every feature at the prior
        self.pool, self.groups, self.first, self.settings = pool, groups, first, settings
        self.theta = np.zeros(len(effects))
        self.chosen: list[int] = []
        self.data = data(self.theta)
        self.status = "converged"
        self.steps, self.dropped, self.exchanged, self.blocked = [], [], [], {}
        self.rejected: dict | None = None
        self.seen = {frozenset()}
        self.restarted: set = set()
        self.rephrased: set = set()

    # -- scoring --------------------------------------------------------------------------------
    def _noise(self, data: FitData) -> float:
        return self.settings.gap_noise * float(np.sqrt(2.0 * data.R.size))

    def _share(self, remaining: float, data: FitData) -> float:
        """The share of the prior's gap a move must explain while ``remaining`` (above the floor)
        is larger than the floor itself; none once it is within it (see the module docstring)."""
        return self.settings.min_share * self.first.gap if remaining > data.floor else 0.0

    def _trial(self, G, b, c, base_cols: list[int], j: int, data: FitData,
               mirror: bool = False) -> tuple[np.ndarray, float, FitData | None]:
        """Held-out SSE per fold with candidate ``j`` added to ``base_cols``; its start; the local
        data at that start (``None``: linearised at 0 on ``data``). With ``mirror``, the same for
        the candidate's time mirror (a filter run backwards in time)."""
        cols = base_cols + self.groups[j]
        options = []
        if not mirror:
            held, train = cv_detail(G, b, c, cols, data.lo, data.hi)
            options.append((held, train, 0.0, None))
        for start in ((0.0,) if mirror else ()) + tuple(self.effects[j].starts):
            local = self._local(base_cols + [j], np.concatenate([self.theta[base_cols], [start]]), mirror)
            Gs, bs, cs_ = grams(local, settings=self.settings)
            h, t = cv_detail(Gs, bs, cs_, list(range(len(base_cols) + 1)), local.lo, local.hi)
            options.append((h, t, start, local))
        if len(options) == 1 and not mirror:
            return options[0][0], 0.0, None
        pick = np.argmin(np.stack([o[1] for o in options]), axis=0)  # per fold, by training fit
        trial = np.array([options[p][0][f] for f, p in enumerate(pick)])
        best = min(options, key=lambda o: o[1].sum() + o[0].sum())
        return trial, best[2], best[3]

    def test(self, data: FitData, base_cols: list[int], j: int, base: np.ndarray, trial: np.ndarray,
             start: float, local: FitData | None, cols: list[int] | None = None) -> dict:
        """The entry tests of the module docstring for ``j`` (or the columns ``cols``, each
        judged for its size) joining ``base_cols``."""
        s = self.settings
        single = cols is None
        cols = self.groups[j] if cols is None else cols
        remaining = max(float(base.sum()) - data.floor, 0.0)
        gains = base - trial
        src, idx = (local, list(range(len(base_cols) + 1))) if local is not None else (data, base_cols + cols)
        k = len(base_cols)
        live = excited(src, idx[k:], s)  # folds without excitation carry no evidence either way
        t_stat = _t(_rel(gains, base)[live]) if live.sum() >= 3 else -np.inf
        if local is not None:  # the whole term from 0: the start's own part and the fitted step
            P = local.Phi[:, :, idx].reshape(-1, len(idx))
            th = box_solve(P.T @ P, P.T @ local.R.ravel(), local.lo[idx], local.hi[idx])
            term = (data.R - local.R).ravel() + P[:, k:] @ th[k:]
            size = float(np.sqrt(np.mean(term ** 2)))
        elif len(cols) == 1 or not single:
            size = float(np.min(term_size(src, idx)[k:]))
        else:  # the size of the group's combined term (its columns may nearly cancel)
            P = src.Phi[:, :, idx].reshape(-1, len(idx))
            th = box_solve(P.T @ P, P.T @ src.R.ravel(), src.lo[idx], src.hi[idx])
            size = float(np.sqrt(np.mean((P[:, k:] @ th[k:]) ** 2)))
        need = max(s.min_size, s.spurious_factor * float(max(data.spurious[c] for c in cols)))
        gain = float(gains.sum())
        need_gain = max(s.min_gain * remaining, self._noise(data), self._share(remaining, data))
        step = {"index": j, "t": t_stat, "gain": gain / remaining if remaining > 0 else None,
                "gain_abs": gain, "gain_needed": need_gain, "remaining_gap": remaining,
                "share_of_prior_gap": gain / self.first.gap,
                "size": size, "size_needed": need, "start": start}
        # a filter (a delay, a lag) is seen where the input changes: its evidence is the whole
        # data's Wald statistic (generalised least squares) when the folds' gains are too uneven
        # for their t statistic or too small against a pure-noise sum of squares
        # (only once the rest is within the floor's size: the statistic's null is a model right
        # but for this effect; against a large gap left by others it measures their misfit too);
        # held out it must then fit no worse than the spread of a pure-noise sum of squares
        filt = single and self.effects[j].is_filter
        z = (self._filter_wald(base_cols, j, start) if filt and (t_stat <= s.t_min or gain <= need_gain)
             and gain > -self._noise(data) and (size > need or self.error is not None)
             and remaining <= data.floor else None)
        step["z"] = None if z is None else z[0]
        significant = z is not None and z[0] > s.z_min
        # the filter's term against the observer's own artefact, in the statistic's own terms: its
        # parameter fitted the same way (whitened, bounded, with the same effects) on the
        # calibration's pure observer error, the two estimates apart by z_min joint standard errors
        artefact = (self._artefact(base_cols, j, z[2], z[3]) if significant and self.error is not None
                    else None)
        if artefact is not None:
            step["z_over_observer"] = artefact
        above = size > need or (artefact is not None and artefact > s.z_min)
        enough = gain > need_gain or significant
        reasons = [why for ok, why in ((t_stat > s.t_min or significant, "not consistent across folds"),
                                       (enough, "explains too little of the gap"),
                                       (above, "below the noise / observer-artefact level"))
                   if not ok]
        if not reasons and filt:
            G, b, c = grams(data, settings=s)
            mirrored = self._trial(G, b, c, base_cols, j, data, mirror=True)[0]
            edge = mirrored - trial
            step["gain_over_mirror"] = float(edge.sum())
            if z is not None:
                step["z_over_mirror"] = z[1]
            if not ((edge.sum() > need_gain and _t(_rel(edge, mirrored)) > s.t_min)
                    or (z is not None and z[1] > s.z_min and edge.sum() > -self._noise(data))):
                reasons.append("no better than its time mirror (a smoother's blur, not a lag)")
        if not reasons and src.runs is not None and len(np.unique(src.runs)) >= 2:
            theta_idx = np.concatenate([self.theta[base_cols], [start] if local is not None
                                        else self.theta[cols]])
            P = src.Phi[:, :, idx].reshape(-1, len(idx))
            pooled = theta_idx + box_solve(P.T @ P, P.T @ src.R.ravel(), src.lo[idx], src.hi[idx])
            values, se = per_run_values(src, idx, theta_idx)
            checks = [consistent(values[:, k + i], pooled[k + i], se[:, k + i]) for i in range(len(idx) - k)]
            step["per_run"] = [c["per_run"] for c in checks]
            if not all(c["consistent"] for c in checks):
                reasons.append("not the same on every run")
        step["accept"] = not reasons
        step["reason"] = "; ".join(reasons)
        return step

    def _filter_wald(self, base_cols: list[int], j: int, start: float) -> tuple[float, float, float, float]:
        """The Wald statistics (:func:`wald`) of filter ``j`` joining ``base_cols`` (linearised at
        ``start``), and of its excess over its time mirror fitted with it (the delay minus the
        advance: a smoother's symmetric blur fits both alike, a late input the delay alone); then
        the filter's parameter and its standard error (:func:`estimate`)."""
        k = len(base_cols)
        at = np.concatenate([self.theta[base_cols], [start]])
        fwd = self._local(base_cols + [j], at)
        back = self._local(base_cols + [j], np.concatenate([self.theta[base_cols], [0.0]]), True)
        both = FitData(fwd.R, np.concatenate([fwd.Phi, back.Phi[:, :, -1:]], axis=2), fwd.sigma,
                       np.append(fwd.spurious, back.spurious[-1]), fwd.labels,
                       np.append(fwd.lo, back.lo[-1]), np.append(fwd.hi, back.hi[-1]), fwd.runs)
        alone, against = np.zeros(k + 1), np.zeros(k + 2)
        alone[k], against[k], against[k + 1] = 1.0, 1.0, -1.0
        blocks, order = self.settings.blocks, self.settings.whiten_order
        value, se = estimate(fwd, list(range(k + 1)), at, alone, blocks, order)
        return (value / max(se, 1e-300), wald(both, list(range(k + 2)), np.append(at, 0.0), against, blocks,
                                              order), value, se)

    def _artefact(self, base_cols: list[int], j: int, value: float, se: float) -> float:
        """How far the filter ``j``'s parameter ``value`` (standard error ``se``) lies above what
        the same fit finds in the observer's own error (the calibration run, ``self.error``): the
        difference over the two standard errors combined. The observer's smoothing can look like a
        late input; measured the same way as the data (whitened, within the parameter's range,
        with the effects already chosen), it is compared in the statistic's own terms, not as a
        raw RMS whose slow, correlated scatter the whitened fit does not count."""
        cols = list(base_cols) + [j]
        err = self.error
        weights = np.zeros(len(cols))
        weights[-1] = 1.0
        s = self.settings
        alone, alone_se = estimate(err, cols, np.zeros(len(cols)), weights, s.blocks, s.whiten_order)
        return float((value - alone) / max(np.hypot(se, alone_se), 1e-300))

    def candidates(self, exclude=()) -> dict:
        """The next candidate: of the ``scan`` best by held-out SSE, the first that passes the tests;
        else the best one, marked not accepted."""
        data = self.data
        G, b, c = grams(data, settings=self.settings)
        base = cv_sse(G, b, c, self.chosen, data.lo, data.hi)
        trials = {}
        for j in self.pool:
            if j in self.chosen or j in exclude or self._spanned(data, j):
                continue
            trials[j] = self._trial(G, b, c, list(self.chosen), j, data)
        if not trials:
            return {"accept": False, "index": None, "reason": "library exhausted"}
        ranked = sorted(trials, key=lambda k: trials[k][0].sum())
        # a filter's evidence is its Wald statistic, not its held-out rank: every filter is tested
        scan = self.settings.scan
        scanned = ranked[:scan] + [j for j in ranked[scan:] if self.effects[j].is_filter]
        steps = [self.test(data, list(self.chosen), j, base, *trials[j]) for j in scanned]
        for st in steps:
            if st["reason"] == "not the same on every run":
                self.blocked[st["index"]] = st
        accepted = next((st for st in steps if st["accept"]), None)
        if len(self.chosen) + 2 <= self.settings.max_effects:
            pair = self.pair(G, b, c, base, {j: trials[j][0] for j in ranked[:self.settings.pair_pool]})
            if pair is not None and (accepted is None or self._better(trials[accepted["index"]][0], pair[1])):
                return pair[0]
        return accepted or steps[0]

    def _spanned(self, data: FitData, j: int) -> bool:
        """Whether candidate ``j``'s features lie in the span of the chosen ones on these data (each
        within ``duplicate_cos`` of its projection, the test for an exact duplicate): added, it
        explains nothing the set does not (an actuator gain beside the inertia, the gravity torque
        and the friction it scales together), so it is no candidate. Ranked by held-out SSE it
        would tie with the set itself, ahead of every real candidate that fits held out a little
        worse, and end the selection in their place."""
        if not self.chosen:
            return False
        P = data.Phi.reshape(-1, data.Phi.shape[2])
        A = P[:, self.chosen]
        for c in self.groups[j]:
            col = P[:, c]
            rest = col - A @ np.linalg.lstsq(A, col, rcond=None)[0]
            if not col @ col > 0 or rest @ rest > (1.0 - self.settings.duplicate_cos ** 2) * (col @ col):
                return False
        return True

    def _better(self, single: np.ndarray, pair: np.ndarray) -> bool:
        """Whether a pair fits held out significantly better than the best single entry: by more
        than the entry tests' gain threshold, consistently over the folds."""
        remaining = max(float(single.sum()) - self.data.floor, 0.0)
        need = max(self.settings.min_gain * remaining, self._noise(self.data))
        edge = single - pair
        return bool(edge.sum() > need and _t(_rel(edge, single)) > self.settings.t_min)

    def pair(self, G, b, c, base: np.ndarray, singles: dict) -> tuple[dict, np.ndarray] | None:
        """Two candidates entering together, when neither passes alone (a friction that an actuator
        gain absorbed, together with the parameter error the gain also stood for) or together they
        fit significantly better than the best single one (a Coulomb friction and a back-EMF
        against a gain that switches a drive off): the pair must pass the entry tests, and each
        member must pass them against the other alone. Returns the step and its held-out SSE."""
        data, chosen, best = self.data, list(self.chosen), None
        names = sorted(singles)
        for a_i, j in enumerate(names):
            for k in names[a_i + 1:]:
                if self.groups[j][0] != j or self.groups[k][0] != k:
                    continue
                cols = self.groups[j] + self.groups[k]
                trial = cv_sse(G, b, c, chosen + cols, data.lo, data.hi)
                step = self.test(data, chosen, j, base, trial, 0.0, None, cols=cols)
                if not step["accept"]:
                    continue
                # each member against the other alone
                if not all(self.test(data, chosen + self.groups[o], m, singles[o], trial, 0.0, None)["accept"]
                           for m, o in ((j, k), (k, j))):
                    continue
                if best is None or trial.sum() < best[0]:
                    best = (trial.sum(), {**step, "index": j, "with": k}, trial)
        return None if best is None else (best[1], best[2])

    # -- moves ----------------------------------------------------------------------------------
    def _apply(self, chosen: list[int], theta: np.ndarray, new: bool = True) -> bool:
        """Refit on ``chosen`` from ``theta``; with ``new``, refused (``False``) if the set was
        chosen before: entries and exchanges never cycle (a drop is always allowed)."""
        key = frozenset(chosen)
        if new and key in self.seen:
            return False
        self.seen.add(key)
        self.theta, self.status = self._refit(theta, chosen)
        self.chosen = list(chosen)
        self.data = self._data(self.theta)
        return True

    def forward(self) -> bool:
        """Enter candidates while one passes (each followed by the backward pass)."""
        moved = False
        while len(self.chosen) < self.settings.max_effects:
            sel = self.candidates()
            if not sel["accept"]:
                self.rejected = sel
                break
            theta = self.theta.copy()
            theta[sel["index"]] = sel.get("start", 0.0)
            cols = self.groups[sel["index"]] + (self.groups[sel["with"]] if "with" in sel else [])
            if not self._apply(self.chosen + cols, theta):
                self.rejected = {**sel, "accept": False, "reason": "would repeat an earlier set"}
                break
            self.steps.append(sel)
            self.backward()
            moved = True
        return moved

    def _drop_loss(self, js: list[int]) -> np.ndarray:
        data = self.data
        G, b, c = grams(data, settings=self.settings)
        without = self._without(js)
        Gw, bw, cw = grams(without, settings=self.settings)
        rest = [i for i in self.chosen if i not in js]
        full = cv_sse(G, b, c, self.chosen, data.lo, data.hi)
        return cv_sse(Gw, bw, cw, rest, without.lo, without.hi) - full

    def _without(self, js: list[int]) -> FitData:
        """The data with the columns ``js`` taken out of the model (their terms back in ``R``)."""
        d = self.data
        lo, hi = d.lo.copy(), d.hi.copy()
        lo[js] += self.theta[js]
        hi[js] += self.theta[js]
        return FitData(d.R + sum(d.Phi[:, :, k] * self.theta[k] for k in js), d.Phi, d.sigma, d.spurious,
                       d.labels, lo, hi, d.runs)

    def backward(self) -> bool:
        """Drop, one at a time, the chosen effect whose loss fails the entry tests."""
        moved = False
        while len(self.chosen) >= 2:
            data = self.data
            G, b, c = grams(data, settings=self.settings)
            full = cv_sse(G, b, c, self.chosen, data.lo, data.hi)
            costs = {}
            for j in self.chosen:
                if len(self.groups[j]) > 1:
                    continue
                loss = self._drop_loss([j])
                remaining = max(float((full + loss).sum()) - data.floor, 0.0)
                need = max(self.settings.min_gain * remaining, self._noise(data),
                           self._share(remaining, data))
                costs[j] = (float(loss.sum()), need, _t(_rel(loss, full + loss)), remaining)
            if not costs:
                break
            j = min(costs, key=lambda k: costs[k][0] / max(costs[k][1], 1e-300))
            loss, need, t_stat, remaining = costs[j]
            if t_stat > self.settings.t_drop and loss > need:
                break
            if self.effects[j].is_filter and loss > -self._noise(data) and remaining <= data.floor \
                    and self._chosen_wald(j) > self.settings.z_min:
                break  # a filter keeps its place on its whole-data Wald statistic, as it entered
            theta = self.theta.copy()
            theta[j] = 0.0
            self._apply([i for i in self.chosen if i != j], theta, new=False)
            self.dropped.append({"index": j, "loss": loss, "needed": need, "t": t_stat})
            moved = True
        return moved

    def _chosen_wald(self, j: int) -> float:
        """The Wald statistic (:func:`wald`, whitened) of the chosen filter ``j`` with the other
        chosen effects, at the current parameters."""
        cols = list(self.chosen)
        weights = np.zeros(len(cols))
        weights[cols.index(j)] = 1.0
        s = self.settings
        return wald(self.data, cols, self.theta[cols], weights, s.blocks, s.whiten_order)

    def at_edge(self, j: int, share: float = 0.05) -> bool:
        """Whether ``j``'s parameter sits within ``share`` of a finite, non-zero edge of its range
        (an actuator gain of -0.988 leaves the drive 1.2 % of its authority, as good as switched
        off: it stands for something else)."""
        lo, hi = self.data.lo[j] + self.theta[j], self.data.hi[j] + self.theta[j]
        return any(np.isfinite(b) and b != 0 and abs(self.theta[j] - b) <= share * abs(b) for b in (lo, hi))

    def _state(self):
        return (list(self.chosen), self.theta.copy(), self.data, self.status, list(self.steps),
                list(self.dropped), self.rejected)

    def _restore(self, state) -> None:
        (self.chosen, self.theta, self.data, self.status, self.steps, self.dropped, self.rejected) = state

    def cv_total(self) -> float:
        G, b, c = grams(self.data, settings=self.settings)
        return float(cv_sse(G, b, c, self.chosen, self.data.lo, self.data.hi).sum())

    def restart(self) -> bool:
        """For a chosen effect pinned at the edge of its range: select again without it (it may not
        come back); keep the new set if it fits held out as well, within the noise of the sums."""
        for j in [i for i in self.chosen if len(self.groups[i]) == 1 and self.at_edge(i)]:
            key = (j, frozenset(self.chosen))
            if key in self.restarted:
                continue
            self.restarted.add(key)
            before, current = self._state(), self.cv_total()
            theta = self.theta.copy()
            theta[j] = 0.0
            self._apply([i for i in self.chosen if i != j], theta, new=False)
            saved_pool = self.pool
            self.pool = [i for i in self.pool if i != j]
            self.forward()
            self.pool = saved_pool
            if j not in self.chosen and self.chosen and self.cv_total() <= current + self._noise(self.data):
                self.exchanged.append({"removed": j, "added": [i for i in self.chosen if i not in before[0]],
                                       "sse": self.cv_total(), "sse_before": current,
                                       "why": "at the edge of its range"})
                return True
            self._restore(before)
        return False

    def exchange(self) -> bool:
        """Replace one chosen effect by one not chosen when that is significantly better held out."""
        data = self.data
        G, b, c = grams(data, settings=self.settings)
        full = cv_sse(G, b, c, self.chosen, data.lo, data.hi)
        remaining = max(float(full.sum()) - data.floor, 0.0)
        need = max(self.settings.min_gain * remaining, self._noise(data))
        best = None
        for j in {self.groups[i][0] for i in self.chosen}:
            js = self.groups[j]
            without = self._without(js)
            Gw, bw, cw = grams(without, settings=self.settings)
            rest = [i for i in self.chosen if i not in js]
            base = cv_sse(Gw, bw, cw, rest, without.lo, without.hi)
            for cand in self.pool:
                if cand in self.chosen or cand == j or frozenset(rest + self.groups[cand]) in self.seen:
                    continue
                trial = cv_sse(Gw, bw, cw, rest + self.groups[cand], without.lo, without.hi)
                gain = full - trial
                if gain.sum() <= need or _t(_rel(gain, full)) <= self.settings.t_min:
                    continue
                if best is None or trial.sum() < best[0]:
                    best = (trial.sum(), j, cand, without, rest, base, trial)
        if best is None:
            return False
        _, j, cand, without, rest, base, trial = best
        st = self.test(without, rest, cand, base, trial, 0.0, None)
        if not st["accept"]:
            return False
        theta = self.theta.copy()
        theta[self.groups[j]] = 0.0
        if not self._apply(rest + self.groups[cand], theta):
            return False
        self.exchanged.append({"removed": j, "added": [cand], "sse": float(trial.sum()),
                               "sse_before": float(full.sum()), "why": "significantly better held out"})
        return True

    def rephrase(self) -> bool:
        """Re-test the chosen set against its neighbours that say the same in other words: one
        chosen effect replaced by one or two prior parameters (an actuator gain by the inertia and
        the gravity torque it scales together), or two chosen effects by one candidate.

        Scored held out (by run when there are several, else by fold), with the data relinearised
        without the removed effects (a lag is far from linear in its time constant). A neighbour
        is taken when it fits significantly better (the exchange's test: a gain that aliases an
        inertia and a gravity torque scaled in nearly the same ratio gives way to the two), or,
        with no more parameters than before, when it reads more plainly (:func:`_plainness`: a
        parameter of the prior for a generic effect, a delay for a lag), says the same
        (:func:`_covered`: its features recover at least half of the removed ones) and fits at
        least as well: within the noise of the sums, losing at most a tenth of what the removed
        effects explained. A move is tried once per set, so the rounds cannot cycle."""
        data = self.data
        labels, k = held_out_groups(data, self.settings)
        G, b, c = grams(data, labels, k)
        full = cv_sse(G, b, c, self.chosen, data.lo, data.hi)
        current = float(full.sum())
        need = max(self.settings.min_gain * max(current - data.floor, 0.0), self._noise(data))
        singles = [j for j in self.chosen if len(self.groups[j]) == 1]
        free = [j for j in self.pool if j not in self.chosen and len(self.groups[j]) == 1]
        params = [j for j in free if _physical(self.effects[j]) and _plainness(self.effects[j])]
        moves = [([j], [a]) for j in singles for a in free]
        moves += [([j], [a, o]) for j in singles if not _physical(self.effects[j])
                  for n, a in enumerate(params) for o in params[n + 1:]]
        moves += [([j, o], [a]) for n, j in enumerate(singles) for o in singles[n + 1:] for a in free]
        best, grams_without = None, {}
        for removed, added in moves:
            key = (frozenset(self.chosen), frozenset(removed), frozenset(added))
            if key in self.rephrased:
                continue
            if tuple(removed) not in grams_without:  # relinearised without them: a lag is far from linear
                theta = self.theta.copy()
                theta[removed] = 0.0
                without = self._data(theta)
                grams_without[tuple(removed)] = (without, *grams(without, labels, k))
            without, Gw, bw, cw = grams_without[tuple(removed)]
            rest = [i for i in self.chosen if i not in removed]
            trial = cv_sse(Gw, bw, cw, rest + added, without.lo, without.hi)
            if len(added) == 2 and min(cv_sse(Gw, bw, cw, rest + [a], without.lo, without.hi).sum()
                                       for a in added) <= trial.sum() + self._noise(data):
                continue  # one of the two alone says as much: the pair is not the reading
            gain = full - trial
            better = gain.sum() > need and (k < 3 or _t(_rel(gain, full)) > self.settings.t_min)
            plainer = (sum(_plainness(self.effects[i]) for i in added)
                       - sum(_plainness(self.effects[i]) for i in removed))
            # "as good": within the noise of the sums, and never losing more than a tenth of what
            # the removed effects explained (a weak effect is not replaced by one explaining nothing)
            worth = float(cv_sse(Gw, bw, cw, rest, without.lo, without.hi).sum()) - current
            tol = min(self._noise(data), 0.1 * max(worth, 0.0))
            # one effect for two must earn the second parameter: significantly better, as an entry
            # (a force gain of -20 % is exactly both cart masses 25 % heavier: the gain stays)
            as_good = plainer > 0 and trial.sum() <= current + tol and len(added) <= len(removed) \
                and _covered(without, removed, added)
            if not (better or as_good):
                continue
            rank = (1, -float(trial.sum())) if better else (0, plainer, -len(added), -float(trial.sum()))
            if best is None or rank > best[0]:
                best = (rank, removed, added, float(trial.sum()), key)
        if best is None:
            return False
        rank, removed, added, score, key = best
        self.rephrased.add(key)
        theta = self.theta.copy()
        theta[removed] = 0.0
        self._apply([i for i in self.chosen if i not in removed] + added, theta, new=False)
        self.exchanged.append({"removed": removed[0] if len(removed) == 1 else removed, "added": added,
                               "sse": score, "sse_before": current,
                               "why": "significantly better held out" if rank[0] else
                               "the prior's own parameters, as good held out"})
        return True


def _covered(data: FitData, removed: list[int], added: list[int], share: float = 0.5) -> bool:
    """Whether the ``added`` columns say what the ``removed`` ones said: least squares on the added
    features recovers at least ``share`` of each removed feature (a rephrasing, not a different
    effect on another state that happens to fit as well)."""
    P = data.Phi.reshape(-1, data.Phi.shape[2])
    A = P[:, added]
    for j in removed:
        col = P[:, j]
        fit = A @ np.linalg.lstsq(A, col, rcond=None)[0]
        if not col @ col > 0 or fit @ fit < share * (col @ col):
            return False
    return True


def _physical(effect) -> bool:
    """A parameter of the system's own prior (``param:<p>``): the user's model names it."""
    return effect.channel.startswith("param:")


def _plainness(effect) -> int:
    """How plainly an effect reads, for choosing between readings that fit as well: a parameter
    of the prior (the user's model names it) with a sign to keep (the ground robot's ``C_D = 0``
    stays an alias of a quadratic drag >= 0), and an input delay rather than a first-order lag
    (shorter than a sample or two the two are the same to first order, and through a smoothing
    observer they are not told apart; a late command is the plainer reading)."""
    kept = np.isfinite(effect.lower) or np.isfinite(effect.upper)  # a prior's 0 has no sign to keep
    return int((_physical(effect) and kept) or effect.kind == "input_delay")


def held_out_groups(data: FitData, settings: FitSettings) -> tuple[np.ndarray, int]:
    """Rows grouped for held-out scoring: by run when there are two or more, else the folds."""
    if data.runs is not None and len(np.unique(data.runs)) >= 2:
        runs = np.unique(data.runs)
        return np.searchsorted(runs, data.runs), len(runs)
    return data.folds(settings.folds)
