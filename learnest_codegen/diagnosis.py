"""Diagnosing the sim-to-real gap of a prior: where it lies, which effect causes it, how far it shrinks.

``diagnose(system, runs)`` answers three questions from recorded runs:

1. **Where.** The one-step residual of the prior, a derivative error per state
   (:func:`~learnest_codegen.effect_fit.one_step`), computed from state observations: the truth
   when a run has it, otherwise the system's pre-training observer. Per state: its share of the
   gap and its size relative to the noise floor (``snr``); binned over the states, inputs and
   time (regimes, drifts); and, given a trained KNODE model, how the learned residual compares.
2. **Which.** The effect library (:mod:`~learnest_codegen.effects`) fitted by sparse,
   cross-validated selection (:mod:`~learnest_codegen.effect_fit`): ranked effects with
   parameters, bootstrap uncertainty and held-out shares, or "unexplained".
3. **How far it shrinks.** On held-out data (the last run, or the last ``holdout`` of a single
   run): the one-step residual and the nominal estimators' MSE with the prior, the corrected
   prior, the KNODE model and (in simulation) the true dynamics.

The noise floor
---------------
What residual would a *perfect* prior leave? With truth, only the integrator's error: the floor
is a relative tolerance, ``relative_floor`` times the RMS of the prior's derivative. With
observer output, the observer's errors ``e_k``: ``r_k ~ (e_{k+1} - e_k) / dt``. The observer's
marginal variances bound this only if its errors were independent from sample to sample,
``(var_k + var_{k+1}) / dt^2`` (reported as ``floor_independent``); a smoother's errors are
strongly correlated, so that bound is far too high (cartpole: 12 m/s^2 for the cart against a
true gap of about 1 m/s^2) and useless as a threshold. The floor is therefore *measured* by a
calibration on the data's own trajectory (:func:`calibration`): synthetic measurements of the
observed trajectory, through the same observer, give per state the residual RMS ``sigma_s`` a
perfect model would leave at the data's speeds and inputs, and per effect what its feature can
"explain" of pure observer error (observer artefacts correlate with the state: a smoother lags
in hard accelerations). A calibration on a separately *simulated* run of the exact prior was
tried first and rejected: the simulated run's speeds need not resemble the data's (the ground
robot's excitation feeds the true drag forward, so an exact-prior run speeds up to 6.5 m/s,
where the observer's speed error is twice as large, which hid the real 1.05-C_D drag below the
floor). When the calibration fails, the floor falls back to the white part of the residual (the
MAD of its first differences), and the report says so.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import casadi as cs
import numpy as np

from .data import Run, read_run
from .effect_fit import EffectFit, FitSettings, Pairs, fit_effects, one_step, single_feature_size, weighted
from .effects import Effect, corrected_system, default_context, library
from .errors import DataError, UnknownNameError
from .integrators import rk4_step
from .systems import System

SOURCES = ("auto", "truth", "observer")


@dataclass(frozen=True)
class DiagnosisSettings:
    """Settings of :func:`diagnose`.

    Attributes
    ----------
    source : ``"auto"`` (truth when every run has it), ``"truth"`` or ``"observer"``.
    observer : pre-training observer (default: the system's).
    holdout : share of a single run held out at its end for the shrink step (several runs: the
        last run is held out).
    relative_floor : floor of a state's noise level, relative to the RMS of its prior derivative.
    calibrate : measure the noise floor on a simulated run of the exact prior.
    snr_gap : a residual state with ``snr`` above this carries a gap.
    estimators, backend : nominal estimators run in the shrink step (``()`` skips them).
    kinds : restrict the library to these effect kinds (default: all).
    fit : the selection settings.
    seed : seeds the calibration's synthetic measurement noise.
    """

    source: str = "auto"
    observer: str | None = None
    holdout: float = 0.3
    relative_floor: float = 1e-3
    calibrate: bool = True
    snr_gap: float = 1.5
    estimators: tuple[str, ...] = ("mhe", "ukf")
    backend: str = "c"
    kinds: tuple[str, ...] | None = None
    fit: FitSettings = field(default_factory=FitSettings)
    regime_bins: int = 5
    time_bins: int = 10
    seed: int = 0

    def __post_init__(self) -> None:
        if self.source not in SOURCES:
            raise UnknownNameError(f"unknown source {self.source!r}; choose from {list(SOURCES)}")
        if self.backend not in ("c", "python"):
            raise UnknownNameError(f"unknown backend {self.backend!r}; choose from ['c', 'python']")
        if not 0.05 <= self.holdout <= 0.8 or not self.relative_floor > 0 or self.regime_bins < 2:
            raise ValueError(f"DiagnosisSettings: need 0.05 <= holdout <= 0.8, relative_floor > 0, "
                             f"regime_bins >= 2; got {self}")
        object.__setattr__(self, "estimators", tuple(self.estimators))

    def to_json(self) -> dict:
        return asdict(self)


@dataclass
class Segment:
    """A stretch of one run with its state observations ``z`` and observer variances ``var``."""

    run: Run
    z: np.ndarray
    var: np.ndarray | None
    reference: np.ndarray  # what estimators are scored against: truth, or z


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


# -- loading ---------------------------------------------------------------------------------------
def load_runs(system: System, data: str | Path) -> list[Run]:
    """A run CSV, or every ``*.csv`` of a folder (sorted by name), in the project's run format."""
    data = Path(data)
    if data.is_dir():
        files = sorted(data.glob("*.csv"))
        if not files:
            raise DataError(f"{data}: no *.csv runs in this folder")
        return [read_run(f, system) for f in files]
    return [read_run(data, system)]


def _read_nanobench(path: Path) -> list[Run]:
    from .recordings import crazyflie

    files = crazyflie.list_flights(path) if path.is_dir() else [path]
    return [crazyflie.read_flight(f).run for f in files]


def _read_dart(path: Path) -> list[Run]:
    from .recordings import dart

    files = sorted(p for p in path.glob("*.csv")) if path.is_dir() else [path]
    return [dart.read_recording(f) for f in files]


# format -> (reader of a file or folder, the system its runs belong to; None: --system decides)
FORMATS = {"run": (None, None), "nanobench": (_read_nanobench, "quadrotor"), "dart": (_read_dart, "rc_car")}


def load(system_name: str | None, data: str | Path, data_format: str = "run") -> tuple[System, list[Run]]:
    """Resolve the system and read the runs of ``data`` in ``data_format`` (see :data:`FORMATS`)."""
    from .systems import get_system

    if data_format not in FORMATS:
        raise UnknownNameError(f"unknown data format {data_format!r}; choose from {sorted(FORMATS)}")
    reader, default_system = FORMATS[data_format]
    system = get_system(system_name or default_system or "cartpole")
    if reader is None:
        return system, load_runs(system, data)
    runs = reader(Path(data))
    if not runs:
        raise DataError(f"{data}: no {data_format} recordings found")
    if any(r.system != system.name for r in runs):
        raise DataError(f"{data}: {data_format} recordings belong to system {runs[0].system!r}, "
                        f"not {system.name!r}")
    return system, runs


# -- state observations and splitting --------------------------------------------------------------
def _segments(system: System, runs: Sequence[Run], settings: DiagnosisSettings):
    source = settings.source
    if source == "auto":
        source = "truth" if all(r.x is not None for r in runs) else "observer"
    if source == "truth" and any(r.x is None for r in runs):
        raise DataError("source 'truth' needs x_ columns in every run")
    from .observers import observe

    segments = []
    for run in runs:
        if source == "truth":
            segments.append(Segment(run, run.x, None, run.x))
        else:
            obs = observe(run, system, settings.observer)
            segments.append(Segment(run, obs.zeta, obs.variance, run.x if run.x is not None else obs.zeta))
    return source, segments


def _cut(seg: Segment, lo: int, hi: int) -> Segment:
    r = seg.run
    run = Run(r.t[lo:hi], r.u[lo:hi], r.y[lo:hi], None if r.x is None else r.x[lo:hi], r.system)
    return Segment(run, seg.z[lo:hi], None if seg.var is None else seg.var[lo:hi], seg.reference[lo:hi])


def split(segments: list[Segment], holdout: float) -> tuple[list[Segment], list[Segment]]:
    """Fit and held-out segments: the last run held out, or the end of a single run."""
    if len(segments) >= 2:
        return segments[:-1], segments[-1:]
    seg = segments[0]
    cut = int(round((1 - holdout) * len(seg.run)))
    if cut < 20 or len(seg.run) - cut < 20:
        raise DataError(f"run of {len(seg.run)} samples is too short to hold out {holdout:.0%}")
    return [_cut(seg, 0, cut)], [_cut(seg, cut, len(seg.run))]


def pairs_of(segments: Sequence[Segment]) -> Pairs:
    return Pairs.from_states([(s.run.t, s.z, s.run.u) for s in segments])


# -- the noise floor ---------------------------------------------------------------------------------
def calibration(system: System, effects: Sequence[Effect], segments: Sequence[Segment],
                settings: DiagnosisSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise floor of the observer on the data's own trajectory (see the module docstring).

    The data's state observations ``z`` are taken as a true trajectory; it is exactly the
    trajectory of the prior plus a known, time-indexed derivative correction ``d_k`` (the prior's
    residual along ``z``). Synthetic measurements ``h(z) + noise`` (the system's measurement
    noise) go through the same observer; the residual of "prior + d_k" on its output is then pure
    observer error, at the data's own speeds, accelerations and inputs. Returns the per-state RMS
    ``(nx,)`` of that residual, its features ``(N, nx, m)`` and the residual ``(N, nx)``.
    """
    rng = np.random.default_rng(settings.seed + 7_777)
    from .observers import observe

    rs, Js = [], []
    for seg in segments:
        run = seg.run
        y = np.asarray(system.h(seg.z, run.u))
        y = y + rng.normal(size=y.shape) * np.asarray(system.noise.measurement_std)
        synthetic = Run(run.t, run.u, y, seg.z, run.system)
        z_cal = observe(synthetic, system, settings.observer).zeta
        on_truth = Pairs.from_states([(run.t, seg.z, run.u)])
        on_observed = Pairs.from_states([(run.t, z_cal, run.u)])
        known, _ = one_step(system, effects, np.zeros(len(effects)), on_truth, with_features=False)
        r, J = one_step(system, effects, np.zeros(len(effects)), on_observed)
        diff = r - known
        for name in system.periodic_states:  # residuals are rates; wrap their step-sized parts
            i = system.state_names.index(name)
            diff[:, i] = np.angle(np.exp(1j * diff[:, i] * on_truth.dt)) / on_truth.dt
        rs.append(diff)
        Js.append(J)
    r, J = np.concatenate(rs), np.concatenate(Js)
    if not np.isfinite(r).all():
        raise DataError("calibration residual is not finite")
    return np.sqrt(np.mean(r**2, axis=0)), J, r


def white_floor(r: np.ndarray) -> np.ndarray:
    """(nx,) std of the white part of a residual: 1.4826 MAD of its first differences / sqrt 2."""
    d = np.diff(r, axis=0)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2.0)


def derivative_scale(system: System, pairs: Pairs) -> np.ndarray:
    """(nx,) RMS of the prior's derivative over the data: the scale of "how fast a state moves"."""
    f = np.asarray(system.f(pairs.x, pairs.u))
    return np.sqrt(np.mean(f**2, axis=0))


# -- where -----------------------------------------------------------------------------------------
def where(system: System, r: np.ndarray, sigma: np.ndarray, pairs: Pairs, settings: DiagnosisSettings,
          var: np.ndarray | None = None) -> dict:
    """Per-state share and snr, and the regime breakdown of the residual (JSON-ready)."""
    snr = np.sqrt(np.mean(r**2, axis=0)) / sigma
    # Shares over the residual states only: a kinematic row (p' = pdot) sees a derivative gap
    # only through the RK4 step's own integration (dt/2 of it), not as a gap of its own.
    residual = np.array([n in system.residual_state_names for n in system.state_names])
    excess = np.where(residual, np.maximum(snr**2 - 1.0, 0.0), 0.0)
    share = excess / excess.sum() if excess.sum() > 0 else np.zeros_like(excess)
    states = []
    for i, name in enumerate(system.state_names):
        row = {"state": name, "share": float(share[i]), "snr": float(snr[i]),
               "rms": float(np.sqrt(np.mean(r[:, i] ** 2))), "mean": float(np.mean(r[:, i])),
               "floor": float(sigma[i]), "unit": f"{system.states[i].unit}/s",
               "residual_state": name in system.residual_state_names,
               "gap": bool(snr[i] > settings.snr_gap and name in system.residual_state_names)}
        if var is not None:
            row["floor_independent"] = float(np.sqrt(np.mean(var[:-1, i] + var[1:, i])) / np.mean(pairs.dt))
        states.append(row)
    return {"states": states, "regimes": regimes(system, r, pairs, settings)}


def regime_variables(system: System, pairs: Pairs) -> dict[str, np.ndarray]:
    """The variables the residual is binned over: every state, every input, and time."""
    out = {}
    for i, s in enumerate(system.states):
        value = pairs.x[:, i]
        if s.name in system.periodic_states:
            value = np.angle(np.exp(1j * value))
        out[s.name] = value
    for j, s in enumerate(system.inputs):
        out[s.name if s.name not in out else f"u_{s.name}"] = pairs.u[:, j]
    out["t"] = pairs.t  # from each run's start
    return out


def regimes(system: System, r: np.ndarray, pairs: Pairs, settings: DiagnosisSettings) -> dict:
    """Mean and RMS of each residual state's residual in quantile bins of each variable.

    ``eta2`` is the correlation ratio (between-bin variance of the residual / its variance): how
    much of the residual that variable's regime explains; ``drivers`` ranks the variables by it.
    Time bins are equal-width (slow drifts); the others are quantile bins.
    """
    out, drivers = {}, {}
    rows = [system.state_names.index(s) for s in system.residual_state_names]
    for name, value in regime_variables(system, pairs).items():
        bins = settings.time_bins if name == "t" else settings.regime_bins
        if name == "t":
            edges = np.linspace(value.min(), value.max(), bins + 1)
        else:
            edges = np.unique(np.quantile(value, np.linspace(0, 1, bins + 1)))
        if len(edges) < 3:
            continue
        label = np.clip(np.searchsorted(edges, value, side="right") - 1, 0, len(edges) - 2)
        entry = {"edges": edges.tolist(), "count": np.bincount(label, minlength=len(edges) - 1).tolist(),
                 "mean": {}, "rms": {}, "eta2": {}}
        for i in rows:
            s = system.state_names[i]
            means = np.array([r[label == b, i].mean() if np.any(label == b) else np.nan
                              for b in range(len(edges) - 1)])
            rms = np.array([np.sqrt(np.mean(r[label == b, i] ** 2)) if np.any(label == b) else np.nan
                            for b in range(len(edges) - 1)])
            total = np.sum((r[:, i] - r[:, i].mean()) ** 2)
            between = np.nansum(np.array(entry["count"]) * (means - r[:, i].mean()) ** 2)
            entry["mean"][s], entry["rms"][s] = means.tolist(), rms.tolist()
            entry["eta2"][s] = float(between / total) if total > 0 else 0.0
        out[name] = entry
    for i in rows:
        s = system.state_names[i]
        ranked = sorted(out, key=lambda v: -out[v]["eta2"][s])
        drivers[s] = [{"variable": v, "eta2": out[v]["eta2"][s]} for v in ranked[:3]]
    return {"variables": out, "drivers": drivers}


# -- residuals of whole models -------------------------------------------------------------------------
def model_residual(system: System, xdot, pairs: Pairs) -> np.ndarray:
    """One-step residual ``(N, nx)`` of ``xdot(x_sx, u_sx) -> SX`` (RK4 with each pair's dt)."""
    x, u, dt = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu), cs.SX.sym("dt")
    step = cs.Function("step", [x, u, dt], [rk4_step(xdot, x, u, dt)])
    pred = np.asarray(step.map(len(pairs))(pairs.x.T, pairs.u.T, pairs.dt[None, :])).T
    diff = pairs.x_next - pred
    for name in system.periodic_states:
        i = system.state_names.index(name)
        diff[:, i] = np.angle(np.exp(1j * diff[:, i]))
    return diff / pairs.dt[:, None]


def gap_size(r: np.ndarray, sigma: np.ndarray, rows: Sequence[int]) -> float:
    """Mean square of the residual states' residual above the floor, in noise units."""
    return float(max(np.mean((r[:, rows] / sigma[rows]) ** 2) - 1.0, 0.0))


def _has_truth_model(system: System) -> bool:
    return system.true_dynamics is not None or dict(system.true_params) != dict(system.params)


# -- the whole diagnosis ---------------------------------------------------------------------------
def diagnose(system: System, runs: Sequence[Run], *, model=None,
             settings: DiagnosisSettings = DiagnosisSettings(), work_dir: str | Path | None = None,
             progress: bool = False) -> Diagnosis:
    """Diagnose the prior of ``system`` on ``runs`` (see the module docstring).

    Parameters
    ----------
    system : the system (its prior is diagnosed).
    runs : recorded or simulated runs of it.
    model : an optional :class:`~learnest_codegen.training.TrainedModel` to compare with.
    settings : :class:`DiagnosisSettings`.
    work_dir : where compiled estimators go (C backend); a temporary folder by default.
    """
    from tqdm.auto import tqdm

    start = time.perf_counter()
    if not runs:
        raise DataError("diagnose: no runs given")
    bar = tqdm(total=5, desc=f"diagnosing {system.name}", disable=not progress)
    source, segments = _segments(system, runs, settings)
    fit_segs, held_segs = split(segments, settings.holdout)
    fit_pairs, held_pairs = pairs_of(fit_segs), pairs_of(held_segs)
    bar.update()

    vel = default_context(system).velocity_states
    speed = {v: float(np.sqrt(np.mean(fit_pairs.x[:, system.state_names.index(v)] ** 2))) for v in vel}
    effects = library(system, default_context(system, speed), settings.kinds)
    r0, _ = one_step(system, effects, np.zeros(len(effects)), fit_pairs, with_features=False)
    scale = derivative_scale(system, fit_pairs)
    floor_method, spurious_raw, cal = "relative", None, None
    sigma_cal = np.zeros(system.nx)
    if source == "observer" and settings.calibrate:
        try:
            sigma_cal, J_cal, r_cal = calibration(system, effects, fit_segs, settings)
            floor_method = "calibration (the observer on synthetic measurements of the data's trajectory)"
            cal = (J_cal, r_cal)
        except Exception as exc:  # e.g. an observer that fails on this system; fall back, say so
            sigma_cal = white_floor(r0)
            floor_method = f"white part of the residual (calibration failed: {exc!r})"
    elif source == "observer":
        sigma_cal, floor_method = white_floor(r0), "white part of the residual"
    sigma = np.maximum(np.maximum(sigma_cal, settings.relative_floor * scale), 1e-12)
    rows = [system.state_names.index(s) for s in system.residual_state_names]
    if cal is not None:
        spurious_raw = single_feature_size(weighted(cal[1], cal[0], rows, sigma[rows]))
    bar.update()

    var = np.concatenate([s.var[:-1] for s in fit_segs]) if fit_segs[0].var is not None else None
    where_part = where(system, r0, sigma, fit_pairs, settings, var)
    if model is not None:
        where_part["knode"] = _knode_comparison(system, model, fit_pairs, r0, rows)
    bar.update()

    fit = fit_effects(system, effects, fit_pairs, rows, sigma[rows], spurious_raw, settings.fit)
    bar.update()

    shrink, held_res, estimates = _shrink(system, effects, fit, model, held_segs, held_pairs, sigma, rows,
                                          settings, work_dir)
    bar.update()
    bar.close()
    report = {
        "system": system.name, "source": source,
        "observer": settings.observer or (system.default_observer if source == "observer" else None),
        "runs": len(runs), "fit_pairs": len(fit_pairs), "heldout_pairs": len(held_pairs),
        "noise_floor": {"method": floor_method,
                        "sigma": dict(zip(system.state_names, map(float, sigma)))},
        "where": where_part["states"], "regimes": where_part["regimes"],
        "knode": where_part.get("knode"),
        "effects": _effects_json(system, effects, fit),
        "unexplained": float(1.0 - fit.explained_total) if _gap_present(where_part, fit) else 0.0,
        "verdict": _verdict(where_part, fit),
        "selection": {"steps": [_step_json(effects, s) for s in fit.steps],
                      "stopped_at": _step_json(effects, fit.rejected) if fit.rejected else None,
                      "library_size": len(effects),
                      "duplicates": {effects[k].name: effects[v].name for k, v in fit.duplicates.items()}},
        "shrink": shrink,
        "settings": settings.to_json(),
        "seconds": time.perf_counter() - start,
    }
    return Diagnosis(system, report, fit_pairs, held_pairs, r0, sigma, held_res, effects, fit, estimates)


def _gap_present(where_part: dict, fit: EffectFit) -> bool:
    return bool(fit.chosen) or any(s["gap"] for s in where_part["states"])


def _verdict(where_part: dict, fit: EffectFit) -> str:
    if not _gap_present(where_part, fit):
        return "no gap"
    if not fit.chosen:
        return "unexplained"
    left = 1.0 - fit.explained_total
    return "explained" if left < 0.25 else "partly explained" if left < 0.6 else "unexplained"


def _step_json(effects: Sequence[Effect], step: dict | None) -> dict | None:
    if step is None or step.get("index") is None:
        return step
    return {**step, "effect": effects[step["index"]].name}


def _effects_json(system: System, effects: Sequence[Effect], fit: EffectFit) -> list[dict]:
    """One entry per selected effect; the columns of a multi-parameter effect (``Effect.group``)
    are one entry with all their parameters (and, for the ``a/X`` + ``1/X`` pattern of a gain over
    a time constant, the derived ``X`` and ``a`` under ``"derived"``)."""
    out, done = [], set()
    t_of = {st["index"]: float(st["t"]) for st in fit.steps}
    for k, j in enumerate(fit.chosen):
        e = effects[j]
        if e.group and e.group in done:
            continue
        ks = [i for i, jj in enumerate(fit.chosen) if effects[jj].group == e.group] if e.group else [k]
        cols = [effects[fit.chosen[i]] for i in ks]
        params = {c.param: float(fit.theta[i]) for c, i in zip(cols, ks)}
        how, target = e.channel.split(":", 1)
        if how == "param":
            params[target] = float(system.params[target] + fit.theta[k])
        entry = {"kind": e.kind, "state": e.state, "channel": e.channel,
                 "name": f"{e.group}({target})" if e.group else e.name,
                 "params": params,
                 "uncertainty": {c.param: float(fit.theta_std[i]) for c, i in zip(cols, ks)},
                 "units": {c.param: c.unit for c in cols},
                 "explained": float(sum(fit.explained[i] for i in ks)),
                 "score": float(fit.scores[k]), "t": t_of.get(j, float("nan")),
                 "aliases": sorted({effects[a].name for i in ks for a in fit.aliases[i]
                                    if effects[a].group != e.group or not e.group}),
                 "description": "; ".join(c.description for c in cols)}
        if e.group:
            done.add(e.group)
            from .effects import DERIVED

            rates = [p for p in params if p.startswith("1/")] if e.group not in DERIVED else []
            derived = DERIVED[e.group](params) if e.group in DERIVED else {}
            for rate in rates:
                x = rate[2:]
                if params[rate] != 0:
                    derived[x] = 1.0 / params[rate]
                    for p, v in params.items():
                        if p.endswith("/" + x) and p != rate:
                            derived[p[:-len(x) - 1]] = v / params[rate]
            if derived:
                entry["derived"] = derived
        out.append(entry)
    return sorted(out, key=lambda d: -d["explained"])


def _knode_comparison(system: System, model, pairs: Pairs, r: np.ndarray, rows: Sequence[int]) -> dict:
    """How the learned residual compares with the measured one (per residual state)."""
    import torch

    with torch.no_grad():
        delta = model.net(torch.as_tensor(pairs.x), torch.as_tensor(pairs.u)).numpy()
    out = {}
    for i in rows:
        s = system.state_names[i]
        err = r[:, i] - delta[:, i]
        var = np.var(r[:, i])
        out[s] = {"r2": float(1 - np.mean(err**2) / var) if var > 0 else None,
                  "corr": float(np.corrcoef(r[:, i], delta[:, i])[0, 1]) if np.std(delta[:, i]) > 0 else 0.0,
                  "learned_rms": float(np.sqrt(np.mean(delta[:, i] ** 2))),
                  "measured_rms": float(np.sqrt(np.mean(r[:, i] ** 2)))}
    return out


# -- shrink ------------------------------------------------------------------------------------------
def _shrink(system: System, effects, fit: EffectFit, model, held_segs, pairs: Pairs, sigma, rows,
            settings: DiagnosisSettings, work_dir):
    chosen = [effects[j] for j in fit.chosen]
    corrected = corrected_system(system, chosen, fit.theta)
    xdots = {"prior": lambda x, u: system.f(x, u),
             "corrected": lambda x, u: corrected.f(x, u)}
    if model is not None:
        xdots["knode"] = lambda x, u: system.f(x, u) + model.net.casadi(x, u)
    simulated = all(s.run.x is not None for s in held_segs) and _has_truth_model(system)
    if simulated:
        xdots["true"] = lambda x, u: system.f(x, u, variant="true")
    residuals = {k: model_residual(system, f, pairs) for k, f in xdots.items()}
    gaps = {k: gap_size(r, sigma, rows) for k, r in residuals.items()}
    one = {"metric": "mean square of the residual-state residual above the noise floor [noise units^2]",
           **{k: v for k, v in gaps.items()}, "before": gaps["prior"], "after": gaps["corrected"],
           "closed": _closed(gaps["prior"], gaps["corrected"], gaps.get("true")),
           "rms": {k: dict(zip(system.state_names, np.sqrt(np.mean(r**2, axis=0)).tolist()))
                   for k, r in residuals.items()},
           "rms_over_floor": {k: float(np.sqrt(np.mean((r[:, rows] / sigma[rows]) ** 2)))
                              for k, r in residuals.items()}}
    if "knode" in gaps:
        one["closed_knode"] = _closed(gaps["prior"], gaps["knode"], gaps.get("true"))
    shrink = {"one_step": one}
    estimates = {}
    if settings.estimators:
        est, estimates = _estimators(system, corrected, fit, chosen, model, held_segs, simulated, settings,
                                     work_dir)
        shrink.update(est)
    return shrink, residuals, estimates


def _closed(before: float, after: float, floor: float | None) -> float | None:
    base = before - (floor or 0.0)
    return float((before - after) / base) if base > 0 else None


def _estimators(system, corrected, fit, chosen, model, held_segs, simulated, settings, work_dir):
    """Run each nominal estimator with each model on the held-out segments; MSE per model."""
    import tempfile

    from .compilation import compile_estimators, estimator_dir, estimator_kind
    from .evaluation import mse, run_estimator
    from .export import hybrid_model, prior_model, true_model

    key = hashlib.sha256(json.dumps([[e.name for e in chosen], list(map(float, fit.theta))]).encode())
    models = {"prior": (prior_model(system), "nominal"),
              "corrected": (prior_model(corrected), "corrected-" + key.hexdigest()[:16])}
    if model is not None:
        models["knode"] = (hybrid_model(system, model.net), model.hash)
    if simulated:
        models["true"] = (true_model(system), "true")
    root = Path(work_dir) if work_dir else Path(tempfile.mkdtemp(prefix="learnest_diagnose_"))
    out, estimates = {}, {}
    for name in settings.estimators:
        kind = estimator_kind(name)
        scores, estimates[name] = {}, {}
        for label, (discrete, model_hash) in models.items():
            if settings.backend == "python":
                estimator = kind.python(discrete, kind.default_settings(discrete))
            else:
                folder = root / "compiled" / label
                compile_estimators(discrete, folder, model_hash=model_hash, estimators=(name,))
                estimator = kind.compiled(estimator_dir(folder, discrete, name),
                                          expect={"system": system.name, "model_hash": model_hash})
            errors, x_hats = [], []
            for seg in held_segs:
                res = run_estimator(estimator, seg.run, seg.reference[0], f"{name}:{label}")
                errors.append(mse(res.x_hat, seg.reference))
                x_hats.append(res.x_hat)
            scores[label] = float(np.mean(errors))
            estimates[name][label] = np.concatenate(x_hats)
        out[name] = {"metric": "MSE against " + ("the truth" if simulated or held_segs[0].run.x is not None
                                                 else "the observer's state observations"),
                     **scores, "before": scores["prior"], "after": scores["corrected"],
                     "closed": _closed(scores["prior"], scores["corrected"], scores.get("true"))}
        if "knode" in scores:
            out[name]["closed_knode"] = _closed(scores["prior"], scores["knode"], scores.get("true"))
    return out, estimates


def summary(report: dict) -> str:
    """A few lines for the terminal."""
    lines = [f"{report['system']}: {report['verdict']} (source: {report['source']}, "
             f"unexplained {report['unexplained']:.0%})"]
    for s in report["where"]:
        if s["residual_state"]:
            lines.append(f"  {s['state']:>10}': share {s['share']:.0%}, snr {s['snr']:.3g}")
    for e in report["effects"]:
        p = ", ".join(f"{k}={v:.4g}" for k, v in e["params"].items())
        lines.append(f"  {e['name']}: {p} (+-{next(iter(e['uncertainty'].values())):.2g}), "
                     f"explains {e['explained']:.0%}")
    one = report["shrink"]["one_step"]
    lines.append(f"  one-step gap {one['before']:.4g} -> {one['after']:.4g}"
                 + (f" (closed {one['closed']:.0%})" if one.get("closed") is not None else ""))
    for name in ("mhe", "ukf"):
        if name in report["shrink"]:
            s = report["shrink"][name]
            lines.append(f"  {name.upper()} MSE {s['before']:.4g} -> {s['after']:.4g}"
                         + (f" (closed {s['closed']:.0%})" if s.get("closed") is not None else ""))
    return "\n".join(lines)
