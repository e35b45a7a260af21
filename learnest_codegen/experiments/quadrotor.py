"""The paper's quadrotor experiment (section V-C, Fig. 3) on real flights, and protocols that
measure whether a learned model generalises to flights it was not trained on.

A study trains the KNODE residual on one or more flights (``linear_rts`` observations: the
Kalman filter and RTS smoother of the prior ``A x`` on Vicon position and accelerometer; the
paper's 2 layers of 16 tanh, 150 epochs, early stopping on each flight's final 20 %), compiles
the KNODE estimators, and runs them and their nominal counterparts (compiled C, every
estimator of :data:`~learnest_codegen.compilation.ESTIMATOR_NAMES`) on test flights, each from
that flight's first measurements. Scores are against the reference states: the truth in
simulation; on real flights Vicon position with Savitzky-Golay velocity and acceleration
(:func:`~learnest_codegen.recordings.crazyflie.reference_states`); the onboard EKF alongside.

Protocols (:mod:`.quadrotor_protocols`): ``single`` (the paper's: one training flight, every
other flight tested), ``leave-type-out`` and ``leave-one-out``.

Features (:data:`FEATURES`) pick the system: ``state`` (the residual sees velocity and
acceleration: the paper's), ``thrust`` (also the thrust command and the battery voltage),
``linear`` (a grey-box prior ``A x`` whose acceleration rows are fitted to the training flights,
then the net on velocity and acceleration), ``linear_prior`` (that prior alone, no net),
``thrust_prior`` (a grey-box prior of the true model's form, ``adot = c_T vbat T + c_v v + c_a
a`` (+ ``c_0`` on z), one thrust gain for all axes, fitted alone), ``thrust_prior_axes`` (its
vertical gain fitted apart), ``thrust_prior_z`` (the thrust on the vertical only: horizontally
the thrust vector and the measured acceleration are turned by the same onboard attitude) and
``thrust_linear`` (``thrust_prior`` then the net on velocity and acceleration).
Each per-flight result records the gate's rejections and the share of samples outside the
training range (:mod:`learnest_codegen.learning.ranges`); the report
(:mod:`.quadrotor_report`) is paired per flight. Measured: ``docs/reports/flights.md``.

Layout of OUT::

    OUT/compiled/nominal/                  nominal estimators
    OUT/observations/<flight>.npz          the pre-training observer's states of a flight
    OUT/runs/<fold>/<features>/model/      the trained model (reused while its training is
                                           unchanged); compiled/ its estimators
    OUT/runs/<fold>/<features>.json        per-flight results (reused while the configuration
                                           hash is unchanged)
    OUT/nominal/<flight>.json              the nominal estimators on one flight
    OUT/quadrotor.md, quadrotor.json       the paired report
    OUT/quadrotor.png                      paired per-flight MSE, nominal against KNODE
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Sequence

import numpy as np
from tqdm.auto import tqdm

from ..compilation import ESTIMATOR_NAMES
from ..errors import LearnestError, SettingsError, UnknownNameError
from ..learning.network import NetworkSettings
from ..learning.training import TrainingSettings
from ..systems import System
from ..systems.quadrotor import QUADROTOR, QUADROTOR_LINEAR, QUADROTOR_STATE, QUADROTOR_THRUST_LINEAR
from .quadrotor_cases import GROUPS as GROUPS
from .quadrotor_cases import Case as Case
from .quadrotor_cases import flight_cases as flight_cases
from .quadrotor_cases import initial_state as initial_state
from .quadrotor_cases import scores as scores
from .quadrotor_cases import simulated_cases as simulated_cases
from .quadrotor_protocols import PROTOCOLS as PROTOCOLS
from .quadrotor_protocols import folds, pooled
from .quadrotor_report import ONBOARD, Summary, summarise
from .store import content_hash as _hash
from .store import write_json as _write_json


@dataclass(frozen=True)
class Features:
    """What a study's KNODE model is: the system (its residual's inputs) and the prior
    parameters fitted to the training flights before the net is trained (the grey-box route)."""

    system: System
    fit_prior: tuple[str, ...] = ()
    start_at_prior: bool = False
    net: bool = True


_THRUST_SHARED = tuple(n for n in QUADROTOR_THRUST_LINEAR.params if n != "dc_T_z")  # one thrust gain
_THRUST_Z = tuple(n for n in QUADROTOR_THRUST_LINEAR.params if n != "c_T")  # thrust on z only
FEATURES: dict[str, Features] = {
    "state": Features(QUADROTOR_STATE), "thrust": Features(QUADROTOR),
    "linear": Features(QUADROTOR_LINEAR, tuple(QUADROTOR_LINEAR.params), start_at_prior=True),
    "linear_prior": Features(QUADROTOR_LINEAR, tuple(QUADROTOR_LINEAR.params), net=False),
    "thrust_prior": Features(QUADROTOR_THRUST_LINEAR, _THRUST_SHARED, net=False),
    "thrust_prior_axes": Features(QUADROTOR_THRUST_LINEAR, tuple(QUADROTOR_THRUST_LINEAR.params), net=False),
    "thrust_prior_z": Features(QUADROTOR_THRUST_LINEAR, _THRUST_Z, net=False),
    "thrust_linear": Features(QUADROTOR_THRUST_LINEAR, _THRUST_SHARED, start_at_prior=True),
}
LABELS = {"mhe": "MHE", "ukf": "UKF", "mhe_gn": "MHE-GN", "mhe_rti": "MHE-RTI"}
PAPER_IMPROVEMENT = {"KNODE-UKF": 26.6, "KNODE-MHE": 11.9}  # [%] of the median MSE
DEFAULT_TRAIN = "B2_circle_medium_rep1"
DEFAULT_MATRIX = ("B2_circle_slow_rep1", "B2_circle_fast_rep2", "B3_figure8_slow_rep1",
                  "B3_figure8_fast_rep1")


def methods(estimators: Sequence[str]) -> list[tuple[str, str, str]]:
    """``(label, estimator, kind)`` of the nominal and KNODE variant of each estimator."""
    return [(f"{prefix}{LABELS[e]}", e, kind) for e in estimators
            for prefix, kind in (("", "nominal"), ("KNODE-", "knode"))]


def pairs(estimators: Sequence[str], tuned: bool = False) -> list[tuple[str, str]]:
    """``(KNODE label, nominal label)`` of each estimator; with ``tuned``, also each KNODE
    estimator against its nominal estimator tuned on the same training flights."""
    out = [(f"KNODE-{LABELS[e]}", LABELS[e]) for e in estimators]
    return out + [(f"KNODE-{LABELS[e]}", tuned_label(e)) for e in estimators if tuned]


def tuned_label(estimator: str) -> str:
    """The label of the nominal ``estimator`` with its noise tuned on the training flights."""
    return f"{LABELS[estimator]} (tuned)"


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
            out["tune_noise"] = True
        return out


def feature_system(features: str) -> System:
    """The quadrotor system whose residual sees the named features (see :data:`FEATURES`)."""
    if features not in FEATURES:
        raise UnknownNameError(f"unknown features {features!r}; choose from {list(FEATURES)}")
    return FEATURES[features].system


# --- running estimators ---------------------------------------------------------------------------


def _estimators(model, out: Path, settings: StudySettings, estimators: Sequence[str] | None = None) -> dict:
    """The study's compiled estimators of ``model`` (see :func:`pipeline.resolve`), by name."""
    from ..pipeline import make_estimator

    clamp = settings.clamp_inputs if model != "nominal" else None
    return {name: make_estimator(model, name, system=QUADROTOR, out=out, clamp_inputs=clamp)
            for name in (estimators or settings.estimators)}


def _tuned(model, train: Sequence[Case], out: Path, settings: StudySettings) -> tuple[dict, dict]:
    """Each of the study's estimators of ``model`` (or ``"nominal"``) with its noise tuned on
    the training flights (:func:`.quadrotor_tuning.tune`), and each one's tuning record."""
    from .quadrotor_tuning import tune

    clamp = settings.clamp_inputs if model != "nominal" else None
    estimators, record = {}, {}
    for name in settings.estimators:
        where = out / name if model == "nominal" else out / "knode" / name
        tuning, estimators[name], grid = tune(model, name, train, where, system=QUADROTOR, clamp_inputs=clamp)
        record[name] = {"process_scale": tuning.process_scale,
                        "measurement_scale": tuning.measurement_scale, "train_mse": grid}
    return estimators, record


def _run_method(estimator, case: Case, model=None) -> dict:
    """Scores of one estimator on one case, its gate's rejections and (with the trained
    ``model``) the share of samples whose net inputs leave the training range."""
    from ..evaluation import run_estimator

    try:
        result = run_estimator(estimator, case.run, initial_state(case.run), type(estimator).__name__)
    except LearnestError as exc:  # an Ipopt failure on one case is a result, not the end
        return {"error": f"{type(exc).__name__}: {exc}", "mse": float("nan")}
    out = {**scores(result.x_hat, case.reference), "us_per_step": result.seconds_per_step * 1e6,
           "rejected": result.rejections, "rejected_share": result.rejections / len(case.run)}
    if model is not None:
        from ..learning.ranges import extrapolation

        outside = extrapolation(model, result.x_hat, case.run.u)
        out["outside"] = None if outside is None else outside.share
    return out


def nominal_results(cases: Sequence[Case], out: Path, settings: StudySettings,
                    progress: bool = True) -> dict[str, dict]:
    """The nominal estimators (and the onboard EKF) on every case, cached per case in
    ``OUT/nominal``; an estimator added later runs alone."""
    labels = [(label, est) for label, est, kind in methods(settings.estimators) if kind == "nominal"]
    results, estimators = {}, None
    quiet = None if progress else True  # None: quiet off a terminal
    for case in tqdm(cases, desc="nominal estimators", disable=quiet, unit="case"):
        path = out / "nominal" / f"{case.name}.json"
        ident = _hash({"samples": len(case.run), "y": float(np.sum(case.run.y)),
                       "ref": float(np.sum(case.reference))})
        stored = json.loads(path.read_text()) if path.is_file() else {}
        done = stored.get("methods", {}) if stored.get("hash") == ident else {}
        missing = [(label, est) for label, est in labels if label not in done]
        if missing:
            estimators = estimators or _estimators("nominal", out / "compiled" / "nominal", settings)
            done.update({label: _run_method(estimators[est], case) for label, est in missing})
            if case.onboard is not None:
                done[ONBOARD] = scores(case.onboard, case.reference)
            _write_json(path, {"hash": ident, "methods": done})
        results[case.name] = {k: v for k, v in done.items() if k in dict(labels) or k == ONBOARD}
    return results


def _observations(cases: Sequence[Case], out: Path, settings: StudySettings) -> list[np.ndarray]:
    """The pre-training observer's states of each case, cached in ``OUT/observations``."""
    from ..observers import observe

    zetas = []
    for case in cases:
        path = out / "observations" / f"{case.name}.npz"
        ident = _hash({"observer": settings.observer, "samples": len(case.run),
                       "y": float(np.sum(case.run.y)), "u": float(np.sum(case.run.u))})
        if path.is_file():
            with np.load(path) as stored:
                if str(stored["ident"]) == ident:
                    zetas.append(stored["zeta"])
                    continue
        zeta = observe(case.run, QUADROTOR, settings.observer).zeta
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, zeta=zeta, ident=ident)
        zetas.append(zeta)
    return zetas


def trained_model(train: Sequence[Case], features: str, out: Path, settings: StudySettings,
                  directory: Path, *, progress: bool = True):
    """The KNODE model trained on ``train`` with ``features``: loaded from ``directory`` when a
    model of the same training is there, else trained (on all the flights at once) and saved."""
    from ..learning.model import load_model
    from ..learning.runs import train_on_runs

    system = feature_system(features)
    ident = _hash({"train": [c.name for c in train], "samples": [len(c.run) for c in train],
                   "features": features, "training": settings.training.to_json(),
                   "observer": settings.observer, "fit_prior": list(FEATURES[features].fit_prior),
                   "start_at_prior": FEATURES[features].start_at_prior, "net": FEATURES[features].net,
                   **({} if settings.net_must_beat_prior else {"net_must_beat_prior": False})})
    meta = directory / "model.json"
    if meta.is_file() and json.loads(meta.read_text()).get("study_training") == ident:
        return load_model(directory, system)
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a 2x16 net: threads only contend
    try:
        model = train_on_runs([c.run for c in train], system, settings.training,
                              names=[c.name for c in train],
                              observer=settings.observer, observations=_observations(train, out, settings),
                              fit_prior=FEATURES[features].fit_prior,
                              start_at_prior=FEATURES[features].start_at_prior, net=FEATURES[features].net,
                              net_must_beat_prior=settings.net_must_beat_prior, progress=progress)
    finally:
        torch.set_num_threads(threads)
    model.meta["study_training"] = ident
    model.save(directory)
    return model


def train_and_test(train: Case | Sequence[Case], tests: Sequence[Case], features: str, out: Path,
                   settings: StudySettings = StudySettings(), *, label: str | None = None,
                   force: bool = False, progress: bool = True) -> dict:
    """Train on ``train`` (one case or several) with ``features``, compile, and run the KNODE
    estimators on ``tests``.

    Returns (and writes to ``OUT/runs/<label>/<features>.json``; ``label`` defaults to the
    training case's name) ``{"train", "train_cases", "features", "hash", "training": {...},
    "cases": {case: {label: scores}}}``; a file with the same configuration hash is reused
    unless ``force``.
    """
    train = (train,) if isinstance(train, Case) else tuple(train)
    label = label or (train[0].name if len(train) == 1 else "+".join(c.name for c in train))
    path = out / "runs" / label / f"{features}.json"
    ident = _hash({"train": [c.name for c in train], "samples": [len(c.run) for c in train],
                   "features": features, "tests": [c.name for c in tests], "settings": settings.to_json(),
                   "references": [float(np.sum(c.reference)) for c in tests]})
    if not force and path.is_file() and json.loads(path.read_text()).get("hash") == ident:
        return json.loads(path.read_text())
    start = time.perf_counter()
    work = path.with_suffix("")
    if force and (work / "model" / "model.json").is_file():
        (work / "model" / "model.json").unlink()  # retrain
    trained = trained_model(train, features, out, settings, work / "model", progress=progress)
    compile_start = time.perf_counter()
    tuning: dict = {}
    if settings.tune_noise:
        estimators, tuning = _tuned(trained, train, work / "tuning", settings)
        # the nominal's builds depend on the fold, not the features: every features' study reuses them
        nominal_estimators, tuning["nominal"] = _tuned("nominal", train, out / "nominal" / "tuning" / label,
                                                       settings)
    else:
        estimators = _estimators(trained, work / "compiled", settings)
    compile_seconds = time.perf_counter() - compile_start
    cases = {}
    quiet = None if progress else True  # None: quiet off a terminal
    for case in tqdm(tests, desc=f"KNODE ({label}, {features})", disable=quiet, unit="case"):
        cases[case.name] = {name: _run_method(estimators[est], case, trained)
                            for name, est, kind in methods(settings.estimators) if kind == "knode"}
        if settings.tune_noise:
            cases[case.name].update({tuned_label(est): _run_method(nominal_estimators[est], case)
                                     for est in settings.estimators})
    results = {"train": label, "train_cases": [c.name for c in train], "features": features, "hash": ident,
               "training": {k: trained.meta.get(k) for k in ("train_seconds", "best_epoch", "final_loss",
                                                              "prior_loss", "observer", "prior_params",
                                                              "net_kept")},
               **({"tuning": tuning} if tuning else {}),
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
              progress: bool = True, skipped: dict[str, str] | None = None) -> list[Summary]:
    """A protocol (:data:`PROTOCOLS`) for each of ``features``, and its paired report.

    With ``single`` every ``train`` flight is its own study; the other protocols pool their
    folds into one study per features. ``matrix`` (``single`` only) names more training flights
    tested with the UKF only; they appear in the headline table, not in the per-flight tables
    or the figure. Writes the per-fold JSON files and ``OUT/quadrotor.{md,json,png}``; returns
    the summaries of the studies followed by those of ``matrix``. ``skipped`` (recording name
    -> reason) is listed in both reports.
    """
    from .quadrotor_report import markdown, plot_paired

    out = Path(out)
    folds(cases, protocol, train)  # validates the names before any work
    for f in features:
        feature_system(f)
    if matrix and protocol != "single":
        raise SettingsError(f"run_study: matrix adds training flights to the single protocol, "
                            f"not to {protocol!r}")
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
    (out / "quadrotor.md").write_text(markdown(summaries, extra, paper, skipped))
    _write_json(out / "quadrotor.json", {"settings": settings.to_json(), "protocol": protocol,
                                         "skipped": dict(skipped or {}),
                                         "studies": [s.to_json() for s in (*summaries, *extra)]})
    plot_paired(summaries[:6], out / "quadrotor.png")
    return [*summaries, *extra]
