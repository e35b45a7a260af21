"""How far the gap shrinks on held-out data, and the verdicts that evidence supports.

Each held-out segment comes with the correction fitted *without* it (a :class:`HeldOut`): the end
of a single run with the fit on its start, the last run with the fit on the others, or, with
pooled runs, every run in turn with the effects refitted on all the others. On it are compared
the one-step residual and the nominal estimators' MSE of the prior, the corrected prior, the
KNODE model and (in simulation) the true dynamics.

Verdicts are tied to that evidence, and every estimator is judged on its own: a correction that
helps the MHE may hurt the UKF (a steep Coulomb term makes the UKF's sigma points straddle a
step). Per estimator: ``improved`` / ``unchanged`` / ``rejected`` (held-out MSE worse by more
than ``worse_tolerance``). Overall:

* ``no gap`` - no residual state above the floor and nothing selected;
* ``refit failed`` - the refinement of the selected effects failed (a verdict, not a traceback);
* ``rejected`` - the correction makes the held-out one-step residual worse, or every estimator
  run worse: its effects are reported under ``rejected_effects``, not as findings;
* ``explained`` - the corrected prior's held-out residual is within the floor (mean square above
  the floor at most ``explained_gap``, or within that of the true dynamics in simulation) and no
  estimator rejects it;
* ``partly explained`` - it closes at least a quarter of the held-out gap but is not at the floor,
  or an estimator rejects it;
* ``unexplained`` - nothing selected, or less than a quarter closed.

The verdict follows the held-out figures only (the held-out gap closed, the corrected residual
against the floor, the estimators' held-out MSE); the in-sample share explained, reported beside
it, never decides it. :func:`verdict_and_reason` gives the sentence that says which rule applied.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..systems import System
from .effects import Effect, corrected_system, filter_inputs
from .fit import Pairs
from .segments import Segment, pairs_of
from .settings import DiagnosisSettings
from .where import gap_size, model_residual


@dataclass(frozen=True)
class HeldOut:
    """A held-out segment and the effect parameters fitted without it."""

    segment: Segment
    theta: np.ndarray


def has_truth_model(system: System) -> bool:
    return system.true_dynamics is not None or dict(system.true_params) != dict(system.params)


def shrink(system: System, chosen: Sequence[Effect], held: Sequence[HeldOut], model, sigma, rows,
           settings: DiagnosisSettings, work_dir, run_estimators: Sequence[int] | None = None,
           reference: str | None = None):
    """Held-out one-step gaps and estimator MSEs; returns ``(shrink, residuals, estimates, pairs)``.

    ``run_estimators``: indices into ``held`` the estimators run on (default: all).
    ``reference``: what the segments' references are, for the report (default: the truth, or
    the observer's state observations).
    """
    simulated = all(h.segment.run.x is not None for h in held) and has_truth_model(system)
    fixed = {"prior": lambda x, u: system.f(x, u)}
    if model is not None:
        fixed["knode"] = lambda x, u: system.f(x, u) + model.net.casadi(x, u)
    if simulated:
        fixed["true"] = lambda x, u: system.f(x, u, variant="true")
    pairs = pairs_of([h.segment for h in held])
    residuals = {k: model_residual(system, f, pairs) for k, f in fixed.items()}
    corrected = []
    for h in held:
        c = corrected_system(system, chosen, h.theta)
        own = pairs_of([h.segment])
        if any(e.is_filter for e in chosen):  # the corrected prior sees the filtered commands
            filters = [(e, t) for e, t in zip(chosen, h.theta) if e.is_filter]
            own = dataclasses.replace(own, u=own.filtered(system, *zip(*filters))[0])
        corrected.append(model_residual(system, lambda x, u, c=c: c.f(x, u), own))
    residuals["corrected"] = np.concatenate(corrected)
    gaps = {k: gap_size(r, sigma, rows) for k, r in residuals.items()}
    one = {"metric": "mean square of the residual-state residual above the noise floor [noise units^2]",
           **gaps, "before": gaps["prior"], "after": gaps["corrected"],
           "closed": closed(gaps["prior"], gaps["corrected"], gaps.get("true")),
           "rms": {k: dict(zip(system.state_names, np.sqrt(np.mean(r**2, axis=0)).tolist()))
                   for k, r in residuals.items()},
           "rms_over_floor": {k: float(np.sqrt(np.mean((r[:, rows] / sigma[rows]) ** 2)))
                              for k, r in residuals.items()},
           "per_segment": _per_segment(residuals, pairs, sigma, rows)}
    if "knode" in gaps:
        one["closed_knode"] = closed(gaps["prior"], gaps["knode"], gaps.get("true"))
    out, estimates = {"one_step": one}, {}
    if settings.estimators:
        picked = list(range(len(held))) if run_estimators is None else list(run_estimators)
        est, estimates = _estimators(system, chosen, model, [held[i] for i in picked], simulated, settings,
                                     work_dir, reference)
        out.update(est)
    return out, residuals, estimates, pairs


def _per_segment(residuals: dict, pairs: Pairs, sigma, rows) -> list[dict]:
    return [{k: gap_size(r[pairs.segment == s], sigma, rows) for k, r in residuals.items()}
            for s in np.unique(pairs.segment)]


def closed(before: float, after: float, floor: float | None) -> float | None:
    """Share of the gap from ``before`` down to ``floor`` (0 if none) that ``after`` closes."""
    base = before - (floor or 0.0)
    return float((before - after) / base) if base > 0 else None


def _key(chosen: Sequence[Effect], theta: np.ndarray) -> str:
    text = json.dumps([[e.name for e in chosen], [float(v) for v in theta]])
    return "corrected-" + hashlib.sha256(text.encode()).hexdigest()[:16]


def _estimators(system, chosen, model, held: Sequence[HeldOut], simulated, settings, work_dir,
                reference=None):
    """Run each nominal estimator with each model on the held-out segments; mean MSE per model."""
    import tempfile

    from ..evaluation import run_estimator
    from ..export import hybrid_model, prior_model, true_model
    from ..pipeline import ResolvedModel, make_estimator

    fixed = {"prior": (prior_model(system), "nominal")}
    if model is not None:
        fixed["knode"] = (hybrid_model(system, model.net), model.hash)
    if simulated:
        fixed["true"] = (true_model(system), "true")
    root = Path(work_dir) if work_dir else Path(tempfile.mkdtemp(prefix="learnest_diagnose_"))
    out, estimates = {}, {}
    for name in settings.estimators:

        def build(discrete, model_hash, label, name=name):
            return make_estimator(ResolvedModel(discrete, model_hash), name, backend=settings.backend,
                                  out=root / "compiled" / label)

        labels = ["prior", "corrected", *(k for k in fixed if k != "prior")]
        errors: dict[str, list[float]] = {k: [] for k in labels}
        x_hats: dict[str, list[np.ndarray]] = {k: [] for k in errors}
        built = {label: build(d, h, label) for label, (d, h) in fixed.items()}
        for h in held:
            key = _key(chosen, h.theta)
            estimators = {**built, "corrected": build(prior_model(corrected_system(system, chosen, h.theta)),
                                                      key, key)}
            seg = h.segment
            for label, estimator in estimators.items():
                run = seg.run
                if label == "corrected" and any(e.is_filter for e in chosen):
                    run = dataclasses.replace(run, u=filter_inputs(system, chosen, h.theta, run.u,
                                                                   float(np.median(np.diff(run.t)))))
                try:
                    res = run_estimator(estimator, run, seg.x0, f"{name}:{label}")
                    value, x_hat = _mse(res.x_hat, seg.reference), res.x_hat
                except Exception as exc:  # noqa: BLE001 - a diverging estimator is evidence, not a crash
                    value, x_hat = float("inf"), np.full_like(seg.reference, np.nan)
                    out.setdefault("failures", []).append(f"{name}:{label}: {exc}")
                errors[label].append(value)
                x_hats[label].append(x_hat)
        scores = {k: float(np.mean(v)) for k, v in errors.items()}
        estimates[name] = {k: np.concatenate(v) for k, v in x_hats.items()}
        truth = simulated or held[0].segment.run.x is not None
        entry = {"metric": "MSE against " + (reference or ("the truth" if truth else
                                                           "the observer's state observations")),
                 **scores, "before": scores["prior"], "after": scores["corrected"],
                 "closed": closed(scores["prior"], scores["corrected"], scores.get("true")),
                 "per_segment": {k: [float(x) for x in v] for k, v in errors.items()},
                 "verdict": estimator_verdict(scores["prior"], scores["corrected"], settings.worse_tolerance)}
        if "knode" in scores:
            entry["closed_knode"] = closed(scores["prior"], scores["knode"], scores.get("true"))
        out[name] = entry
    return out, estimates


def _mse(x_hat: np.ndarray, reference: np.ndarray) -> float:
    """Mean square error over samples and states, over the reference's finite cells."""
    err = (np.asarray(x_hat) - reference) ** 2
    ok = np.isfinite(reference)
    return float(np.mean(err[ok])) if ok.all() else float(np.nanmean(np.where(ok, err, np.nan)))


def estimator_verdict(before: float, after: float, tolerance: float) -> str:
    """``rejected`` if the corrected MSE is worse by more than ``tolerance`` (relative), ``improved``
    if better by more, else ``unchanged``."""
    if not np.isfinite(after) or after > before * (1 + tolerance):
        return "rejected"
    return "improved" if after < before * (1 - tolerance) else "unchanged"


def by_estimator(names: Sequence[str], result: dict, estimators: Sequence[str]) -> dict:
    """Per estimator: its verdict on the correction, its held-out MSE before and after, and the
    effects that are findings *for it* (``found``: the correction improved it) or rejected by it
    (``rejected``: it made it worse); with ``unchanged`` the effects are neither."""
    out = {}
    for n in estimators:
        if n not in result:
            continue
        v = result[n]["verdict"]
        out[n] = {"verdict": v, "before": result[n]["before"], "after": result[n]["after"],
                  "found": list(names) if v == "improved" else [],
                  "rejected": list(names) if v == "rejected" else []}
    return out


def verdict(gap_present: bool, chosen: bool, refit: str, result: dict, settings: DiagnosisSettings) -> str:
    """The overall verdict from the held-out evidence (see the module docstring)."""
    return verdict_and_reason(gap_present, chosen, refit, result, settings)[0]


def verdict_and_reason(gap_present: bool, chosen: bool, refit: str, result: dict,
                       settings: DiagnosisSettings) -> tuple[str, str]:
    """The overall verdict (see the module docstring) and the sentence that states why, in terms
    of the held-out figures only."""
    if not gap_present:
        return "no gap", "no residual state is above the noise floor and no effect passes the tests"
    if refit.startswith("failed"):
        return "refit failed", f"the joint refit of the selected effects failed ({refit})"
    if not chosen:
        return "unexplained", "no effect of the library passes the selection's tests"
    one = result["one_step"]
    ests = {n: result[n]["verdict"] for n in settings.estimators if n in result}
    if one["after"] > one["before"]:
        return "rejected", "the correction makes the held-out one-step residual worse"
    if ests and all(v == "rejected" for v in ests.values()):
        return "rejected", "every estimator's held-out MSE gets worse with the correction"
    against = [n.upper() for n, v in ests.items() if v == "rejected"]
    floor = settings.explained_gap + (one["true"] if "true" in one else 0.0)
    share = one["closed"] if one["closed"] is not None else 0.0
    if one["after"] <= floor and not against:
        return "explained", (f"the corrected prior's held-out residual is within the noise floor "
                             f"({one['after']:.3g} noise units^2 above it, at most {floor:.3g} allowed)")
    if share >= 0.25:
        why = (f"the {' and the '.join(against)} held-out MSE gets worse with the correction" if against else
               f"the corrected residual stays above the noise floor ({one['after']:.3g} noise units^2 above "
               f"it; 'explained' needs at most {floor:.3g})")
        return "partly explained", f"it closes {share:.1%} of the held-out gap (at least 25 %), but {why}"
    return "unexplained", f"the correction closes only {share:.1%} of the held-out gap (less than 25 %)"
