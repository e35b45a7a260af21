"""The study's estimator noise chosen on the training flights (``--tune-noise``), by predicting
held-out raw measurements.

A model that predicts better can be trusted more, but how much is a number the system's hand
tuning cannot know. It is chosen on the training flights, the same way for the KNODE and the
nominal estimators, by a criterion that compares measurements with predictions, never a
measured quantity with a smoothed copy of itself (which rewards an estimator for smoothing as
much as the copy does):

* **Prediction of raw measurements.** Run the estimator over a training flight; from each
  filtered estimate ``x_k``, predict the outputs ``h`` samples ahead with the estimator's own
  model and the logged inputs, open loop, and compare with the measurements at ``k + h``,
  which the estimate has not seen. The criterion is the mean over the horizons
  (:data:`HORIZONS_S`: one sample, 0.1 s and 0.5 s) of the log of the mean squared prediction
  error of the chosen outputs (the quadrotor's: the motion-capture position, whose noise is
  white at 0.04-0.1 mm; its accelerometer's error is coloured, an interpolated and filtered
  stream with a slowly varying offset, so predicting its next sample would reward copying
  it). A velocity that lags or is noisy predicts the position badly; one that is right
  predicts it well.
* **What is searched.** An estimate depends on the ratios of the noise stds only, so the
  process stds stay as built and each group of outputs (by unit: the quadrotor's position and
  accelerometer) gets a measurement scale on a grid of powers of two. A coarse grid (factors
  of 4) is refined by factors of 2 around its best point; a best point on the grid's edge
  widens the grid that way (up to :data:`EXPONENT_LIMIT`) and, if still on the edge, is
  reported (``edge`` in the record, a warning).
* **The gate.** The innovation gate reads the scales too (a larger measurement std widens
  it). Every point of the grid is scored with the narrowest gate that rejects at most
  :data:`MAX_REJECTED` of the training flights' outputs: when it rejects more, every std is
  doubled (the estimate stays, the gate widens) until it does not, so no point wins by
  discarding measurements. The record keeps the share rejected and the doublings.

Measured: ``docs/reports/flights_study.md``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import SolverError
from .quadrotor_cases import Case, initial_state

#: Prediction horizons [s] of the criterion (one sample, then these), rounded to samples.
HORIZONS_S = (0.0, 0.1, 0.5)
#: The coarse grid of each measurement group's scale: 4 ** k for these k, then 2 ** k around
#: the best point; the grid widens past its edge up to 2 ** +-EXPONENT_LIMIT.
COARSE_EXPONENTS = tuple(range(-8, 3, 2))
EXPONENT_LIMIT = 16
#: Spacing of the estimates the predictions start from [s] (every sample would cost five
#: times as much for the same criterion: neighbouring starts share their errors).
STRIDE_S = 0.05
#: The largest share of training outputs a tuning's gate may reject, and how many times every
#: std may be doubled to keep it there (the estimate stays, the gate widens).
MAX_REJECTED, MAX_WIDENINGS = 0.01, 10
#: Changes with the criterion or the search (a stored tuning of another version is redone).
TUNING_VERSION = 3


@dataclass(frozen=True)
class Tuning:
    """The system's noise stds scaled: every process std by ``process_scale``, each output
    group's measurement stds by its entry of ``measurement_scales`` (``groups``: the output
    names of each group; one group of every output when empty, scaled by
    ``measurement_scale``)."""

    process_scale: float = 1.0
    measurement_scale: float = 1.0
    measurement_scales: tuple[float, ...] = ()
    groups: tuple[tuple[str, ...], ...] = field(default=(), compare=True)

    @property
    def label(self) -> str:
        scales = "_".join(f"{s:g}" for s in self.measurement_scales) or f"{self.measurement_scale:g}"
        return f"q{self.process_scale:g}_r{scales}"

    def measurement_factors(self, output_names: Sequence[str]) -> np.ndarray:
        """(ny,) factor on each output's std."""
        factors = np.full(len(output_names), float(self.measurement_scale))
        for names, scale in zip(self.groups, self.measurement_scales):
            for n in names:
                factors[list(output_names).index(n)] = self.measurement_scale * scale
        return factors

    def settings(self, name: str, model) -> Any:
        """Estimator ``name``'s settings for the discrete ``model`` with these stds, through the
        estimators' own defaults (an MHE's arrival cost is recomputed for them)."""
        from ..compilation import estimator_kind

        noise = model.system.noise
        factors = self.measurement_factors(model.system.output_names)
        return estimator_kind(name).default_settings(
            model, process_std=tuple(self.process_scale * s for s in noise.process_std),
            measurement_std=tuple(float(f * s) for f, s in zip(factors, noise.measurement_std)))

    def to_json(self) -> dict:
        return {"process_scale": self.process_scale, "measurement_scale": self.measurement_scale,
                "measurement_scales": list(self.measurement_scales),
                "groups": [list(g) for g in self.groups], "label": self.label}


def output_groups(system) -> tuple[tuple[str, ...], ...]:
    """The system's outputs grouped by unit, in order of first appearance."""
    groups: dict[str, list[str]] = {}
    for signal in system.outputs:
        groups.setdefault(signal.unit, []).append(signal.name)
    return tuple(tuple(g) for g in groups.values())


def start_state(case: Case, nx: int) -> np.ndarray:
    """The quadrotor start state from the first measurements, padded with zeros to ``nx``
    (the accelerometer offsets of ``quadrotor_*_bias`` start at 0)."""
    x0 = initial_state(case.run)
    return np.concatenate([x0, np.zeros(nx - x0.size)])


def prediction_errors(model, x_hat: np.ndarray, run, outputs: Sequence[int],
                      horizons: Sequence[int], stride: int = 1) -> dict[int, float]:
    """Horizon -> mean squared error of the outputs ``outputs`` (indices) predicted ``h``
    samples ahead of the filtered estimates ``x_hat[k]`` (every ``stride``-th ``k``) with
    ``model`` (a :class:`~learnest_codegen.export.DiscreteModel`) and the logged inputs, against
    the measurements at ``k + h`` (missing ones left out)."""
    T = len(x_hat)
    top = max(horizons)
    starts = np.arange(0, T - 1, stride)
    F, H = model.F.map(len(starts)), model.h.map(len(starts))
    x = np.asarray(x_hat[starts], float).T
    out = {}
    for step in range(1, top + 1):
        u = run.u[np.minimum(starts + step - 1, T - 1)].T  # u[k] drives x[k] to x[k + 1]
        x = np.asarray(F(x, u))
        if step in horizons:
            valid = starts + step < T
            y_pred = np.asarray(H(x, u)).T[valid][:, outputs]
            y_meas = run.y[starts[valid] + step][:, outputs]
            out[step] = float(np.nanmean((y_pred - y_meas) ** 2))
    return out


def _horizons(dt: float) -> tuple[int, ...]:
    return tuple(sorted({max(1, int(round(h / dt))) for h in HORIZONS_S}))


class _Criterion:
    """The criterion of every noise scale for one model and estimator on the training cases,
    memoised by the scales' exponents; the estimator is compiled once (its noise is a
    run-time setting)."""

    def __init__(self, model, name: str, cases: Sequence[Case], out: Path, *, system, clamp_inputs,
                 outputs: Sequence[str] | None):
        from ..compilation import estimator_kind
        from ..pipeline import make_estimator, resolve

        self.model, self.name, self.cases = model, name, cases
        self.discrete = resolve(model, system, clamp_inputs=clamp_inputs).model
        sysm = self.discrete.system
        self.groups = output_groups(sysm)
        self.outputs = list(outputs or sysm.output_names)
        self.predicted = [sysm.output_names.index(n) for n in self.outputs]
        self.horizons = _horizons(sysm.dt)
        self.stride = max(1, int(round(STRIDE_S / sysm.dt)))
        self.base = make_estimator(model, name, system=system, out=out, clamp_inputs=clamp_inputs)
        self.kind = estimator_kind(name)
        self.scores: dict[tuple[int, ...], float] = {}
        self.detail: dict[tuple[int, ...], dict] = {}

    def tuning(self, point: tuple[int, ...], level: int = 0) -> Tuning:
        return Tuning(2.0 ** level, 2.0 ** level, tuple(2.0 ** e for e in point), self.groups)

    def estimator(self, tuning: Tuning):
        return self.kind.compiled(self.base.directory, settings=tuning.settings(self.name, self.discrete))

    def measure(self, point: tuple[int, ...], level: int = 0) -> dict:
        """The criterion at ``point`` with every std times ``2 ** level`` (the gate's width)."""
        from ..evaluation import run_estimator

        estimator = self.estimator(self.tuning(point, level))
        nx, dt = self.discrete.system.nx, self.discrete.system.dt
        errors, rejected, samples = [], 0, 0
        for case in self.cases:
            try:
                result = run_estimator(estimator, case.run, start_state(case, nx), self.name)
            except SolverError:
                return {"criterion": math.inf, "prediction_mse": {}, "rejected_share": 1.0}
            errors.append(prediction_errors(self.discrete, result.x_hat, case.run, self.predicted,
                                            self.horizons, stride=self.stride))
            rejected += result.rejections
            samples += int(np.sum(~np.isnan(case.run.y)))
        mean = {h: float(np.mean([e[h] for e in errors])) for h in self.horizons}
        finite = all(np.isfinite(v) and v > 0 for v in mean.values())
        return {"criterion": float(np.mean(np.log(list(mean.values())))) if finite else math.inf,
                "prediction_mse": {f"{h * dt:g}s": v for h, v in mean.items()},
                "rejected_share": rejected / max(samples, 1)}

    def sane(self, point: tuple[int, ...]) -> dict:
        """:meth:`measure` at the narrowest gate (every std doubled ``level`` times) that rejects
        at most :data:`MAX_REJECTED` of the outputs: every point is scored as it would be used."""
        for level in range(MAX_WIDENINGS + 1):
            info = {**self.measure(point, level), "level": level}
            if info["rejected_share"] <= MAX_REJECTED:
                break
        return info

    def __call__(self, point: tuple[int, ...]) -> float:
        if point not in self.scores:
            self.detail[point] = self.sane(point)
            self.scores[point] = self.detail[point]["criterion"]
        return self.scores[point]


def tune(model, name: str, cases: Sequence[Case], out: Path, *, system,
         clamp_inputs: bool | None = None, outputs: Sequence[str] | None = None,
         progress=None, parameters: Sequence[tuple[str, Sequence[float]]] = ()) -> tuple[Tuning, Any, dict]:
    """The :class:`Tuning` whose estimator ``name`` of ``model`` predicts the measurements
    ``outputs`` (names; default every output) of ``cases`` (the training flights) best (see the
    module docstring), that estimator, and the search's record: every point's criterion,
    the chosen point's prediction errors, the gate's rejection share, and ``edge`` (output
    groups whose scale sits on the widest grid's edge, and parameters on their grid's end).
    ``progress(text)`` gets one line per grid pass.

    ``parameters`` (``(name, values)``; ``model`` a prior, a
    :class:`~learnest_codegen.export.DiscreteModel`) are prior parameters chosen by the same
    criterion: the scales are searched at the model's own value, each value is scored at those
    scales, and the scales are refined at the best value (``record["parameters"]``; the
    estimator returned is that model's)."""
    criterion = _Criterion(model, name, cases, out, system=system, clamp_inputs=clamp_inputs, outputs=outputs)
    groups = criterion.groups
    best = _search(criterion, len(groups), progress)
    edge = [list(groups[i]) for i, e in enumerate(best) if abs(e) >= EXPONENT_LIMIT]
    chosen_params, parameter_criteria = {}, {}
    for pname, values in parameters:
        from ..export import prior_model
        from ..learning.prior_fit import fitted_system

        candidates = {}
        for value in values:
            variant = prior_model(fitted_system(criterion.discrete.system, {pname: float(value)}))
            candidates[float(value)] = _Criterion(variant, name, cases, out / f"{pname}_{value:g}",
                                                  system=system, clamp_inputs=None, outputs=outputs)
            parameter_criteria[f"{value:g}"] = candidates[float(value)](best)
        value = min(candidates, key=lambda v: candidates[v](best))
        criterion, chosen_params[pname] = candidates[value], value
        best = _refine(criterion, best)
        if value in (min(values), max(values)):
            edge.append([pname])
        if progress:
            progress(f"{pname} {value:g} (criterion {criterion(best):.3f}), scales 2**{list(best)}")
    if edge:
        warnings.warn(f"tuning {name}: {edge} sit on their grid's edge (widest grid); the noise model "
                      f"of those outputs, or those parameters, may be far off", stacklevel=2)
    criterion(best)
    info = criterion.detail[best]
    level = info["level"]
    chosen = criterion.tuning(best, level)
    sysm = criterion.discrete.system
    record = {**chosen.to_json(), "criterion": info["criterion"],
              "prediction_mse": info["prediction_mse"], "rejected_share": info["rejected_share"],
              "gate_widened": level, "edge": edge, "predicted_outputs": criterion.outputs,
              "horizons_s": [h * sysm.dt for h in criterion.horizons],
              "grid": {"_".join(str(e) for e in p): v for p, v in criterion.scores.items()},
              **({"parameters": chosen_params, "parameter_criteria": parameter_criteria}
                 if parameters else {})}
    return chosen, criterion.estimator(chosen), record


def reuse(model, name: str, out: Path, record: dict, *, system, clamp_inputs: bool | None = None):
    """The :class:`Tuning` of a stored ``record`` (:func:`tune`'s) and its estimator (of the
    model with the record's chosen ``parameters``)."""
    from ..compilation import estimator_kind
    from ..pipeline import make_estimator, resolve

    tuning = Tuning(record["process_scale"], record["measurement_scale"], tuple(record["measurement_scales"]),
                    tuple(tuple(g) for g in record["groups"]))
    where = out
    if record.get("parameters"):
        from ..export import prior_model
        from ..learning.prior_fit import fitted_system

        model = prior_model(fitted_system(resolve(model, system).model.system, record["parameters"]))
        (pname, value), = record["parameters"].items()
        where, clamp_inputs = out / f"{pname}_{value:g}", None
    discrete = resolve(model, system, clamp_inputs=clamp_inputs).model
    base = make_estimator(model, name, system=system, out=where, clamp_inputs=clamp_inputs)
    return tuning, estimator_kind(name).compiled(base.directory, settings=tuning.settings(name, discrete))


def _search(evaluate, n: int, progress=None) -> tuple[int, ...]:
    """The exponents (one per group) of the best point: a coarse grid of even exponents,
    widened past its edge while the best point sits on it, then the factor-2 neighbours."""
    import itertools

    axes = [[e for e in COARSE_EXPONENTS if abs(e) <= EXPONENT_LIMIT] for _ in range(n)]
    while True:
        for point in itertools.product(*axes):
            evaluate(point)
        best = min(((p, evaluate(p)) for p in itertools.product(*axes)), key=lambda kv: kv[1])[0]
        widened = False
        for i, e in enumerate(best):
            if e == axes[i][0] and e - 2 >= -EXPONENT_LIMIT:
                axes[i].insert(0, e - 2)
                widened = True
            elif e == axes[i][-1] and e + 2 <= EXPONENT_LIMIT:
                axes[i].append(e + 2)
                widened = True
        if progress:
            progress(f"grid {'x'.join(str(len(a)) for a in axes)}, best 2**{list(best)}")
        if not widened:
            break
    return _refine(evaluate, best)


def _refine(evaluate, best: tuple[int, ...]) -> tuple[int, ...]:
    """From ``best``, move to the best factor-2 neighbour until none is better."""
    import itertools

    while True:
        around = [p for p in itertools.product(*[(e - 1, e, e + 1) for e in best])
                  if all(abs(e) <= EXPONENT_LIMIT for e in p)]
        new = min(around, key=evaluate)
        if new == best:
            return best
        best = new
