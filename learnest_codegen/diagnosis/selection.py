"""Sparse, cross-validated selection of effects, re-tested until no single move improves it.

A greedy forward pass alone can be captured by its first pick: on a pendulum swing-up whose
torque correlates with ``sign(qdot)``, an actuator gain entered first absorbs the Coulomb
friction, and the friction then explains too little of what is left to enter. So the selection
(folds from :func:`~learnest_codegen.diagnosis.cv.fold_labels`; moves and tests in
:mod:`~learnest_codegen.diagnosis.search`) runs in rounds until the set no longer changes:

1. **forward**: enter the best candidate that passes the entry tests, scored against the gap that
   *remains* after the effects already chosen (refitted jointly and relinearised there), then
   drop any chosen effect that no longer earns its place (**backward**: its held-out loss when
   dropped is below the entry's gain threshold, or consistent over folds only at ``t <=
   t_drop``, lower than the entry's ``t_min``: a hysteresis, so an effect does not flip in and out
   on a borderline statistic);
2. **swap**: replace a generic effect by a parameter of the system's own prior when the two sets
   are exactly equivalent on the data (an actuator gain plus a gravity torque describe a pendulum
   as well as its inertia plus the gravity torque; the user's model names the latter);
3. **re-test**: drop what no longer earns its place against the others, retry every candidate
   not chosen (also those blocked or dropped before) against the new set, **exchange** one
   chosen effect for one not chosen when the held-out fit is significantly better, and
   **restart** without an effect pinned at the edge of its physical range (a boundary solution
   stands for something else: an actuator gain of -0.996 switches a drive off where a drive curve
   with a dead zone and a back-EMF is the physical reading), keeping the new set when it fits
   held out as well.

A set is never entered twice, so the rounds cannot cycle. Every fit is bounded: each parameter
stays in its physical range. Last, all chosen effects are refitted jointly.

The two figures reported for the fit data are the **in-sample share explained** (of the sum of
squares above the floor, by the final refit) and, per effect, its part of it (the in-sample loss
when it is dropped and the others refitted). The held-out evidence is in
:mod:`~learnest_codegen.diagnosis.shrink`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..systems import System
from .cv import FitData, aliases, baseline, block_bootstrap, cv_sse, fit_step, grams, weighted
from .effects import Effect
from .fit import FitSettings, Pairs, one_step
from .refine import Refined, bounds, refine
from .search import Search, apply_ar, ar_filters


@dataclass
class EffectFit:
    """Selected effects with their parameters, uncertainty and shares of the gap.

    Attributes
    ----------
    chosen : indices into the library, in the order selected.
    theta : (len(chosen),) fitted parameters; ``theta_std`` their block-bootstrap stds.
    explained : (len(chosen),) in-sample share of the gap each explains: ``explained_total`` split
        in proportion to the in-sample loss when the effect is dropped from the final set.
    scores : (len(chosen),) held-out share each explains alone (at the prior).
    explained_total : in-sample share of the fit data's gap (sum of squares above the floor)
        explained by the final refit.
    cv_explained : the cross-validated share (folds held out in turn), for diagnostics.
    gap, total : held-out sums of squares of the prior's residual above the floor, and in all.
    steps, rejected : the selection path (diagnostics); ``dropped``, ``swapped`` and
        ``exchanged`` record the other moves; ``blocked`` the candidates refused only because
        their parameter differs between runs.
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
    exchanged: list[dict] = field(default_factory=list)
    blocked: list[dict] = field(default_factory=list)
    cv_explained: float = 0.0


class _Problem:
    """The data of one selection: evaluates the weighted residual and features at ``theta``."""

    def __init__(self, system: System, effects: Sequence[Effect], pairs: Pairs, rows, sigma,
                 spurious, labels, settings: FitSettings):
        self.system, self.effects, self.pairs = system, list(effects), pairs
        self.rows, self.sigma, self.spurious, self.labels = list(rows), sigma, spurious, labels
        self.settings = settings
        self.lo, self.hi = bounds(system, self.effects, settings.bound)

    def data(self, theta: np.ndarray) -> FitData:
        r, J = one_step(self.system, self.effects, theta, self.pairs)
        return weighted(r, J, self.rows, self.sigma, self.spurious, self.labels, self.lo - theta,
                        self.hi - theta, self.pairs.segment)

    def local(self, cols: list[int], values: np.ndarray, mirror: bool = False) -> FitData:
        """The columns ``cols`` alone at ``values``; with ``mirror`` the last one is a filter run
        backwards in time (see :mod:`~learnest_codegen.diagnosis.search`)."""
        effects = [self.effects[j] for j in cols]
        if mirror:
            effects[-1] = _mirrored(effects[-1])
        r, J = one_step(self.system, effects, values, self.pairs)
        return weighted(r, J, self.rows, self.sigma, self.spurious[cols], self.labels,
                        self.lo[cols] - values, self.hi[cols] - values, self.pairs.segment)

    def refit(self, theta: np.ndarray, chosen: list[int], whitened: bool = False) -> tuple[np.ndarray, str]:
        """Refine ``theta[chosen]`` jointly (others 0) with the damped, bounded LM (``whitened``:
        then by generalised least squares, see :func:`refit`)."""
        full = np.zeros_like(theta)
        if not chosen:
            return full, "converged"
        out = refit(self.system, [self.effects[j] for j in chosen], theta[chosen], self.pairs, self.rows,
                    self.sigma, self.settings, whitened=whitened)
        full[chosen] = out.theta
        return full, out.status


def refit(system: System, effects: Sequence[Effect], theta: np.ndarray, pairs: Pairs, rows, sigma,
          settings: FitSettings = FitSettings(), iterations: int | None = None,
          whitened: bool = False) -> Refined:
    """Refine the parameters of ``effects`` (all of them, from ``theta``) on ``pairs`` with the
    damped, bounded Levenberg-Marquardt of :mod:`~learnest_codegen.diagnosis.refine`.

    With ``whitened`` (and ``settings.whiten_order`` > 0), by generalised least squares after
    the ordinary fit: residual and Jacobian filtered by the autoregression of the ordinary fit's
    residual, per run and state (:func:`~learnest_codegen.diagnosis.search.ar_filters`, the
    filter held fixed while the parameters move). An observer's smoothing correlates the one-step
    residual over many samples; ordinary least squares weighs the slow scatter as much as the
    sharp events that fix an effect (a late torque's steps), and the whitened fit estimates such a
    parameter several times more precisely (the Wald statistic of the selection uses the same
    whitening)."""
    base = np.array([float(system.params[e.channel.split(":", 1)[1]]) if e.channel.startswith("param:")
                     else 0.0 for e in effects])
    lo, hi = bounds(system, effects, settings.bound)
    its = settings.refine_iterations if iterations is None else iterations

    def evaluate(values):
        r, J = one_step(system, effects, values, pairs)
        d = weighted(r, J, rows, sigma)
        return d.R.ravel(), d.Phi.reshape(-1, len(effects))

    plain = refine(evaluate, np.asarray(theta, float), lo, hi, lambda th: base + th, iterations=its,
                   max_step=settings.max_step)
    order = settings.whiten_order
    if not whitened or order <= 0 or not plain.ok:
        return plain
    r, _ = one_step(system, effects, plain.theta, pairs, with_features=False)
    filters = ar_filters(weighted(r, np.zeros(r.shape + (0,)), rows, sigma).R, pairs.segment, order)

    def evaluate_white(values):
        r, J = one_step(system, effects, values, pairs)
        d = weighted(r, J, rows, sigma)
        P, R, _ = apply_ar(d.Phi, d.R, filters, pairs.segment, order)
        return R.ravel(), P.reshape(-1, len(effects))

    white = refine(evaluate_white, plain.theta, lo, hi, lambda th: base + th, iterations=its,
                   max_step=settings.max_step)
    return white if white.ok else plain


def fit_effects(system: System, effects: Sequence[Effect], pairs: Pairs, rows: Sequence[int],
                sigma: np.ndarray, spurious: np.ndarray | None = None,
                settings: FitSettings = FitSettings(), labels: np.ndarray | None = None,
                error: FitData | None = None) -> EffectFit:
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
    error : the observer's own error on a calibration run, weighted, every feature at the prior
        (:func:`~learnest_codegen.diagnosis.floor.noise_floor`): a delay or a lag must stand above
        what the same fit finds there.
    """
    spurious = np.zeros(len(effects)) if spurious is None else np.asarray(spurious, float)
    prob = _Problem(system, effects, pairs, rows, sigma, spurious, labels, settings)
    data0 = prob.data(np.zeros(len(effects)))
    first = baseline(data0, settings, [j for j, e in enumerate(effects) if e.starts])
    groups = _groups(effects)
    # a multi-parameter effect (a group) is a candidate as a whole, through its first column
    pool = [j for j in first.pool if groups[j][0] == j and all(k in first.pool for k in groups[j])]
    if error is not None:  # fitted within the same physical ranges as the data
        error = FitData(error.R, error.Phi, error.sigma, error.spurious, None, prob.lo, prob.hi, error.runs)
    search = Search(effects, prob.data, prob.local, prob.refit, pool, groups, first, settings, error)
    swapped = []
    search.forward()
    for _ in range(settings.rounds):
        moved = False
        if search.chosen:
            moved |= _swap(search, swapped)
        moved |= search.backward()
        moved |= search.forward()
        moved |= search.exchange()
        moved |= search.rephrase()
        moved |= search.restart()
        if not moved:
            break
    excess = float(np.mean(search.data.R ** 2)) - 1.0  # what the ordinary fit leaves above the floor
    if search.chosen and settings.whiten_order > 0 and excess <= settings.gls_excess:
        # the final parameters by generalised least squares, when what is left is noise (an
        # observer's correlated scatter): an autoregression fitted to a residual far above the
        # floor whitens unmodelled dynamics, and the refit then drifts from every run's own fit
        # (DART's Coulomb friction 15.5 where each run's ordinary fit gives 3.3-3.9)
        search.theta, search.status = prob.refit(search.theta, search.chosen, whitened=True)
        search.data = prob.data(search.theta)
    chosen, theta, data = search.chosen, search.theta, search.data
    G, b, c = grams(data, settings=settings)
    cv_share = float(np.clip((first.total - cv_sse(G, b, c, chosen, data.lo, data.hi).sum()) / first.gap,
                             0.0, 1.0)) if chosen else 0.0
    total_in, sse_in = float(np.sum(data0.R ** 2)), float(np.sum(data.R ** 2))
    gap_in = max(total_in - data0.floor, 0.01 * data0.floor)
    share_in = float(np.clip((total_in - sse_in) / gap_in, 0.0, 1.0)) if chosen else 0.0
    losses = np.array([_in_sample_loss(data, theta, chosen, groups[j]) / len(groups[j]) for j in chosen])
    explained = (losses * share_in / losses.sum() if losses.sum() > 0
                 else np.full(len(chosen), share_in / max(len(chosen), 1)))
    std = block_bootstrap(data.columns(chosen), settings).std(axis=0) if chosen else np.zeros(0)
    name = lambda j: effects[j].name  # noqa: E731
    return EffectFit(chosen, theta[chosen], std, explained,
                     np.array([first.single.get(j, 0.0) for j in chosen]), share_in,
                     first.gap, first.total, [{**st, "effect": name(st["index"]),
                                               **({"with": name(st["with"])} if "with" in st else {})}
                                              for st in search.steps if st["index"] in chosen],
                     search.rejected, [aliases(data0, j, pool, settings)
                                       + [k for k, v in first.duplicates.items() if v == j] for j in chosen],
                     first.duplicates, search.status,
                     [{**d, "effect": name(d["index"])} for d in search.dropped], swapped,
                     [_equivalents(data, j, theta[j], first.duplicates) for j in chosen],
                     [{**e, "removed": [name(r) for r in e["removed"]] if isinstance(e["removed"], list)
                       else name(e["removed"]), "added": [name(a) for a in e["added"]]}
                      for e in search.exchanged],
                     [{**st, "effect": name(j)} for j, st in search.blocked.items() if j not in chosen],
                     cv_share)


def _mirrored(effect: Effect) -> Effect:
    """A ``filter:<u>`` effect run backwards in time (a delay becomes an advance)."""
    import dataclasses

    forward = effect.transform
    return dataclasses.replace(effect, transform=lambda u, dt, th: forward(u[::-1], dt, th)[::-1])


def _in_sample_loss(data: FitData, theta: np.ndarray, chosen: list[int], js: list[int]) -> float:
    """In-sample sum of squares added when the columns ``js`` leave the final set (the others
    refitted, linearised)."""
    R = data.R + sum(data.Phi[:, :, k] * theta[k] for k in js)
    rest = [i for i in chosen if i not in js]
    if not rest:
        return float(np.sum(R ** 2) - np.sum(data.R ** 2))
    lo, hi = data.lo.copy(), data.hi.copy()
    lo[js] += theta[js]
    hi[js] += theta[js]
    without = FitData(R, data.Phi, data.sigma, data.spurious, data.labels, lo, hi, data.runs)
    d = fit_step(without, rest)
    P = data.Phi[:, :, rest].reshape(-1, len(rest))
    e = R.ravel() - P @ d
    return float(e @ e - np.sum(data.R ** 2))


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


def _bounded(effect: Effect) -> bool:
    return bool(np.isfinite(effect.lower) or np.isfinite(effect.upper))


def _preference(effect: Effect) -> int:
    """A parameter of the system's own prior is preferred to a generic effect it is equivalent to."""
    return 1 if effect.channel.startswith("param:") else 0


def _swap(search: Search, swapped: list[dict]) -> bool:
    """Replace a chosen generic effect by an unchosen prior parameter when the two sets fit the
    data equally well (in-sample SSE within ``swap_tol`` of the total, linearised at ``theta``) and
    its range is bounded too (a prior parameter of value 0 has no sign to keep: the ground robot's
    ``C_D`` stays an alias of a quadratic drag >= 0)."""
    effects, data, theta, chosen = search.effects, search.data, search.theta, list(search.chosen)
    P = data.Phi.reshape(-1, data.Phi.shape[2])
    R = data.R.ravel() + P[:, chosen] @ theta[chosen]  # the residual with the chosen effects removed

    def sse(cols):
        th = np.linalg.lstsq(P[:, cols], R, rcond=None)[0]
        e = R - P[:, cols] @ th
        return float(e @ e)

    current = sse(chosen)
    tol = search.settings.swap_tol * float(R @ R)
    new, theta = list(chosen), theta.copy()
    for j in list(chosen):
        if len(search.groups[j]) > 1 or _preference(effects[j]) == 1:
            continue
        for c in search.pool:
            if c in new or len(search.groups[c]) > 1 or _preference(effects[c]) <= _preference(effects[j]) \
                    or not _bounded(effects[c]) and _bounded(effects[j]):
                continue  # a parameter without a sign (a prior's 0) would lose the effect's physical range
            cols = [c if k == j else k for k in new]
            value = sse(cols)
            if abs(value - current) <= tol:  # the same model on these data, not a better one
                swapped.append({"removed": effects[j].name, "added": effects[c].name,
                                "sse": value, "sse_before": current})
                theta[j] = 0.0
                new, current = cols, value
                break
    if new == chosen:
        return False
    return search._apply(new, theta, new=False)
