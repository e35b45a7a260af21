"""Diagnosing the sim-to-real gap of a prior: where it lies, which effect causes it, how far it shrinks.

``diagnose(system, runs)`` answers three questions from recorded runs:

1. **Where.** The one-step residual of the prior, a derivative error per state
   (:func:`~learnest_codegen.diagnosis.fit.one_step`), computed from state observations: the truth
   when a run has it, otherwise the system's pre-training observer. Per state: its share of the
   gap and its size relative to the noise floor (``snr``); binned over the states, inputs and
   time (regimes, drifts); and, given a trained KNODE model, how the learned residual compares.
2. **Which.** The effect library (:mod:`~learnest_codegen.diagnosis.effects`: physical kinds
   and one candidate per parameter of the prior) fitted by sparse, cross-validated selection
   against the remaining gap (:mod:`~learnest_codegen.diagnosis.selection`): ranked effects with
   parameters, bootstrap uncertainty and held-out shares, or "unexplained".
3. **How far it shrinks.** On held-out data (the last run, the last ``holdout`` of a single run,
   or with pooled runs every run in turn, :mod:`~learnest_codegen.diagnosis.pooling`): the
   one-step residual and the nominal estimators' MSE with the prior, the corrected prior, the
   KNODE model and (in simulation) the true dynamics; verdicts from that evidence, one per
   estimator (:mod:`~learnest_codegen.diagnosis.shrink`).

The noise floor that every test is measured against is in :mod:`~learnest_codegen.diagnosis.floor`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from ..data import Run
from ..errors import DataError, ModelMismatchError
from ..systems import System
from .cv import fold_labels
from .effects import Effect, default_context, library
from .findings import effects_json, step_json
from .fit import Pairs, one_step
from .floor import noise_floor
from .loading import Recordings
from .pooling import consistency, leave_one_out
from .segments import missing, observations, pairs_of, split
from .selection import EffectFit, fit_effects
from .settings import DiagnosisSettings
from .shrink import HeldOut, by_estimator, shrink, verdict_and_reason
from .where import knode_comparison, where


@dataclass
class Diagnosis:
    """The result: ``report`` is the JSON content, the rest feeds the figures."""

    system: System
    report: dict
    fit_pairs: Pairs
    heldout_pairs: Pairs
    residual: np.ndarray  # (N, nx) prior residual on the fit data
    sigma: np.ndarray  # (nx,) noise floor per state
    heldout_residuals: dict[str, np.ndarray]  # model -> (M, nx)
    effects: list[Effect]
    fit: EffectFit
    estimates: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def write(self, out: str | Path) -> Path:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        path = out / "diagnosis.json"
        path.write_text(json.dumps(self.report, indent=2))
        return path


def diagnose(system: System, runs: "Sequence[Run] | Recordings", *, model=None,
             settings: DiagnosisSettings = DiagnosisSettings(), work_dir: str | Path | None = None,
             progress: bool = False) -> Diagnosis:
    """Diagnose the prior of ``system`` on ``runs`` (see the module docstring).

    Parameters
    ----------
    system : the system (its prior is diagnosed).
    runs : recorded or simulated runs of it, or :class:`~learnest_codegen.diagnosis.loading.Recordings`
        (runs with their own references, start states and the recordings skipped).
    model : an optional KNODE model to compare with: a
        :class:`~learnest_codegen.learning.training.TrainedModel`, or the path (``str`` or
        ``Path``) of a trained model directory, loaded for ``system``.
    settings : :class:`~learnest_codegen.diagnosis.settings.DiagnosisSettings`.
    work_dir : where compiled estimators go (C backend); a temporary folder by default.
    progress : show a progress bar.

    Returns
    -------
    Diagnosis
        ``report`` holds the JSON content; the verdict is ``report["verdict"]`` (why:
        ``report["verdict_reason"]``) and each estimator's under ``report["estimator_verdicts"]``.
    """
    from tqdm.auto import tqdm

    start = time.perf_counter()
    model = _model(system, model)
    found = runs if isinstance(runs, Recordings) else \
        Recordings(list(runs), [f"run {i}" for i in range(len(runs))])
    if not found.runs:
        raise DataError("diagnose: no runs given")
    bar = tqdm(total=5, desc=f"diagnosing {system.name}", disable=None if progress else True)
    source, segments = observations(system, found.runs, settings, found.references, found.starts)
    pooled = len(segments) >= 2  # runs are fitted together, each held out in turn
    fit_segs, held_segs = (segments, []) if pooled else split(segments, settings.holdout)
    fit_pairs = pairs_of(fit_segs)
    labels, fold_method = fold_labels(fit_pairs, settings.fit.folds)
    bar.update()

    vel = default_context(system).velocity_states
    speed = {v: float(np.sqrt(np.mean(fit_pairs.x[:, system.state_names.index(v)] ** 2))) for v in vel}
    umax = dict(zip(system.input_names, np.max(np.abs(fit_pairs.u), axis=0).tolist()))
    effects = library(system, default_context(system, speed, umax), settings.kinds)
    r0, _ = one_step(system, effects, np.zeros(len(effects)), fit_pairs, with_features=False)
    sigma, floor_method, spurious, observer_error = noise_floor(system, effects, fit_segs, fit_pairs, r0,
                                                                source, settings)
    rows = [system.state_names.index(s) for s in system.residual_state_names]
    bar.update()

    var = np.concatenate([s.var[pairs_of([s]).k] for s in fit_segs]) if fit_segs[0].var is not None else None
    where_part = where(system, r0, sigma, fit_pairs, settings, var)
    if model is not None:
        where_part["knode"] = knode_comparison(system, model, fit_pairs, r0, rows)
    bar.update()

    fit = fit_effects(system, effects, fit_pairs, rows, sigma[rows], spurious, settings.fit, labels,
                      observer_error)
    chosen = [effects[j] for j in fit.chosen]
    bar.update()

    if pooled:
        held, fold_status = leave_one_out(system, chosen, fit.theta, segments, rows, sigma[rows],
                                          settings.fit)
        run_estimators = list(range(max(len(held) - settings.estimator_runs, 0), len(held)))
    else:
        held, fold_status = [HeldOut(s, fit.theta) for s in held_segs], []
        run_estimators = None
    per_run = consistency(system, chosen, fit.theta, fit_segs, rows, sigma[rows], settings.fit)
    result, held_res, estimates, held_pairs = shrink(system, chosen, held, model, sigma, rows, settings,
                                                     work_dir, run_estimators, found.reference)
    bar.update()
    bar.close()
    gap_present = bool(fit.chosen) or any(s["gap"] for s in where_part["states"])
    tried = list(dict.fromkeys(e.kind for e in effects))
    overall, reason = verdict_and_reason(gap_present, bool(chosen), fit.refit, result, settings, tried)
    entries = effects_json(system, effects, fit)
    per_estimator = by_estimator([e["name"] for e in entries], result, settings.estimators)
    for e in entries:
        e["estimators"] = {n: v["verdict"] for n, v in per_estimator.items()}
    report = {
        "system": system.name, "source": source,
        "observer": settings.observer or (system.default_observer if source == "observer" else None),
        "runs": len(found.runs), "names": list(found.names), "skipped": dict(found.skipped),
        "missing": missing(found.runs), "pooled": pooled, "folds": fold_method,
        "basis": (f"{len(found.runs)} runs fitted together, each held out in turn" if pooled else
                  f"one run: fitted on its first {1 - settings.holdout:.0%}, scored on the rest; the "
                  f"findings rest on this one run (a folder of runs holds each out in turn and checks "
                  f"that each effect is the same on every run)"),
        "reference": found.reference,
        "fit_pairs": len(fit_pairs), "heldout_pairs": len(held_pairs),
        "noise_floor": {"method": floor_method,
                        "sigma": dict(zip(system.state_names, map(float, sigma)))},
        "where": where_part["states"], "regimes": where_part["regimes"],
        "knode": where_part.get("knode"),
        "effects": [] if overall == "rejected" else entries,
        "rejected_effects": entries if overall == "rejected" else [],
        "explained_in_sample": float(fit.explained_total) if gap_present else 0.0,
        "heldout_gap_closed": result["one_step"]["closed"],
        "verdict": overall, "verdict_reason": reason,
        "estimator_verdicts": {n: v["verdict"] for n, v in per_estimator.items()},
        "by_estimator": per_estimator,
        "consistency": per_run,
        "selection": {"steps": [step_json(effects, s) for s in fit.steps],
                      "stopped_at": step_json(effects, fit.rejected) if fit.rejected else None,
                      "dropped": fit.dropped, "swapped": fit.swapped, "exchanged": fit.exchanged,
                      "blocked": fit.blocked, "refit": fit.refit,
                      "cross_validated_share": fit.cv_explained,
                      "heldout_refits": fold_status,
                      "library_size": len(effects),
                      "duplicates": {effects[k].name: effects[v].name for k, v in fit.duplicates.items()}},
        "shrink": result,
        "settings": settings.to_json(),
        "seconds": time.perf_counter() - start,
    }
    return Diagnosis(system, report, fit_pairs, held_pairs, r0, sigma, held_res, effects, fit, estimates)


def _model(system: System, model):
    """``model`` as a trained model: loaded from its directory when given a path."""
    if model is None or hasattr(model, "net"):
        return model
    if not isinstance(model, (str, Path)):
        raise ModelMismatchError(f"diagnose: model must be a TrainedModel or the path of a trained model "
                                 f"directory, got {type(model).__name__}")
    from ..learning.training import load_model

    if not ((Path(model) / "model.json").is_file() and (Path(model) / "weights.pt").is_file()):
        raise ModelMismatchError(f"diagnose: {model} is not a trained model directory (it needs model.json "
                                 f"and weights.pt); give the folder `learnest train --out` wrote")
    return load_model(model, system)
