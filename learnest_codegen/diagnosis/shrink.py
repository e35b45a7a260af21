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
  the floor at most ``explained_gap``, or within that of the true dynamics in simulation), no
  estimator rejects it, and every estimator's corrected held-out MSE is within
  ``explained_estimator`` (20 %) of the level the data support: the true dynamics' estimator on
  the same data in simulation, else the corrected estimator on a run its own model generated
  with the held-out inputs and the system's measurement noise (:func:`_own_level`);
* ``partly explained`` - it closes at least a quarter of the held-out gap but is not at the floor,
  an estimator rejects it, or an estimator stays above the supported level (the reason says
  which, by how much, and which kinds the library tried);
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
        own: list[float] = []  # the corrected estimator on data its own model generated
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
            if not simulated:
                own.append(_own_level(system, chosen, h, estimators["corrected"], settings, reference, name))
        scores = {k: float(np.mean(v)) for k, v in errors.items()}
        estimates[name] = {k: np.concatenate(v) for k, v in x_hats.items()}
        truth = simulated or held[0].segment.run.x is not None
        supported, how = ((scores["true"], "the true dynamics' estimator on the same data")
                          if "true" in scores else (float(np.mean(own)), _OWN)
                          if own and np.all(np.isfinite(own))
                          else (None, "not measured (the corrected model's own run failed)"))
        if "true" not in scores and supported is not None and supported > scores["prior"]:
            supported, how = None, (f"not measured: the corrected model's own run ({supported:.4g}) is worse "
                                    f"than the prior's estimator on the data, so it is no level the data "
                                    f"support (run open loop, it leaves the data's range)")
        entry = {"metric": "MSE against " + (reference or ("the truth" if truth else
                                                           "the observer's state observations")),
                 **scores, "before": scores["prior"], "after": scores["corrected"],
                 "closed": closed(scores["prior"], scores["corrected"], scores.get("true")),
                 "supported": supported, "supported_by": how,
                 "above_supported": None if not supported else scores["corrected"] / supported - 1.0,
                 "per_segment": {k: [float(x) for x in v] for k, v in errors.items()},
                 "verdict": estimator_verdict(scores["prior"], scores["corrected"], settings.worse_tolerance)}
        if "knode" in scores:
            entry["closed_knode"] = closed(scores["prior"], scores["knode"], scores.get("true"))
        out[name] = entry
    return out, estimates


_OWN = ("the corrected estimator on a run its own model generated (the held-out inputs, the "
        "system's measurement noise), scored the same way")


def _own_level(system: System, chosen, h: HeldOut, estimator, settings: DiagnosisSettings,
               reference: str | None, name: str) -> float:
    """The held-out MSE the data could support if the corrected model were exact: its own run.

    The corrected model (filters included) is driven by the held-out segment's inputs from its
    start state, measured through the system's outputs with its measurement noise (seeded), and
    the corrected estimator runs on that; it is scored as the real segment is: against the truth
    when the segment's reference is the truth or a recording's own, else against the same
    observer's states of the synthetic run. ``inf`` when the model cannot be simulated."""
    from ..data import Run
    from ..evaluation import run_estimator
    from ..observers import observe
    from ..simulation import integrate_interval

    seg, run = h.segment, h.segment.run
    model = corrected_system(system, chosen, h.theta)
    dt = float(np.median(np.diff(run.t)))
    seen = filter_inputs(system, chosen, h.theta, run.u, dt)
    try:
        x = np.empty((len(run), system.nx))
        x[0] = seg.x0
        for k in range(len(run) - 1):
            x[k + 1] = integrate_interval(model, "prior", x[k], seen[k], run.t[k + 1] - run.t[k], run.t[k])
        rng = np.random.default_rng(settings.seed + 4_242)
        y = np.asarray(system.h(x, run.u))
        y = y + rng.normal(size=y.shape) * np.asarray(system.noise.measurement_std)
        synthetic = Run(run.t, run.u, y, x, run.system)
        target = x if reference is not None or run.x is not None else \
            observe(synthetic, system, settings.observer).zeta
        res = run_estimator(estimator, dataclasses.replace(synthetic, u=seen), seg.x0, f"{name}:own")
        return _mse(res.x_hat, target)
    except Exception:  # noqa: BLE001 - an unstable corrected model has no level to offer
        return float("inf")


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
                       settings: DiagnosisSettings, tried: Sequence[str] = ()) -> tuple[str, str]:
    """The overall verdict (see the module docstring) and the sentence that states why, in terms
    of the held-out figures only; short of "explained", it says what is left and (``tried``)
    which kinds of effect the library offered."""
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
    short = _short_of_supported(result, settings)
    kinds = f"; kinds tried: {', '.join(tried)}" if tried else ""
    if one["after"] <= floor and not against and not short:
        ran = [n.upper() for n in ests]
        return "explained", (f"the corrected prior's held-out residual is within the noise floor "
                             f"({one['after']:.3g} noise units^2 above it, at most {floor:.3g} allowed)"
                             + (f" and the {' and the '.join(ran)} reach the error the data support "
                                f"(within {settings.explained_estimator:.0%})" if ran else
                                "; the estimators were not run, so their error is not checked"))
    if share >= 0.25:
        why = (f"the {' and the '.join(against)} held-out MSE gets worse with the correction" if against else
               f"the corrected residual stays above the noise floor ({one['after']:.3g} noise units^2 above "
               f"it; 'explained' needs at most {floor:.3g})" if one["after"] > floor else short)
        return "partly explained", (f"it closes {share:.1%} of the held-out gap (at least 25 %), "
                                    f"but {why}{kinds}")
    return "unexplained", (f"the correction closes only {share:.1%} of the held-out gap (less than 25 %)"
                           f"{kinds}")


def _short_of_supported(result: dict, settings: DiagnosisSettings) -> str:
    """What keeps the estimators from "explained": each one whose corrected held-out MSE is more
    than ``explained_estimator`` above the level the data support (or whose level could not be
    measured), in words; ``""`` when none."""
    words = []
    for n in settings.estimators:
        entry = result.get(n)
        if entry is None:
            continue
        if entry.get("supported") is None:
            words.append(f"the {n.upper()}'s supported error could not be measured")
        elif entry["above_supported"] > settings.explained_estimator:
            words.append(f"the {n.upper()}'s held-out error stays {entry['above_supported']:.0%} above "
                         f"what the data support ({entry['after']:.4g} against {entry['supported']:.4g}, "
                         f"{entry['supported_by']})")
    return "; ".join(words)
