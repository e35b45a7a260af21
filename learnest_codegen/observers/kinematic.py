"""Kinematic observers (``kf``, ``rts``) and the full-state smoother: one constant-acceleration
Kalman filter per kinematic chain (a measured position and its derivatives), no dynamics model,
white-jerk intensity by maximum innovation likelihood."""

from __future__ import annotations

import numpy as np

from ..data import Run
from ..errors import ObserverError
from ..systems import KinematicChain, System
from .base import JERK_GRID, Observations
from .kalman import FilterPasses, LinearGaussian, integrator_chain, kalman_filter, rts_smoother


def _kinematic(run: Run, system: System, smooth: bool) -> Observations:
    chains = kinematic_chains(system)
    name = "rts" if smooth else "kf"
    if not chains:
        raise ObserverError(f"system {system.name!r} declares no kinematic chains and none can be read "
                            f"from its equations (an output equal to a state); observer {name!r} "
                            "needs them: use observer 'ekf_rts' or 'ukf'")
    T = len(run)
    zeta = np.full((T, system.nx), np.nan)
    var = np.full((T, system.nx), np.nan)
    info = {}
    groups = chain_groups(system, chains)
    fits = {}
    for batch in _same_filters(run, system, groups):  # chains whose filters differ only in z
        fits.update(zip(batch, _fit_chains(run, system, [groups[i] for i in batch], smooth)))
    for g, (chain, measured) in enumerate(groups):
        means, covs, q = fits[g]
        for j, state in enumerate(chain.states):
            i = system.state_names.index(state)
            zeta[:, i], var[:, i] = means[:, j], covs[:, j, j]
        info[chain.output] = {"jerk_spectral_density": q,
                              "outputs": {system.output_names[o]: chain.states[k] for o, k in measured}}
    uncovered = [n for n, col in zip(system.state_names, zeta.T) if np.isnan(col).any()]
    if uncovered:
        raise ObserverError(f"system {system.name!r}: states {uncovered} are in no kinematic chain; "
                            f"observer {name!r} needs every state in one: use observer 'ekf_rts' or 'ukf'")
    if not system.kinematic_chains:
        info["chains_read_from_equations"] = [[c.output, list(c.states)] for c in chains]
    return Observations(zeta, var, name, info)


def kinematic_chains(system: System) -> tuple[KinematicChain, ...]:
    """The system's kinematic chains: those it declares, or else those its prior's equations
    show (see :func:`inferred_chains`)."""
    return tuple(system.kinematic_chains) or inferred_chains(system)


def inferred_chains(system: System) -> tuple[KinematicChain, ...]:
    """Kinematic chains read off the prior's equations: an output that is exactly a state
    (``h_j(x, u) = x_i``), followed by the states that are exactly its successive derivatives
    (``f_i(x, u) = x_k``, ...). Evaluated symbolically (CasADi), so ``y = x[0]`` and ``qdot``
    as the derivative of ``q`` are recognised whatever the file calls them."""
    import casadi as cs

    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    xu = cs.vertcat(x, u)
    h, f = system.h(x, u), system.f(x, u)

    def state_of(expr) -> int | None:  # i when expr is identically x_i
        J = cs.jacobian(expr, xu)
        if cs.depends_on(J, xu):
            return None
        row = np.array(cs.DM(cs.evalf(J))).ravel()
        offset = float(cs.evalf(cs.substitute(expr, xu, cs.DM.zeros(xu.shape[0]))))
        hits = np.flatnonzero(row)
        if offset != 0 or len(hits) != 1 or row[hits[0]] != 1.0 or hits[0] >= system.nx:
            return None
        return int(hits[0])

    chains = []
    for j, output in enumerate(system.output_names):
        i = state_of(h[j])
        if i is None:
            continue
        states = [i]
        while (k := state_of(f[states[-1]])) is not None and k not in states:
            states.append(k)
        chains.append(KinematicChain(output, tuple(system.state_names[s] for s in states)))
    return tuple(chains)


def chain_groups(system: System, chains: tuple[KinematicChain, ...] | None = None
                 ) -> list[tuple[KinematicChain, list[tuple[int, int]]]]:
    """The kinematic chains with every output that measures one of their states.

    A chain whose states continue another's (``KinematicChain("qdot", ("qdot",))`` after
    ``KinematicChain("q", ("q", "qdot"))``: a gyro next to an encoder) is not filtered on its
    own: its output becomes a second measurement of the longer chain's filter, at its derivative
    order, so the angle and the rate are fused rather than one replacing the other. Returns per
    longest chain the ``(output index, position in the chain)`` of each output it carries.
    Chains that share states without one continuing the other are an error.
    """
    chains = list(system.kinematic_chains if chains is None else chains)

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
                raise ObserverError(f"system {system.name!r}: state {s!r} is in the kinematic chains of "
                                 f"outputs {seen[s]!r} and {a.output!r}, and neither continues the other")
            seen[s] = a.output
    return out


def _chain_filter(run: Run, system: System, chain: KinematicChain, measured: list[tuple[int, int]]):
    """A chain's filter: its outputs, their variances, the derivative orders they measure and
    the filter's order."""
    outputs = [o for o, _ in measured]
    r = np.square(np.asarray(system.noise.measurement_std, float)[outputs])
    return outputs, r, tuple(k for _, k in measured), len(chain.states) + 1


def _same_filters(run: Run, system: System, groups: list) -> list[list[int]]:
    """The chain groups (indices into ``groups``) whose filters share everything but the
    measurements' values: the order, the derivative orders measured, the variances and which
    samples are missing. Their covariance recursions are then the same, and one batch filters
    them all in one pass (the numbers of separate passes)."""
    batches: list[tuple[tuple, list[int]]] = []
    for g, (chain, measured) in enumerate(groups):
        outputs, r, rows, order = _chain_filter(run, system, chain, measured)
        key = (order, rows, r.tobytes(), np.isfinite(run.y[:, outputs]).tobytes())
        hit = next((b for k, b in batches if k == key), None)
        if hit is None:
            batches.append((key, [g]))
        else:
            hit.append(g)
    return [b for _, b in batches]


def _fit_chains(run: Run, system: System, groups: list, smooth: bool) -> list[tuple]:
    """Each chain group's smoothed (or filtered) means and covariances of its states and its
    jerk intensity by maximum likelihood; the groups share their filters' structure
    (:func:`_same_filters`), and every chain with every grid intensity is one member of one
    batch."""
    G = len(JERK_GRID)
    filters = [_chain_filter(run, system, chain, measured) for chain, measured in groups]
    _, r, rows, order = filters[0]
    z = np.repeat(np.stack([run.y[:, outputs] for outputs, *_ in filters], axis=1), G, axis=1)
    passes, model = chain_passes(z, run.dt, order, np.tile(JERK_GRID, len(groups)), r, rows)
    best = np.argmax(passes.loglik.reshape(len(groups), G), axis=1)  # the first of equals, as max()
    members = best + G * np.arange(len(groups))  # member c * G + g: chain c, intensity g
    chosen = FilterPasses(*(a[:, members] for a in (passes.means, passes.covs, passes.means_p,
                                                    passes.covs_p)), passes.loglik[members])
    means, covs = rts_smoother(model.F, chosen) if smooth else (chosen.means, chosen.covs)
    n = order - 1
    return [(means[:, c, :n], covs[:, c, :n, :n], float(JERK_GRID[b])) for c, b in enumerate(best)]


def chain_passes(z: np.ndarray, dt: float, order: int, q, r, rows: tuple[int, ...] = (0,)):
    """Constant-(order-1)-derivative Kalman filters over one coordinate, one per white-noise
    intensity in ``q`` (one pass for all), measured at the derivative orders ``rows``.

    ``z`` is (T,) or (T, len(rows)) with NaN for a missing sample, or (T, B, len(rows)) per
    filter; ``r`` the measurement variances, (len(rows),) or (B, len(rows)). The filters start
    at the first sample present with its variance, the unmeasured derivatives at 0 with variance
    1e4. Returns the :class:`~.kalman.FilterPasses` and the model (``F``, ``Q`` of each filter).
    """
    z = np.asarray(z, float)
    z = z.reshape(len(z), -1) if z.ndim < 3 else z
    qs = np.atleast_1d(np.asarray(q, float))
    B, m = len(qs), z.shape[-1]
    r = np.broadcast_to(np.asarray(r, float), (B, m))
    F, unit = integrator_chain(order, dt)  # exact discretisation of an integrator chain
    unit = unit if order <= 4 else np.eye(order) * dt
    Q = qs[:, None, None] * unit
    H = np.eye(order)[list(rows)]
    R = r[:, :, None] * np.eye(m)
    x0, P0 = np.zeros((B, order)), np.full((B, order), 1e4)
    first = np.broadcast_to(z[0], (B, m))  # z[0] is (m,) shared or (B, m) per filter
    for col, k in enumerate(rows):
        seen = np.isfinite(first[:, col])
        x0[seen, k], P0[seen, k] = first[seen, col], r[seen, col]
    passes = kalman_filter(F, H, Q, R, z, x0, P0[:, :, None] * np.eye(order))
    return passes, LinearGaussian(F, Q, H, R)


def smooth_states(states: np.ndarray, dt: float, std) -> np.ndarray:
    """Full-state measurements to state observations: each state column is smoothed on its own
    by a constant-acceleration RTS smoother (white-jerk intensity by maximum likelihood).

    The full-state variant of training measures every state with noise ``std``; this is its
    pre-training observer. Differencing raw noisy states one step apart would bury the
    residual's ``dt * Delta`` under ``sqrt(2) * std`` of noise.
    """
    states = np.asarray(states, dtype=float)
    T, nx = states.shape
    std = np.broadcast_to(np.asarray(std, dtype=float), (nx,))
    r = np.maximum(std**2, 1e-18)
    G = len(JERK_GRID)
    # every state column with every grid intensity: one batch of nx * G filters
    z = np.repeat(states, G, axis=1)[:, :, None]  # member c * G + g: column c, intensity g
    passes, model = chain_passes(z, dt, 3, np.tile(JERK_GRID, nx), np.repeat(r, G)[:, None])
    best = np.argmax(passes.loglik.reshape(nx, G), axis=1) + np.arange(nx) * G
    chosen = FilterPasses(*(a[:, best] for a in (passes.means, passes.covs, passes.means_p,
                                                 passes.covs_p)), passes.loglik[best])
    means, _ = rts_smoother(model.F, chosen)
    return means[:, np.arange(nx), 0]
