"""Kinematic observers (``kf``, ``rts``) and the full-state smoother: one constant-acceleration
Kalman filter per kinematic chain (a measured position and its derivatives), no dynamics model,
white-jerk intensity by maximum innovation likelihood."""

from __future__ import annotations

import numpy as np
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter
from scipy.linalg import expm

from ..data import Run
from ..systems import KinematicChain, System
from .base import JERK_GRID, Observations


def _kinematic(run: Run, system: System, smooth: bool) -> Observations:
    if not system.kinematic_chains:
        raise ValueError(f"system {system.name!r} declares no kinematic chains; use observer 'ukf'")
    T = len(run)
    zeta = np.full((T, system.nx), np.nan)
    var = np.full((T, system.nx), np.nan)
    info = {}
    for chain, measured in chain_groups(system):
        means, covs, q = _fit_chain(run, system, chain, smooth, measured)
        for j, name in enumerate(chain.states):
            i = system.state_names.index(name)
            zeta[:, i], var[:, i] = means[:, j], covs[:, j, j]
        info[chain.output] = {"jerk_spectral_density": q,
                              "outputs": {system.output_names[o]: chain.states[k] for o, k in measured}}
    uncovered = [n for n, col in zip(system.state_names, zeta.T) if np.isnan(col).any()]
    if uncovered:
        raise ValueError(f"system {system.name!r}: states {uncovered} are in no kinematic chain")
    return Observations(zeta, var, "rts" if smooth else "kf", info)


def chain_groups(system: System) -> list[tuple[KinematicChain, list[tuple[int, int]]]]:
    """The kinematic chains with every output that measures one of their states.

    A chain whose states continue another's (``KinematicChain("qdot", ("qdot",))`` after
    ``KinematicChain("q", ("q", "qdot"))``: a gyro next to an encoder) is not filtered on its
    own: its output becomes a second measurement of the longer chain's filter, at its derivative
    order, so the angle and the rate are fused rather than one replacing the other. Returns per
    longest chain the ``(output index, position in the chain)`` of each output it carries.
    Chains that share states without one continuing the other are an error.
    """
    chains = list(system.kinematic_chains)

    def inside(b: KinematicChain, a: KinematicChain) -> int | None:
        n = len(b.states)
        starts = range(len(a.states) - n + 1)
        return next((k for k in starts if tuple(a.states[k:k + n]) == tuple(b.states)), None)

    def within_another(a: KinematicChain) -> bool:  # in a longer chain, or repeats an earlier one
        return any(b is not a and inside(a, b) is not None
                   and (len(b.states) > len(a.states) or chains.index(b) < chains.index(a)) for b in chains)

    roots = [a for a in chains if not within_another(a)]
    out = []
    for a in roots:
        measured = [(system.output_names.index(b.output), inside(b, a)) for b in chains
                    if inside(b, a) is not None]
        out.append((a, sorted(measured, key=lambda m: m[1])))
    seen: dict[str, str] = {}
    for a, _ in out:
        for s in a.states:
            if s in seen:
                raise ValueError(f"system {system.name!r}: state {s!r} is in the kinematic chains of "
                                 f"outputs {seen[s]!r} and {a.output!r}, and neither continues the other")
            seen[s] = a.output
    return out


def _fit_chain(run: Run, system: System, chain: KinematicChain, smooth: bool,
               measured: list[tuple[int, int]] | None = None):
    measured = measured or [(system.output_names.index(chain.output), 0)]
    outputs = [o for o, _ in measured]
    z = run.y[:, outputs]
    r = np.square(np.asarray(system.noise.measurement_std, float)[outputs])
    rows = tuple(k for _, k in measured)
    order = len(chain.states) + 1  # one derivative beyond the chain, driven by white noise
    best = max(JERK_GRID, key=lambda q: _chain_filter(z, run.dt, order, q, r, rows)[2])
    means, covs, _, kf, fs = _chain_filter(z, run.dt, order, best, r, rows)
    if smooth:
        means, covs, _, _ = kf.rts_smoother(means, covs, Fs=fs)
    n = len(chain.states)
    return means[:, :n, 0] if means.ndim == 3 else means[:, :n], covs[:, :n, :n], float(best)


def _chain_filter(z: np.ndarray, dt: float, order: int, q: float, r, rows: tuple[int, ...] = (0,)):
    """Constant-(order-1)-derivative KF over one coordinate, measured at the derivative orders
    ``rows`` (``z`` (T,) or (T, len(rows)), variances ``r``); returns the log-likelihood too."""
    z = np.asarray(z, float).reshape(len(z), -1)
    r = np.broadcast_to(np.asarray(r, float), (z.shape[1],))
    m = z.shape[1]
    kf = KalmanFilter(dim_x=order, dim_z=m)
    kf.F = expm(np.diag(np.full(order - 1, dt), 1))  # exact discretisation of an integrator chain
    kf.Q = Q_continuous_white_noise(dim=order, dt=dt, spectral_density=q) if order in (2, 3, 4) \
        else np.eye(order) * q * dt
    kf.H = np.eye(order)[list(rows)]
    kf.R = np.diag(r)
    kf.x = np.zeros((order, 1))
    P0 = np.full(order, 1e4)
    for col, k in enumerate(rows):
        kf.x[k, 0], P0[k] = z[0, col], r[col]
    kf.P = np.diag(P0)
    means, covs, means_p, covs_p = kf.batch_filter(z[:, :, None])
    innov = z - np.einsum("ij,tj->ti", kf.H, means_p[:, :, 0])
    S = np.einsum("ij,tjk,lk->til", kf.H, covs_p, kf.H) + kf.R
    white = np.linalg.solve(S, innov[:, :, None])[..., 0]
    loglik = -0.5 * float(np.sum(np.einsum("ti,ti->t", innov, white) + np.linalg.slogdet(2 * np.pi * S)[1]))
    return means, covs, loglik, kf, [kf.F] * len(z)


def smooth_states(states: np.ndarray, dt: float, std) -> np.ndarray:
    """Full-state measurements to state observations: each state column is smoothed on its own
    by a constant-acceleration RTS smoother (white-jerk intensity by maximum likelihood).

    The full-state variant of training measures every state with noise ``std``; this is its
    pre-training observer. Differencing raw noisy states one step apart would bury the
    residual's ``dt * Delta`` under ``sqrt(2) * std`` of noise.
    """
    states = np.asarray(states, dtype=float)
    std = np.broadcast_to(np.asarray(std, dtype=float), (states.shape[1],))
    out = np.empty_like(states)
    for i, (z, s) in enumerate(zip(states.T, std)):
        r = max(float(s) ** 2, 1e-18)
        best = max(JERK_GRID, key=lambda q: _chain_filter(z, dt, 3, q, r)[2])
        means, covs, _, kf, fs = _chain_filter(z, dt, 3, best, r)
        means, _, _, _ = kf.rts_smoother(means, covs, Fs=fs)
        out[:, i] = means[:, 0, 0] if means.ndim == 3 else means[:, 0]
    return out
