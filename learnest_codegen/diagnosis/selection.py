"""Sparse, cross-validated selection of effects against the gap that remains.

Forward stepwise selection over the library with K-fold cross-validation (folds from
:func:`~learnest_codegen.diagnosis.fit.fold_labels`). At every step each candidate is scored
against the gap that *remains* after the effects already chosen (refitted jointly and
relinearised there), not against the prior's gap: a dominant effect (an actuator gain standing in
for two wrong parameters) must not set the bar for a small one (a friction) that explains most
of what is left. A candidate enters only if all of these hold:

* its held-out improvement is consistent over folds: the t statistic of the folds' relative
  held-out SSE reductions exceeds ``t_min`` (paired, relative differences: a drag that grows
  with v^2 gains different absolute amounts in slow and fast folds, but a similar fraction);
* its held-out gain exceeds ``min_gain`` of the remaining gap and ``gap_noise`` standard
  deviations of a pure-noise sum of squares, ``sqrt(2 n)`` for ``n`` weighted rows (the remaining
  gap's own noise floor: a remainder at the floor has nothing left to explain);
* its size (RMS of its fitted term, in noise units) exceeds ``min_size`` and ``spurious_factor``
  times what the same feature "explains" of pure observer error (``FitData.spurious``).

After each entry the chosen parameters are refined together on the nonlinear residual
(:mod:`~learnest_codegen.diagnosis.refine`), then a **backward pass** drops any chosen effect
whose removal would fail the same tests (its loss judged against the gap of the smaller model).
A **swap pass** then replaces a generic effect by a parameter of the system's own prior when the
two sets are exactly equivalent on the data (an actuator gain plus a gravity torque describe a
pendulum as well as its inertia plus the gravity torque; the user's model names the latter).
Last, all chosen effects are refitted jointly.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..systems import System
from .effects import Effect
from .fit import (
    FitData,
    FitSettings,
    Pairs,
    _cv_sse,
    _grams,
    _term_size,
    aliases,
    baseline,
    block_bootstrap,
    one_step,
    weighted,
)
from .refine import Refined, bounds, refine


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
    steps, rejected : the selection path (diagnostics); ``dropped`` and ``swapped`` record the
        backward and swap passes.
    aliases : per chosen effect, library indices indistinguishable from it on these data.
    duplicates : library index -> the index it duplicates exactly on these data.
    refit : status of the final joint refinement (``"failed: ..."`` is a verdict).
    equivalents : per chosen effect, its exact duplicates (another channel with the same
        signature, e.g. a friction on ``qdot'`` directly and as a torque through ``tau``) with the
        parameter value each would have: the same finding in the other's units.
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
    refit: str = "converged"
    dropped: list[dict] = field(default_factory=list)
    swapped: list[dict] = field(default_factory=list)
    equivalents: list[dict[int, float]] = field(default_factory=list)


class _Problem:
    """The data of one selection: evaluates the weighted residual and features at ``theta``."""

    def __init__(self, system: System, effects: Sequence[Effect], pairs: Pairs, rows, sigma,
                 spurious, labels, settings: FitSettings):
        self.system, self.effects, self.pairs = system, list(effects), pairs
        self.rows, self.sigma, self.spurious, self.labels = list(rows), sigma, spurious, labels
        self.settings = settings

    def data(self, theta: np.ndarray) -> FitData:
        r, J = one_step(self.system, self.effects, theta, self.pairs)
        return weighted(r, J, self.rows, self.sigma, self.spurious, self.labels)

    def refit(self, theta: np.ndarray, chosen: list[int]) -> tuple[np.ndarray, Refined]:
        """Refine ``theta[chosen]`` jointly (others stay 0) with the damped, bounded LM."""
        out = refit(self.system, [self.effects[j] for j in chosen], theta[chosen], self.pairs, self.rows,
                    self.sigma, self.settings)
        full = np.zeros_like(theta)
        full[chosen] = out.theta
        return full, out


def refit(system: System, effects: Sequence[Effect], theta: np.ndarray, pairs: Pairs, rows, sigma,
          settings: FitSettings = FitSettings(), iterations: int | None = None) -> Refined:
    """Refine the parameters of ``effects`` (all of them, from ``theta``) on ``pairs`` with the
    damped, bounded Levenberg-Marquardt of :mod:`~learnest_codegen.diagnosis.refine`."""
    base = np.array([float(system.params[e.channel.split(":", 1)[1]]) if e.channel.startswith("param:")
                     else 0.0 for e in effects])
    lo, hi = bounds(system, effects, settings.bound)

    def evaluate(values):
        r, J = one_step(system, effects, values, pairs)
        d = weighted(r, J, rows, sigma)
        return d.R.ravel(), d.Phi.reshape(-1, len(effects))

    return refine(evaluate, np.asarray(theta, float), lo, hi, lambda th: base + th,
                  iterations=settings.refine_iterations if iterations is None else iterations,
                  max_step=settings.max_step)


def fit_effects(system: System, effects: Sequence[Effect], pairs: Pairs, rows: Sequence[int],
                sigma: np.ndarray, spurious: np.ndarray | None = None,
                settings: FitSettings = FitSettings(), labels: np.ndarray | None = None) -> EffectFit:
    """Select, refine and score effects of ``effects`` on ``pairs`` (see the module docstring).

    Parameters
    ----------
    system : the system whose prior the effects modify.
    effects : the candidate library.
    pairs : state pairs (one or more runs).
    rows : indices of the residual states; ``sigma`` their noise floor.
    spurious : per effect, what its feature explains of pure observer error (noise units).
    settings : :class:`~learnest_codegen.diagnosis.fit.FitSettings`.
    labels : cross-validation fold of each pair (default: contiguous time blocks).
    """
    prob = _Problem(system, effects, pairs, rows, sigma,
                    np.zeros(len(effects)) if spurious is None else spurious, labels, settings)
    theta = np.zeros(len(effects))
    data0 = prob.data(theta)
    first = baseline(data0, settings)
    groups = _groups(effects)
    # a multi-parameter effect (a group) is a candidate as a whole, through its first column
    pool = [j for j in first.pool if groups[j][0] == j and all(k in first.pool for k in groups[j])]
    chosen, steps, rejected, dropped, out_of_pool, status = [], [], None, [], set(), "converged"
    data = data0
    while len(chosen) < settings.max_effects:
        sel = _next(data, chosen, [j for j in pool if j not in out_of_pool], settings, groups)
        if sel["accept"] is False:
            rejected = sel
            break
        chosen.extend(groups[sel["index"]])
        steps.append(sel)
        theta, res = prob.refit(theta, chosen)
        status = res.status
        data = prob.data(theta)
        while (drop := _superseded(data, theta, chosen, settings, groups)) is not None:
            j, why = drop
            chosen.remove(j)
            out_of_pool.add(j)  # never re-entered: no add/drop cycles
            dropped.append({"index": j, "effect": effects[j].name, **why})
            steps = [st for st in steps if st["index"] != j]
            theta[j] = 0.0
            theta, res = prob.refit(theta, chosen)
            status = res.status
            data = prob.data(theta)
    swapped = []
    if chosen:
        chosen, theta, swapped = _swap(prob, data, theta, chosen, pool, settings, groups)
        theta, res = prob.refit(theta, chosen)  # the final joint refit
        status = res.status
        data = prob.data(theta)
    G, b, c = _grams(data, settings=settings)
    explained_total = float(np.clip((first.total - _cv_sse(G, b, c, chosen).sum()) / first.gap, 0.0, 1.0)) \
        if chosen else 0.0
    # a group's columns share the loss of dropping the whole group
    losses = np.array([max(_drop_loss(data, theta, chosen, groups[j], settings).sum(), 0.0)
                       / len(groups[j]) for j in chosen])
    explained = (losses * explained_total / losses.sum() if losses.sum() > 0
                 else np.full(len(chosen), explained_total / max(len(chosen), 1)))
    std = block_bootstrap(data.columns(chosen), settings).std(axis=0) if chosen else np.zeros(0)
    return EffectFit(chosen, theta[chosen], std, explained,
                     np.array([first.single.get(j, 0.0) for j in chosen]), explained_total,
                     first.gap, first.total, steps, rejected,
                     [aliases(data0, j, pool, settings) + [k for k, v in first.duplicates.items() if v == j]
                      for j in chosen], first.duplicates, status, dropped, swapped,
                     [_equivalents(data, j, theta[j], first.duplicates) for j in chosen])


def _equivalents(data: FitData, j: int, value: float, duplicates: dict[int, int]) -> dict[int, float]:
    """Each exact duplicate ``k`` of ``j`` with the parameter giving the same term:
    ``Phi_k theta_k = Phi_j theta_j`` in the least-squares sense, at the final parameters."""
    P = data.Phi.reshape(-1, data.Phi.shape[2])
    out = {}
    for k, v in duplicates.items():
        if v == j and P[:, k] @ P[:, k] > 0:
            out[k] = float(value * (P[:, k] @ P[:, j]) / (P[:, k] @ P[:, k]))
    return out


def _groups(effects: Sequence[Effect]) -> list[list[int]]:
    """Per library index, the indices selected together with it (itself, or its group's)."""
    by_name: dict[str, list[int]] = {}
    for j, e in enumerate(effects):
        if e.group:
            by_name.setdefault(e.group, []).append(j)
    return [by_name[e.group] if e.group else [j] for j, e in enumerate(effects)]


def _noise(data: FitData, settings: FitSettings) -> float:
    """``gap_noise`` standard deviations of a pure-noise sum of squares over the rows."""
    return settings.gap_noise * float(np.sqrt(2.0 * data.R.size))


def _drop_loss(data: FitData, theta: np.ndarray, chosen: list[int], j: int | list[int],
               settings: FitSettings) -> np.ndarray:
    """Per-fold increase of the held-out SSE when effect ``j`` (or the columns ``j``) is dropped
    (linearised at theta)."""
    js = [j] if isinstance(j, (int, np.integer)) else list(j)
    G, b, c = _grams(data, settings=settings)
    without = data.with_R(data.R + sum(data.Phi[:, :, k] * theta[k] for k in js))
    Gj, bj, cj = _grams(without, settings=settings)
    return _cv_sse(Gj, bj, cj, [i for i in chosen if i not in js]) - _cv_sse(G, b, c, chosen)


def _t(rel: np.ndarray) -> float:
    return float(rel.mean() / max(rel.std(ddof=1) / np.sqrt(len(rel)), 1e-300))


def _superseded(data: FitData, theta: np.ndarray, chosen: list[int], settings: FitSettings,
                groups: list[list[int]]) -> tuple[int, dict] | None:
    """The chosen effect whose removal costs least, if that cost fails the entry tests against
    the gap of the model without it (the columns of a multi-parameter effect stay together)."""
    if len(chosen) < 2:
        return None
    G, b, c = _grams(data, settings=settings)
    full = _cv_sse(G, b, c, chosen)
    costs = {}
    for j in chosen:
        if len(groups[j]) > 1:
            continue
        loss = _drop_loss(data, theta, chosen, j, settings)
        remaining = max(float((full + loss).sum()) - data.floor, 0.0)
        need = max(settings.min_gain * remaining, _noise(data, settings))
        costs[j] = (float(loss.sum()), need, _t(loss / np.maximum(full + loss, 1e-300)))
    if not costs:
        return None
    j = min(costs, key=lambda k: costs[k][0] / max(costs[k][1], 1e-300))
    loss, need, t_stat = costs[j]
    if t_stat <= settings.t_min or loss <= need:
        return j, {"loss": loss, "needed": need, "t": t_stat}
    return None


def _next(data: FitData, chosen: list[int], pool: list[int], settings: FitSettings,
          groups: list[list[int]]) -> dict:
    """The next candidate: of the ``settings.scan`` best by held-out SSE, the first that passes the
    tests of the module docstring; else the best one, marked not accepted."""
    G, b, c = _grams(data, settings=settings)
    base = _cv_sse(G, b, c, chosen)
    trials = {j: _cv_sse(G, b, c, chosen + groups[j]) for j in pool if j not in chosen}
    if not trials:
        return {"accept": False, "index": None, "reason": "library exhausted"}
    remaining = max(float(base.sum()) - data.floor, 0.0)
    ranked = sorted(trials, key=lambda k: trials[k].sum())[:settings.scan]
    steps = [_test(data, chosen, j, base, trials[j], remaining, settings, groups[j]) for j in ranked]
    return next((st for st in steps if st["accept"]), steps[0])


def _test(data: FitData, chosen: list[int], j: int, base: np.ndarray, trial: np.ndarray,
          remaining: float, settings: FitSettings, cols: list[int]) -> dict:
    gains = base - trial
    t_stat = _t(gains / np.maximum(base, 1e-300))
    if len(cols) == 1:
        size = float(_term_size(data, chosen + [j])[-1])
    else:  # the size of the group's combined term (its columns may nearly cancel)
        P = data.Phi[:, :, chosen + cols].reshape(-1, len(chosen) + len(cols))
        th = np.linalg.lstsq(P, data.R.ravel(), rcond=None)[0]
        size = float(np.sqrt(np.mean((P[:, len(chosen):] @ th[len(chosen):]) ** 2)))
    need = max(settings.min_size, settings.spurious_factor * float(max(data.spurious[k] for k in cols)))
    gain = float(gains.sum())
    need_gain = max(settings.min_gain * remaining, _noise(data, settings))
    step = {"index": j, "t": t_stat, "gain": gain / remaining if remaining > 0 else None, "gain_abs": gain,
            "gain_needed": need_gain, "remaining_gap": remaining, "size": size, "size_needed": need}
    reasons = [why for ok, why in ((t_stat > settings.t_min, "not consistent across folds"),
                                   (gain > need_gain, "explains too little of the remaining gap"),
                                   (size > need, "below the noise / observer-artefact level"))
               if not ok]
    step["accept"] = not reasons
    step["reason"] = "; ".join(reasons)
    return step


def _preference(effect: Effect) -> int:
    """A parameter of the system's own prior is preferred to a generic effect it is equivalent to."""
    return 1 if effect.channel.startswith("param:") else 0


def _swap(prob: _Problem, data: FitData, theta: np.ndarray, chosen: list[int], pool: list[int],
          settings: FitSettings, groups: list[list[int]]):
    """Replace a chosen generic effect by an unchosen prior parameter when the two sets fit the
    data equally well (in-sample SSE within ``swap_tol`` of the total, linearised at ``theta``)."""
    swapped = []
    effects = prob.effects
    P = data.Phi.reshape(-1, data.Phi.shape[2])
    R = data.R.ravel() + P[:, chosen] @ theta[chosen]  # the residual with the chosen effects removed

    def sse(cols):
        th = np.linalg.lstsq(P[:, cols], R, rcond=None)[0]
        e = R - P[:, cols] @ th
        return float(e @ e)

    current = sse(chosen)
    tol = settings.swap_tol * float(R @ R)
    for j in list(chosen):
        if len(groups[j]) > 1 or _preference(effects[j]) == 1:
            continue
        for c in pool:
            if c in chosen or len(groups[c]) > 1 or _preference(effects[c]) <= _preference(effects[j]):
                continue
            cols = [c if k == j else k for k in chosen]
            value = sse(cols)
            if value <= current + tol:
                swapped.append({"removed": effects[j].name, "added": effects[c].name,
                                "sse": value, "sse_before": current})
                theta = theta.copy()
                theta[j] = 0.0
                chosen = cols
                current = value
                break
    return chosen, theta, swapped
