"""Where the gap lies: per-state share and snr, and the residual binned over regimes."""

from __future__ import annotations

from typing import Sequence

import casadi as cs
import numpy as np

from ..integrators import rk4_step
from ..systems import System
from .blur import matched
from .fit import Pairs
from .settings import DiagnosisSettings


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


def model_residual(system: System, xdot, pairs: Pairs) -> np.ndarray:
    """One-step residual ``(N, nx)`` of ``xdot(x_sx, u_sx) -> SX`` (RK4 with each pair's dt)."""
    x, u, dt = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu), cs.SX.sym("dt")
    step = cs.Function("step", [x, u, dt], [rk4_step(xdot, x, u, dt)])
    pred = np.asarray(step.map(len(pairs))(pairs.x.T, pairs.u.T, pairs.dt[None, :])).T
    diff = pairs.x_next - pred
    for name in system.periodic_states:
        i = system.state_names.index(name)
        diff[:, i] = np.angle(np.exp(1j * diff[:, i]))
    return matched(pairs, diff / pairs.dt[:, None])[0]


def gap_size(r: np.ndarray, sigma: np.ndarray, rows: Sequence[int]) -> float:
    """Mean square of the residual states' residual above the floor, in noise units."""
    return float(max(np.mean((r[:, rows] / sigma[rows]) ** 2) - 1.0, 0.0))


def _has_truth_model(system: System) -> bool:
    return system.true_dynamics is not None or dict(system.true_params) != dict(system.params)


def knode_comparison(system: System, model, pairs: Pairs, r: np.ndarray, rows: Sequence[int]) -> dict:
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
