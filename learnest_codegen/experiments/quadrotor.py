"""The paper's quadrotor experiment (section V-C, Fig. 3): train on one flight, test on the others.

For a training case (a real NanoBench flight, or a simulated quadrotor run) and a choice of the
residual's *features*, one study

1. turns the training run into state observations with the pre-training observer (``linear_rts``:
   the Kalman filter and RTS smoother of the prior ``A x`` on Vicon position and accelerometer)
   and trains the KNODE residual (2 layers, 16 hidden, tanh, 150 epochs: the paper's settings;
   early stopping on the final 20 % of the flight, see below);
2. compiles KNODE-MHE and KNODE-UKF (the nominal MHE and UKF are compiled once per output
   folder);
3. runs MHE, KNODE-MHE, UKF and KNODE-UKF (compiled C) on every other case, each starting
   from that case's first measurements, and scores them against the reference states: the truth
   in simulation, and on real flights Vicon position with Savitzky-Golay velocity and
   acceleration (:func:`~learnest_codegen.recordings.crazyflie.reference_states`). The
   Crazyflie's onboard EKF is scored alongside on position and velocity (its logged
   acceleration is not a world-frame acceleration in m/s^2: it regresses on the reference with
   slope 0.13).

Features pick the system (:data:`FEATURES`): ``"thrust"`` is
:data:`~learnest_codegen.systems.quadrotor.QUADROTOR`, whose residual sees velocity,
acceleration, the world-frame thrust command and the battery voltage; ``"state"`` is
``QUADROTOR_STATE``, whose residual sees velocity and acceleration only (the paper's setting).
Neither sees the position. A model directory names its system, so it loads with either.

Early stopping matters more than anything else here. Trained to the end (``validation_fraction
= 0``), the net fits the observer's error dynamics on the training flight (its one-step loss
falls 3-4x) and the KNODE-UKF is 30-260 % *worse* than the UKF on the other flights. The held-out
final 20 % of a flight is its landing, a regime the net has not seen; stopping when the loss
there is least (after 2-15 epochs) keeps the part that carries over to other flights. Holding out
a cruise segment instead (the landing cut off) stops later and is worse.

Training-flight matrix (``matrix``): more training flights, each tested on all other flights
with the UKF only (microseconds per step; the MHE takes milliseconds), for both features.

Layout of OUT::

    OUT/compiled/nominal/                   nominal MHE and UKF
    OUT/runs/<train>/<features>/model/      the trained model; compiled/ its estimators
    OUT/runs/<train>/<features>.json        per-case results (resumable: skipped when its
                                            configuration hash is unchanged)
    OUT/nominal/<case>.json                 the nominal estimators on one case (shared)
    OUT/quadrotor.md, quadrotor.json        tables: per-case MSE, medians, improvements
    OUT/quadrotor.png                       box plots like the paper's Fig. 3
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
from tqdm.auto import tqdm

from ..data import Run
from ..errors import DataError, LearnestError, UnknownNameError
from ..learning.network import NetworkSettings
from ..learning.training import TrainingSettings
from ..systems import System
from ..systems.quadrotor import QUADROTOR, QUADROTOR_STATE
from .store import content_hash as _hash
from .store import write_json as _write_json

FEATURES: dict[str, System] = {"state": QUADROTOR_STATE, "thrust": QUADROTOR}
METHODS = (("MHE", "mhe", "nominal"), ("KNODE-MHE", "mhe", "knode"),
           ("UKF", "ukf", "nominal"), ("KNODE-UKF", "ukf", "knode"))
PAIRS = (("KNODE-UKF", "UKF"), ("KNODE-MHE", "MHE"))
PAPER_IMPROVEMENT = {"KNODE-UKF": 26.6, "KNODE-MHE": 11.9}  # [%] of the median MSE
ONBOARD = "onboard EKF"
GROUPS = {"p": slice(0, 3), "v": slice(3, 6), "a": slice(6, 9)}
DEFAULT_TRAIN = "B2_circle_medium_rep1"
DEFAULT_MATRIX = ("B2_circle_slow_rep1", "B2_circle_fast_rep2", "B3_figure8_slow_rep1",
                  "B3_figure8_fast_rep1")


@dataclass(frozen=True)
class Case:
    """One run to train or test on.

    Attributes
    ----------
    name : e.g. the flight's name or ``"sim_seed3"``.
    run : the quadrotor run (``y = [p, a]``, ``u = [T, vbat]``).
    reference : (T, 9) states to score against (truth in simulation, Savitzky-Golay on flights).
    onboard : (T, 9) the onboard EKF's states, or ``None``.
    """

    name: str
    run: Run
    reference: np.ndarray
    onboard: np.ndarray | None = None


@dataclass(frozen=True)
class StudySettings:
    """How the KNODE model is trained and which estimators run; the paper's defaults."""

    training: TrainingSettings = field(default_factory=lambda: TrainingSettings(
        epochs=150, network=NetworkSettings(layers=2, hidden=16, activation="Tanh")))
    observer: str = "linear_rts"
    estimators: tuple[str, ...] = ("mhe", "ukf")

    def __post_init__(self) -> None:
        unknown = [e for e in self.estimators if e not in ("mhe", "ukf")]
        if unknown or not self.estimators:
            raise UnknownNameError(f"unknown estimator(s) {unknown or self.estimators}; choose from mhe, ukf")

    def to_json(self) -> dict:
        return {"training": self.training.to_json(), "observer": self.observer,
                "estimators": list(self.estimators)}


# --- cases ----------------------------------------------------------------------------------------


def flight_cases(root: str | Path, *, skipped: dict[str, str] | None = None,
                 **read_options) -> list[Case]:
    """Every NanoBench flight under ``root`` as a :class:`Case` (see ``read_flight``).

    A flight that cannot be used (one that never leaves the ground, a gap, another sampling
    rate) raises :class:`DataError`; with a ``skipped`` dict it is left out instead and its
    reason recorded there under the file's name, so one bad recording does not stop a study.
    """
    from ..recordings.crazyflie import list_flights, read_flight

    paths = list_flights(root)
    if not paths:
        raise FileNotFoundError(f"no flight CSVs under {root}")
    cases = []
    for path in paths:
        try:
            f = read_flight(path, **read_options)
            if abs(f.timing.dt - QUADROTOR.dt) > 1e-3 * QUADROTOR.dt:
                raise DataError(f"flight {f.name}: sampled every {f.timing.dt} s, but the quadrotor "
                                f"estimators step {QUADROTOR.dt} s")
        except DataError as exc:
            if skipped is None:
                raise
            skipped[Path(path).stem] = str(exc)
            continue
        cases.append(Case(f.name, f.run, f.reference, f.onboard))
    if not cases:
        raise DataError(f"no usable flight under {root}: " + "; ".join(f"{k}: {v}" for k, v in
                                                                     (skipped or {}).items()))
    return cases


def simulated_cases(seeds: Iterable[int], duration: float | None = None) -> list[Case]:
    """Simulated quadrotor runs (seeded reference shape, speed and battery) with their truth."""
    from ..simulation import simulate

    cases = []
    for seed in seeds:
        run = simulate(QUADROTOR, seed, duration=duration)
        cases.append(Case(f"sim_seed{seed}", run, run.x))
    return cases


def feature_system(features: str) -> System:
    """The quadrotor system whose residual sees the named features (see :data:`FEATURES`)."""
    if features not in FEATURES:
        raise UnknownNameError(f"unknown features {features!r}; choose from {list(FEATURES)}")
    return FEATURES[features]


def initial_state(run: Run, fit_samples: int = 11) -> np.ndarray:
    """(9,) start state from the first measurements: position and acceleration as measured,
    velocity the slope of a line fitted to the first ``fit_samples`` positions."""
    n = min(fit_samples, len(run))
    velocity = np.polyfit(run.t[:n] - run.t[0], run.y[:n, :3], 1)[0]
    return np.concatenate([run.y[0, :3], velocity, run.y[0, 3:6]])


def scores(x_hat: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """MSE overall (the paper's metric: mean over samples and the 9 states) and per group."""
    out = {"mse": float(np.mean((x_hat - reference) ** 2))}
    out.update({f"mse_{g}": float(np.mean((x_hat[:, s] - reference[:, s]) ** 2)) for g, s in GROUPS.items()})
    return out


# --- running estimators ---------------------------------------------------------------------------


def _estimators(model, out: Path, settings: StudySettings) -> dict:
    """The study's compiled estimators of ``model`` (see :func:`pipeline.resolve`), by name."""
    from ..pipeline import make_estimator

    return {name: make_estimator(model, name, system=QUADROTOR, out=out) for name in settings.estimators}


def _run_method(estimator, case: Case) -> dict:
    from ..evaluation import run_estimator

    try:
        result = run_estimator(estimator, case.run, initial_state(case.run), type(estimator).__name__)
    except LearnestError as exc:  # an Ipopt failure on one case is a result, not the end
        return {"error": f"{type(exc).__name__}: {exc}", "mse": float("nan")}
    return {**scores(result.x_hat, case.reference), "us_per_step": result.seconds_per_step * 1e6}


def nominal_results(cases: Sequence[Case], out: Path, settings: StudySettings,
                    progress: bool = True) -> dict[str, dict]:
    """The nominal MHE and UKF (and the onboard EKF) on every case, cached in ``OUT/nominal``."""
    estimators = _estimators("nominal", out / "compiled" / "nominal", settings)
    results = {}
    for case in tqdm(cases, desc="nominal estimators", disable=not progress, unit="case"):
        path = out / "nominal" / f"{case.name}.json"
        ident = _hash({"estimators": settings.estimators, "samples": len(case.run),
                       "y": float(np.sum(case.run.y)), "ref": float(np.sum(case.reference))})
        if path.is_file() and json.loads(path.read_text()).get("hash") == ident:
            results[case.name] = json.loads(path.read_text())["methods"]
            continue
        methods = {label: _run_method(estimators[est], case)
                   for label, est, kind in METHODS if kind == "nominal" and est in settings.estimators}
        if case.onboard is not None:
            methods[ONBOARD] = scores(case.onboard, case.reference)
        _write_json(path, {"hash": ident, "methods": methods})
        results[case.name] = methods
    return results


def train_and_test(train: Case, tests: Sequence[Case], features: str, out: Path,
                   settings: StudySettings = StudySettings(), *, force: bool = False,
                   progress: bool = True) -> dict:
    """Train on ``train`` with ``features``, compile, and run KNODE-MHE/UKF on ``tests``.

    Returns (and writes to ``OUT/runs/<train>/<features>.json``) ``{"train", "features",
    "hash", "training": {...}, "cases": {case: {label: scores}}}``; a file with the same
    configuration hash is reused unless ``force``.
    """
    from ..learning.training import train_on_run

    system = feature_system(features)
    path = out / "runs" / train.name / f"{features}.json"
    ident = _hash({"train": train.name, "samples": len(train.run), "features": features,
                   "tests": [c.name for c in tests], "settings": settings.to_json(),
                   "references": [float(np.sum(c.reference)) for c in tests]})
    if not force and path.is_file() and json.loads(path.read_text()).get("hash") == ident:
        return json.loads(path.read_text())
    start = time.perf_counter()
    work = path.with_suffix("")
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # a 2x16 net: threads only contend (150 epochs: 5 s, not 200 s)
    try:
        trained = train_on_run(train.run, system, settings.training, observer=settings.observer,
                               progress=progress)
    finally:
        torch.set_num_threads(threads)
    trained.save(work / "model")
    compile_start = time.perf_counter()
    estimators = _estimators(trained, work / "compiled", settings)
    compile_seconds = time.perf_counter() - compile_start
    cases = {}
    bar = tqdm(tests, desc=f"KNODE ({train.name}, {features})", disable=not progress, unit="case")
    for case in bar:
        cases[case.name] = {label: _run_method(estimators[est], case)
                            for label, est, kind in METHODS if kind == "knode" and est in settings.estimators}
    results = {"train": train.name, "features": features, "hash": ident,
               "training": {k: trained.meta[k] for k in ("train_seconds", "best_epoch", "final_loss",
                                                          "prior_loss", "observer")},
               "compile_seconds": compile_seconds, "wall_seconds": time.perf_counter() - start,
               "cases": cases}
    _write_json(path, results)
    return results


# --- summaries ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Summary:
    """One (train, features) study: per-case MSE of every method, medians and improvements."""

    train: str
    features: str
    per_case: dict[str, dict[str, dict]]  # case -> method label -> scores
    medians: dict[str, float]  # method -> median overall MSE over the test cases
    velocity_medians: dict[str, float]  # method -> median velocity MSE (onboard EKF included)
    improvement: dict[str, float]  # KNODE label -> (median nominal - median KNODE) / nominal [%]
    wins: dict[str, int]  # KNODE label -> test cases on which it beats its nominal counterpart

    def to_json(self) -> dict:
        return asdict(self)


def summarise(nominal: dict[str, dict], knode: dict) -> Summary:
    """Combine the nominal results and one KNODE study into a :class:`Summary`."""
    per_case = {name: {**nominal[name], **methods} for name, methods in knode["cases"].items()}
    labels = [m for m in (*(label for label, _, _ in METHODS), ONBOARD)
              if all(m in v for v in per_case.values())]

    def median(key: str, label: str) -> float:
        return float(np.nanmedian([v[label].get(key, np.nan) for v in per_case.values()]))

    medians = {m: median("mse", m) for m in labels if m != ONBOARD}
    velocity = {m: median("mse_v", m) for m in labels}
    improvement = {k: 100.0 * (medians[n] - medians[k]) / medians[n] for k, n in PAIRS
                   if k in medians and n in medians}
    wins = {k: int(sum(v[k]["mse"] < v[n]["mse"] for v in per_case.values())) for k, n in PAIRS
            if k in medians and n in medians}
    return Summary(knode["train"], knode["features"], per_case, medians, velocity, improvement, wins)


def markdown(summaries: Sequence[Summary], matrix: Sequence[Summary] = ()) -> str:
    """Per-case table of every study, then a median/improvement table of all of them and of the
    training-flight ``matrix`` studies (UKF only: "-" in the MHE columns)."""
    lines = []
    for s in summaries:
        labels = [*s.medians, *([ONBOARD] if ONBOARD in s.velocity_medians else [])]
        lines += [f"### trained on {s.train}, features {s.features!r} (MSE overall; velocity MSE)", "",
                  "| test case | " + " | ".join(labels) + " |", "|---" * (len(labels) + 1) + "|"]
        for name, methods in s.per_case.items():
            cells = [f"{methods[m].get('mse', float('nan')):.4g}; {methods[m].get('mse_v', float('nan')):.3g}"
                     if m != ONBOARD else f"-; {methods[m]['mse_v']:.3g}" for m in labels]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        cells = [f"**{s.medians[m]:.4g}**; {s.velocity_medians[m]:.3g}" if m != ONBOARD
                 else f"-; {s.velocity_medians[m]:.3g}" for m in labels]
        lines += ["| **median** | " + " | ".join(cells) + " |", ""]
    lines += ["### medians and improvements (paper: KNODE-UKF 26.6 %, KNODE-MHE 11.9 %)", "",
              "| train | features | " + " | ".join(label for label, _, _ in METHODS)
              + " | KNODE-UKF vs UKF | KNODE-MHE vs MHE |", "|---" * 8 + "|"]
    for s in (*summaries, *matrix):
        meds = [f"{s.medians[m]:.4g}" if m in s.medians else "-" for m, _, _ in METHODS]
        imps = [f"{s.improvement[k]:+.1f} % ({s.wins[k]}/{len(s.per_case)})" if k in s.improvement else "-"
                for k, _ in PAIRS]
        lines.append(f"| {s.train} | {s.features} | " + " | ".join(meds + imps) + " |")
    return "\n".join(lines) + "\n"


def plot_boxes(summaries: Sequence[Summary], path: Path) -> Path:
    """Fig. 3 of the paper: box plots of the per-case overall MSE, one panel per study."""
    from ..plotting import _save, plt

    fig, axes = plt.subplots(1, len(summaries), figsize=(4.5 * len(summaries), 4), squeeze=False)
    for ax, s in zip(axes[0], summaries):
        labels = list(s.medians)
        data = [[v[m]["mse"] for v in s.per_case.values() if np.isfinite(v[m]["mse"])] for m in labels]
        ax.boxplot(data, medianprops={"color": "tab:orange"})
        ax.set_xticks(range(1, len(labels) + 1), labels, rotation=20)
        ax.set_yscale("log")
        ax.set_ylabel("MSE over the 9 translational states")
        ax.set_title(f"train {s.train}\nfeatures {s.features}", fontsize=9)
    return _save(fig, path)


def run_study(cases: Sequence[Case], out: str | Path, *, train: Sequence[str],
              features: Sequence[str] = tuple(FEATURES), settings: StudySettings = StudySettings(),
              matrix: Sequence[str] = (), force: bool = False,
              progress: bool = True, skipped: dict[str, str] | None = None) -> list[Summary]:
    """Each training case in ``train`` x each of ``features``, tested on all other cases.

    ``matrix`` names more training cases that are tested with the UKF only (the training-flight
    matrix); they appear in the medians table, not in the per-case tables or the box plot.
    Writes the per-study JSON files, ``OUT/quadrotor.{md,json,png}``; returns the summaries of
    ``train`` followed by those of ``matrix``. ``skipped`` (recording name -> reason) is listed
    in both reports.
    """
    out = Path(out)
    names = [c.name for c in cases]
    unknown = [t for t in (*train, *matrix) if t not in names]
    if unknown:
        raise UnknownNameError(f"unknown training case(s) {unknown}; choose from {names}")
    for f in features:
        feature_system(f)  # validates the name before any work
    nominal = nominal_results(cases, out, settings, progress)
    ukf_only = replace(settings, estimators=("ukf",))
    studies = [(name, settings) for name in train]
    studies += [(name, ukf_only) for name in matrix if name not in train and "ukf" in settings.estimators]
    summaries = []
    for name, chosen in studies:
        train_case = next(c for c in cases if c.name == name)
        tests = [c for c in cases if c.name != name]
        for f in features:
            knode = train_and_test(train_case, tests, f, out, chosen, force=force, progress=progress)
            summaries.append(summarise(nominal, knode))
    main = summaries[:len(train) * len(features)]
    report = markdown(main, matrix=summaries[len(main):])
    if skipped:
        report += "\n### recordings left out\n\n" + "".join(f"- {k}: {v}\n" for k, v in skipped.items())
    (out / "quadrotor.md").write_text(report)
    _write_json(out / "quadrotor.json", {"settings": settings.to_json(), "skipped": dict(skipped or {}),
                                         "studies": [s.to_json() for s in summaries]})
    plot_boxes(main[:8], out / "quadrotor.png")
    return summaries
