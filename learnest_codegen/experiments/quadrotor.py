"""The paper's quadrotor experiment (section V-C, Fig. 3) on real flights, and protocols that
measure whether a learned model generalises to flights it was not trained on.

A study trains the KNODE residual on one or more flights (``linear_rts`` observations: the
Kalman filter and RTS smoother of the prior ``A x`` on Vicon position and accelerometer; the
paper's 2 layers of 16 tanh, 150 epochs, early stopping on each flight's final 20 %), compiles
the KNODE estimators, and runs them and their nominal counterparts (compiled C, every
estimator of :data:`~learnest_codegen.compilation.ESTIMATOR_NAMES`) on test flights, each from
that flight's first measurements. Scores are against reference states: the truth in
simulation; on real flights Vicon position with velocity and acceleration from Savitzky-Golay
fits of several windows and a central-difference velocity
(:mod:`~learnest_codegen.recordings.references`), per state group; the onboard EKF alongside.

Protocols (:mod:`.quadrotor_protocols`): ``single`` (the paper's: one training flight, every
other flight tested), ``train-test`` (one model on a training set, tested on the rest),
``leave-type-out`` and ``leave-one-out``. Features (:mod:`.quadrotor_models`) pick the model.
With ``tune_noise`` every estimator's noise is chosen on the training flights
(:mod:`.quadrotor_tuning`). Each per-flight result records the gate's rejections and the share
of samples outside the training range (:mod:`learnest_codegen.learning.ranges`); the report
(:mod:`.quadrotor_report`, :mod:`.quadrotor_states`) is paired per flight and per state group.
Progress goes to stderr, one line per step. Measured: ``docs/reports/flights_study.md``.

Layout of OUT::

    OUT/compiled/nominal/                  nominal estimators
    OUT/observations/<flight>.npz          the pre-training observer's states of a flight
    OUT/runs/<fold>/<features>/model/      the trained model (reused while its training is
                                           unchanged); compiled/ its estimators
    OUT/runs/<fold>/<features>.json        per-flight results (reused while the configuration
                                           hash is unchanged)
    OUT/nominal/<flight>.json              the nominal estimators on one flight
    OUT/nominal/tuning/<fold>/<estimator>/ the nominal estimators tuned on a fold (tuning.json)
    OUT/quadrotor.md, quadrotor.json       the paired report
    OUT/quadrotor.png                      paired per-flight MSE, nominal against KNODE
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np

from ..compilation import ESTIMATOR_NAMES, ESTIMATORS
from ..errors import LearnestError, SettingsError, UnknownNameError
from ..export import DiscreteModel
from ..learning.network import NetworkSettings
from ..learning.training import TrainingSettings
from ..systems import System
from ..systems.quadrotor import QUADROTOR
from .quadrotor_cases import GROUPS as GROUPS
from .quadrotor_cases import Case as Case
from .quadrotor_cases import flight_cases as flight_cases
from .quadrotor_cases import flight_paths as flight_paths
from .quadrotor_cases import initial_state as initial_state
from .quadrotor_cases import scores as scores
from .quadrotor_cases import simulated_cases as simulated_cases
from .quadrotor_models import FEATURES as FEATURES
from .quadrotor_models import RECOMMENDED_FEATURES as RECOMMENDED_FEATURES
from .quadrotor_models import Features as Features
from .quadrotor_models import feature_system as feature_system
from .quadrotor_models import trained_model as trained_model
from .quadrotor_models import training_record
from .quadrotor_protocols import PROTOCOLS as PROTOCOLS
from .quadrotor_protocols import folds, pooled
from .quadrotor_report import ONBOARD, Summary, summarise
from .store import code_hash
from .store import content_hash as _hash
from .store import write_json as _write_json

PAPER_IMPROVEMENT = {"KNODE-UKF": 26.6, "KNODE-MHE": 11.9}  # [%] of the median MSE
DEFAULT_TRAIN = "B2_circle_medium_rep1"
DEFAULT_MATRIX = ("B2_circle_slow_rep1", "B2_circle_fast_rep2", "B3_figure8_slow_rep1",
                  "B3_figure8_fast_rep1")


def methods(estimators: Sequence[str]) -> list[tuple[str, str, str]]:
    """``(label, estimator, kind)`` of the nominal and KNODE variant of each estimator."""
    return [(f"{prefix}{ESTIMATORS[e].label}", e, kind) for e in estimators
            for prefix, kind in (("", "nominal"), ("KNODE-", "knode"))]


def pairs(estimators: Sequence[str], tuned: bool = False) -> list[tuple[str, str]]:
    """``(KNODE label, nominal label)`` of each estimator; with ``tuned``, also each KNODE
    estimator against its nominal estimator tuned on the same training flights."""
    out = [(f"KNODE-{ESTIMATORS[e].label}", ESTIMATORS[e].label) for e in estimators]
    return out + [(f"KNODE-{ESTIMATORS[e].label}", tuned_label(e)) for e in estimators if tuned]


def tuned_label(estimator: str) -> str:
    """The label of the nominal ``estimator`` with its noise tuned on the training flights."""
    return f"{ESTIMATORS[estimator].label} (tuned)"


@dataclass(frozen=True)
class StudySettings:
    """How the KNODE model is trained and which estimators run; the paper's defaults.

    ``clamp_inputs`` keeps the net's inputs inside their training range in the compiled
    estimators (``None``: :data:`~learnest_codegen.compilation.CLAMP_INPUTS`).
    ``net_must_beat_prior`` keeps the trained net only when its validation loss beats the prior
    alone (see :func:`~learnest_codegen.learning.runs.train_on_runs`).
    ``tune_noise`` chooses each KNODE estimator's noise scales on the training flights
    (:mod:`.quadrotor_tuning`), and beside them, as a control, each nominal estimator's the same
    way (labels ``"<estimator> (tuned)"``).
    """

    training: TrainingSettings = field(default_factory=lambda: TrainingSettings(
        epochs=150, network=NetworkSettings(layers=2, hidden=16, activation="Tanh")))
    observer: str = "linear_rts"
    estimators: tuple[str, ...] = ("mhe", "ukf")
    clamp_inputs: bool | None = None
    net_must_beat_prior: bool = True
    tune_noise: bool = False

    def __post_init__(self) -> None:
        unknown = [e for e in self.estimators if e not in ESTIMATOR_NAMES]
        if unknown or not self.estimators:
            raise UnknownNameError(f"unknown estimator(s) {unknown or list(self.estimators)}; choose from "
                                   f"{', '.join(ESTIMATOR_NAMES)}")

    def to_json(self) -> dict:
        out = {"training": self.training.to_json(), "observer": self.observer,
               "estimators": list(self.estimators)}
        if self.clamp_inputs is not None:
            out["clamp_inputs"] = self.clamp_inputs
        if not self.net_must_beat_prior:
            out["net_must_beat_prior"] = False
        if self.tune_noise:
            out["tune_noise"] = "prediction"  # the criterion of quadrotor_tuning
        return out


# --- running estimators ---------------------------------------------------------------------------

#: The outputs whose prediction chooses the tuning (quadrotor_tuning: the accelerometer's error
#: is coloured, the motion capture's white).
TUNING_OUTPUTS = ("px", "py", "pz")


def say(progress: bool, text: str) -> None:
    """One progress line on stderr (a terminal or not): long studies are never silent."""
    if progress:
        print(f"[quadrotor] {text}", file=sys.stderr, flush=True)


def _estimators(model, out: Path, settings: StudySettings, estimators: Sequence[str] | None = None,
                system: System = QUADROTOR) -> dict:
    """The study's compiled estimators of ``model`` (see :func:`pipeline.resolve`), by name."""
    from ..pipeline import make_estimator

    clamp = settings.clamp_inputs if not isinstance(model, (str, DiscreteModel)) else None
    return {name: make_estimator(model, name, system=system, out=out, clamp_inputs=clamp)
            for name in (estimators or settings.estimators)}


def _tuned(model, train: Sequence[Case], out: Path, settings: StudySettings, *, system: System = QUADROTOR,
           progress: bool = True, parameters: Sequence = ()) -> tuple[dict, dict]:
    """Each of the study's estimators of ``model`` (or ``"nominal"``) with its noise tuned on
    the training flights (:func:`.quadrotor_tuning.tune`), and each one's tuning record."""
    from .quadrotor_tuning import TUNING_VERSION, reuse, tune

    clamp = settings.clamp_inputs if not isinstance(model, (str, DiscreteModel)) else None
    estimators, record = {}, {}
    what = "nominal" if isinstance(model, str) else "KNODE"
    for name in settings.estimators:
        cache = out / name / "tuning.json"
        ident = _hash({"model": _model_hash(model, system), "estimator": name, "outputs": TUNING_OUTPUTS,
                       "code": code_hash(),
                       "train": [_case_hash(c) for c in train], "version": TUNING_VERSION,
                       **({"parameters": [[p, list(v)] for p, v in parameters]} if parameters else {})})
        stored = json.loads(cache.read_text()) if cache.is_file() else {}
        if stored.get("hash") == ident:
            tuning, estimators[name] = reuse(model, name, out / name, stored["record"], system=system,
                                             clamp_inputs=clamp)
            record[name] = stored["record"]
            say(progress, f"  {what} {name}: tuning reused ({tuning.label})")
            continue
        tuning, estimators[name], record[name] = tune(
            model, name, train, out / name, system=system, clamp_inputs=clamp, outputs=TUNING_OUTPUTS,
            progress=lambda text, n=name: say(progress, f"  tuning {what} {n}: {text}"),
            parameters=parameters)
        _write_json(cache, {"hash": ident, "record": record[name]})
        say(progress, f"  tuned {what} {name}: {tuning.label}, criterion {record[name]['criterion']:.3f}, "
                      f"gate rejects {100 * record[name]['rejected_share']:.2f} % of the training outputs"
            + (f"; on the grid's edge: {record[name]['edge']}" if record[name]["edge"] else ""))
    return estimators, record


def _model_hash(model, system: System) -> str:
    """What identifies a model for the tuning cache: the name, the trained model's weights and
    fitted parameters, or the prior's system and parameters."""
    if isinstance(model, str):
        return f"{model}:{system.name}"
    if isinstance(model, DiscreteModel):
        return _hash({"prior": model.system.name, "params": dict(model.system.params)})
    from ..pipeline import resolve

    return resolve(model, system).hash


def _run_method(estimator, case: Case, model=None) -> dict:
    """Scores of one estimator on one case (per reference and state group), its gate's
    rejections and (with the trained ``model``) the share of samples whose net inputs leave
    the training range."""
    from ..evaluation import run_estimator
    from .quadrotor_tuning import start_state

    try:
        result = run_estimator(estimator, case.run, start_state(case, estimator.nx), type(estimator).__name__)
    except LearnestError as exc:  # an Ipopt failure on one case is a result, not the end
        return {"error": f"{type(exc).__name__}: {exc}", "mse": float("nan")}
    out = {**scores(result.x_hat, case.reference, case.scored_against()),
           "us_per_step": result.seconds_per_step * 1e6,
           "rejected": result.rejections, "rejected_share": result.rejections / len(case.run)}
    if model is not None and not isinstance(model, DiscreteModel):
        from ..learning.ranges import extrapolation

        outside = extrapolation(model, result.x_hat, case.run.u)
        out["outside"] = None if outside is None else outside.share
    return out


def _case_hash(case: Case) -> str:
    return _hash({"samples": len(case.run), "y": float(np.nansum(case.run.y)),
                  "refs": {k: float(np.nansum(v)) for k, v in case.scored_against().items()}})


def nominal_results(cases: Sequence[Case], out: Path, settings: StudySettings,
                    progress: bool = True) -> dict[str, dict]:
    """The nominal estimators (and the onboard EKF) on every case, cached per case in
    ``OUT/nominal``; an estimator added later runs alone."""
    labels = [(label, est) for label, est, kind in methods(settings.estimators) if kind == "nominal"]
    results, estimators = {}, None
    for i, case in enumerate(cases):
        path = out / "nominal" / f"{case.name}.json"
        ident = _hash({"case": _case_hash(case), "settings": settings.to_json(), "code": code_hash()})
        stored = json.loads(path.read_text()) if path.is_file() else {}
        done = stored.get("methods", {}) if stored.get("hash") == ident else {}
        missing = [(label, est) for label, est in labels if label not in done]
        if missing:
            say(progress, f"nominal estimators on {case.name} ({i + 1}/{len(cases)})")
            estimators = estimators or _estimators("nominal", out / "compiled" / "nominal", settings)
            done.update({label: _run_method(estimators[est], case) for label, est in missing})
            if case.onboard is not None:
                done[ONBOARD] = scores(case.onboard, case.reference, case.scored_against())
            _write_json(path, {"hash": ident, "methods": done})
        results[case.name] = {k: v for k, v in done.items() if k in dict(labels) or k == ONBOARD}
    return results


def train_and_test(train: Case | Sequence[Case], tests: Sequence[Case], features: str, out: Path,
                   settings: StudySettings = StudySettings(), *, label: str | None = None,
                   force: bool = False, progress: bool = True) -> dict:
    """Train on ``train`` (one case or several) with ``features``, compile, and run the KNODE
    estimators on ``tests``.

    Returns (and writes to ``OUT/runs/<label>/<features>.json``; ``label`` defaults to the
    training case's name) ``{"train", "train_cases", "features", "hash", "training": {...},
    "tuning": {...}, "cases": {case: {label: scores}}}``; a file with the same configuration
    hash is reused unless ``force``.
    """
    train = (train,) if isinstance(train, Case) else tuple(train)
    label = label or (train[0].name if len(train) == 1 else "+".join(c.name for c in train))
    path = out / "runs" / label / f"{features}.json"
    ident = _hash({"train": [c.name for c in train], "samples": [len(c.run) for c in train],
                   "features": features, "tests": [c.name for c in tests], "settings": settings.to_json(),
                   "references": [_case_hash(c) for c in tests], "code": code_hash()})
    if not force and path.is_file() and json.loads(path.read_text()).get("hash") == ident:
        say(progress, f"{label}, {features}: results reused ({path})")
        return json.loads(path.read_text())
    start = time.perf_counter()
    work = path.with_suffix("")
    if force and (work / "model" / "model.json").is_file():
        (work / "model" / "model.json").unlink()  # retrain
    say(progress, f"{label}, {features}: training on {len(train)} flight(s)")
    trained = trained_model(train, features, out, settings, work / "model", progress=progress)
    system = feature_system(features)
    compile_start = time.perf_counter()
    tuning: dict = {}
    if settings.tune_noise:
        say(progress, f"{label}, {features}: tuning the noise on the training flights")
        estimators, tuning = _tuned(trained, train, work / "tuning", settings, system=system,
                                    progress=progress, parameters=FEATURES[features].choose)
        # the nominal's builds depend on the fold, not the features: every features' study reuses them
        nominal_estimators, tuning["nominal"] = _tuned("nominal", train, out / "nominal" / "tuning" / label,
                                                       settings, progress=progress)
    else:
        say(progress, f"{label}, {features}: compiling")
        estimators = _estimators(trained, work / "compiled", settings, system=system)
    compile_seconds = time.perf_counter() - compile_start
    cases = {}
    for i, case in enumerate(tests):
        say(progress, f"{label}, {features}: testing on {case.name} ({i + 1}/{len(tests)})")
        cases[case.name] = {name: _run_method(estimators[est], case, trained)
                            for name, est, kind in methods(settings.estimators) if kind == "knode"}
        if settings.tune_noise:
            cases[case.name].update({tuned_label(est): _run_method(nominal_estimators[est], case)
                                     for est in settings.estimators})
    results = {"train": label, "train_cases": [c.name for c in train], "features": features, "hash": ident,
               "training": training_record(trained), **({"tuning": tuning} if tuning else {}),
               "compile_seconds": compile_seconds, "wall_seconds": time.perf_counter() - start,
               "cases": cases}
    _write_json(path, results)
    return results


# --- studies --------------------------------------------------------------------------------------


def run_protocol(cases: Sequence[Case], out: str | Path, protocol: str, features: str,
                 settings: StudySettings = StudySettings(), *, train: Sequence[str] = (),
                 force: bool = False, progress: bool = True) -> list[dict]:
    """Every fold of ``protocol`` with ``features``: one :func:`train_and_test` result each."""
    out = Path(out)
    return [train_and_test(fold.train, fold.tests, features, out, settings, label=fold.label, force=force,
                           progress=progress) for fold in folds(cases, protocol, train)]


def run_study(cases: Sequence[Case], out: str | Path, *, train: Sequence[str] = (),
              features: Sequence[str] = tuple(FEATURES), settings: StudySettings = StudySettings(),
              protocol: str = "single", matrix: Sequence[str] = (), force: bool = False,
              progress: bool = True, skipped: dict[str, str] | None = None,
              findings: Sequence = ()) -> list[Summary]:
    """A protocol (:data:`PROTOCOLS`) for each of ``features``, and its paired report.

    With ``single`` every ``train`` flight is its own study; ``train-test`` trains one model
    on the ``train`` flights and tests it on every other; the other protocols pool their
    folds into one study per features. ``matrix`` (``single`` only) names more training flights
    tested with the UKF only; they appear in the headline table, not in the per-flight tables
    or the figure. Writes the per-fold JSON files and ``OUT/quadrotor.{md,json,png}``; returns
    the summaries of the studies followed by those of ``matrix``. ``skipped`` (recording name
    -> reason) and ``findings`` (the recording checks' :class:`~learnest_codegen.recordings.checks.Finding`)
    are listed in both reports.
    """
    from .quadrotor_report import markdown, plot_paired

    out = Path(out)
    folds(cases, protocol, train)  # validates the names before any work
    for f in features:
        feature_system(f)
    if matrix and protocol != "single":
        raise SettingsError(f"run_study: matrix adds training flights to the single protocol, "
                            f"not to {protocol!r}")
    start = time.perf_counter()
    nominal = nominal_results(cases, out, settings, progress)
    summaries = []
    for f in features:
        results = run_protocol(cases, out, protocol, f, settings, train=train, force=force, progress=progress)
        studies = results if protocol == "single" else [pooled(results, protocol)]
        summaries += [summarise(nominal, r, pairs(settings.estimators, settings.tune_noise))
                      for r in studies]
    extra = []
    if "ukf" in settings.estimators:
        ukf_only = replace(settings, estimators=("ukf",))
        for name in (m for m in matrix if m not in train):
            for f in features:
                r = run_protocol(cases, out, "single", f, ukf_only, train=[name], force=force,
                                 progress=progress)
                extra.append(summarise(nominal, r[0], pairs(("ukf",))))
    paper = PAPER_IMPROVEMENT if protocol == "single" else None
    found = [f.to_json() if hasattr(f, "to_json") else dict(f) for f in findings]
    (out / "quadrotor.md").write_text(markdown(summaries, extra, paper, skipped, found))
    _write_json(out / "quadrotor.json", {"settings": settings.to_json(), "protocol": protocol,
                                         "skipped": dict(skipped or {}), "findings": found,
                                         "studies": [s.to_json() for s in (*summaries, *extra)]})
    plot_paired(summaries[:6], out / "quadrotor.png")
    say(progress, f"done in {time.perf_counter() - start:.0f} s: {out / 'quadrotor.md'}")
    return [*summaries, *extra]
