"""The one-step residual of a prior with effects and its exact features.

The one-step residual of a model with effect parameters ``theta`` is a derivative error,

    r_k(theta) = wrap(z_{k+1} - RK4_{dt_k}[f_prior + effects(theta)](z_k, u_k)) / dt_k   (N, nx)

and its features are ``Phi_k = d RK4 / d theta / dt_k`` (N, nx, m), exact CasADi derivatives
through the RK4 step, so ``r(theta + d) ~ r(theta) - Phi d``: a linear least-squares problem in
the library's parameters (with a damped, bounded refinement, :mod:`.refine`, for effects that
are nonlinear in their parameter, such as a mass). A ``filter:<u>`` effect (a delay, a lag)
changes the input sequence the pairs are stepped with; its feature is the step's Jacobian with
respect to the input times the filtered input's derivative in the parameter. The weighted,
cross-validated, bounded least squares on these is in :mod:`~learnest_codegen.diagnosis.cv`;
the selection in :mod:`~learnest_codegen.diagnosis.selection`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import casadi as cs
import numpy as np

from ..errors import ShapeError
from ..integrators import rk4_step
from ..systems import System
from ..systems.backends import CasadiOps
from .blur import matched
from .effects import Effect, corrected_dynamics, filter_inputs


@dataclass(frozen=True)
class FitSettings:
    """Settings of the sparse cross-validated selection (see the module docstring)."""

    folds: int = 10  # cross-validation folds (contiguous blocks, within runs)
    max_effects: int = 6
    t_min: float = 2.5  # fold-consistency t statistic to enter
    z_min: float = 4.0  # ... or, for a filter (a delay, a lag), the whole data's Wald statistic
    whiten_order: int = 20  # ... on data whitened by an AR(p <= this) of the residual (0: not whitened)
    gls_excess: float = 1.0  # final parameters by GLS only when the ordinary fit leaves at most this
    #                          mean square above the noise floor (noise units^2 a residual entry)
    t_drop: float = 1.5  # ... below which a chosen effect's loss lets it go (hysteresis: no flip-flop)
    min_gain: float = 0.01
    min_size: float = 0.1
    spurious_factor: float = 2.0
    alias_cos: float = 0.95  # |cosine| of weighted features above which two effects are aliases
    duplicate_cos: float = 0.99999  # ... above which the later one is dropped as a duplicate
    scan: int = 8  # candidates tested per step, best held-out SSE first
    pair_pool: int = 6  # when none passes alone, pairs of the best this many are tested together
    gap_noise: float = 1.0  # entry also needs a gain above this many stds of a pure-noise SSE
    min_share: float = 0.002  # ... and above this share of the prior's held-out gap
    rounds: int = 4  # re-test rounds once the forward selection stops (drop, retry, exchange)
    swap_tol: float = 1e-6  # relative SSE change within which two effect sets are equivalent
    refine_iterations: int = 20  # Levenberg-Marquardt iterations (see refine.py)
    max_step: float = 0.5  # per-step limit, relative to a parameter's value (or its scale)
    bound: float = 100.0  # a prior parameter stays within [p / bound, p * bound]
    bootstrap: int = 300
    blocks: int = 24
    seed: int = 0

    def __post_init__(self) -> None:
        if self.folds < 3 or self.whiten_order < 0 or self.max_effects < 1 or self.blocks < 4 \
                or self.bootstrap < 10 or not self.bound > 1 or not 0 < self.max_step <= 10 \
                or not self.gls_excess >= 0:
            raise ValueError(f"FitSettings: need folds >= 3, whiten_order >= 0, max_effects >= 1, "
                             f"blocks >= 4, bootstrap >= 10, bound > 1, 0 < max_step <= 10, "
                             f"gls_excess >= 0; got {self}")

    def to_json(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Pairs:
    """Consecutive sample pairs of one or more runs (pairs never cross runs).

    Attributes
    ----------
    x, x_next : (N, nx) states at ``t_k`` and ``t_{k+1}``.
    u : (N, nu) input held over the step.
    dt : (N,) step [s].
    t : (N,) time of ``x`` [s], from the start of its run.
    segment : (N,) index of the run each pair comes from.
    k : (N,) index of ``x`` within its run.
    inputs : per run, its whole ``(T, nu)`` input sequence (what ``filter:<u>`` effects filter).
    run_dt : per run, its sample period [s].
    blur : per run, the chains its observer smoothed (:mod:`~learnest_codegen.diagnosis.blur`;
        ``()``: the plain one-step residual).
    """

    x: np.ndarray
    u: np.ndarray
    x_next: np.ndarray
    dt: np.ndarray
    t: np.ndarray
    segment: np.ndarray
    k: np.ndarray | None = None
    inputs: tuple = ()
    run_dt: tuple = ()
    blur: tuple = ()

    def __len__(self) -> int:
        return self.x.shape[0]

    @classmethod
    def from_states(cls, segments: Sequence[tuple]) -> "Pairs":
        """From ``(t (T,), z (T, nx), u (T, nu))`` per run, optionally with the run's smoothed chains
        as a fourth element. A pair with a non-finite state or input (a missing sample) is left
        out; a run without any complete pair is an error."""
        parts, inputs, run_dt, blur = [], [], [], []
        for i, (t, z, u, *chains) in enumerate(segments):
            t, z, u = np.asarray(t, float), np.asarray(z, float), np.asarray(u, float)
            if z.ndim != 2 or u.ndim != 2 or len(t) != len(z) or len(u) != len(z) or len(z) < 2:
                raise ShapeError(f"run {i}: expected t (T,), z (T, nx), u (T, nu) with T >= 2, "
                                 f"got {t.shape}, {z.shape}, {u.shape}")
            ok = np.isfinite(z).all(axis=1) & np.isfinite(u).all(axis=1)
            keep = ok[:-1] & ok[1:]
            if not keep.any():
                raise ShapeError(f"run {i}: no pair of consecutive samples with finite states and inputs")
            k = np.flatnonzero(keep)
            parts.append((z[k], u[k], z[k + 1], t[k + 1] - t[k], t[k] - t[0], np.full(len(k), i), k))
            inputs.append(_held(u))
            run_dt.append(float(np.median(np.diff(t))))
            blur.append(tuple(chains[0]) if chains and chains[0] else ())
        return cls(*(np.concatenate(a) for a in zip(*parts)), inputs=tuple(inputs), run_dt=tuple(run_dt),
                   blur=tuple(blur))

    def subset(self, mask: np.ndarray) -> "Pairs":
        return Pairs(self.x[mask], self.u[mask], self.x_next[mask], self.dt[mask], self.t[mask],
                     self.segment[mask], None if self.k is None else self.k[mask], self.inputs, self.run_dt,
                     self.blur)

    def filtered(self, system: System, effects: Sequence[Effect], thetas: Sequence[float],
                 derivatives: bool = False) -> tuple[np.ndarray, list[np.ndarray]]:
        """The inputs ``(N, nu)`` through the ``filter:<u>`` ``effects``, and with ``derivatives``
        each filter's ``d u_j / d theta`` ``(N,)`` (forward differences: the delay is piecewise
        linear in its parameter, the lag smooth)."""
        if not effects:
            return self.u, []
        if self.k is None or not self.inputs:
            raise ShapeError("filter effects need pairs built with Pairs.from_states (input sequences)")
        thetas = [float(v) for v in thetas]
        u = self.u.copy()
        du = [np.zeros(len(self)) for _ in effects]
        for s, (seq, dt) in enumerate(zip(self.inputs, self.run_dt)):
            rows = self.segment == s
            if not rows.any():
                continue
            base = filter_inputs(system, effects, thetas, seq, dt)
            u[rows] = base[self.k[rows]]
            for q, e in enumerate(effects if derivatives else ()):
                h = 1e-6 * dt
                up = filter_inputs(system, effects, [v + h if i == q else v for i, v in enumerate(thetas)],
                                   seq, dt)
                j = system.input_names.index(e.channel.split(":", 1)[1])
                du[q][rows] = (up[self.k[rows], j] - base[self.k[rows], j]) / h
        return u, du


def _held(u: np.ndarray) -> np.ndarray:
    """``u`` with non-finite cells holding the last finite value (the first one before it)."""
    u = np.array(u, dtype=float, copy=True)
    for j in range(u.shape[1]):
        col = u[:, j]
        ok = np.isfinite(col)
        if ok.all() or not ok.any():
            continue
        idx = np.where(ok, np.arange(len(col)), 0)
        np.maximum.accumulate(idx, out=idx)
        idx[:int(np.argmax(ok))] = int(np.argmax(ok))
        u[:, j] = col[idx]
    return u


_STEPS: dict = {}


def _step_function(system: System, effects: Sequence[Effect], features: bool, by_input: bool):
    """The RK4 step of the prior plus ``effects`` (parameters symbolic) and its Jacobians, cached."""
    # keyed by identity: two effects of one name may differ (a Coulomb smoothing or a saturation
    # level set from the data), and the cache holds the objects so that no id is reused
    key = (id(system), tuple(id(e) for e in effects), features, by_input)
    hit = _STEPS.get(key)
    if hit is not None and hit[0] is system and all(a is b for a, b in zip(hit[1], effects)):
        return hit[2]
    m, nx = len(effects), system.nx
    x, u = cs.SX.sym("x", nx), cs.SX.sym("u", system.nu)
    dt, th = cs.SX.sym("dt"), cs.SX.sym("theta", max(m, 1))
    fn = corrected_dynamics(system, effects, [th[i] for i in range(m)])
    f = lambda xx, uu: cs.vertcat(*fn(CasadiOps, [xx[i] for i in range(nx)],  # noqa: E731
                                      [uu[j] for j in range(system.nu)], system.params))
    x_next = rk4_step(f, x, u, dt)
    outs = [x_next]
    if features:
        outs.append(cs.reshape(cs.jacobian(x_next, th)[:, :m], nx * m, 1))
        if by_input:
            outs.append(cs.reshape(cs.jacobian(x_next, u), nx * system.nu, 1))
    step = cs.Function("step", [x, u, dt, th], outs)
    if len(_STEPS) > 64:
        _STEPS.clear()
    _STEPS[key] = (system, tuple(effects), step)
    return step


def one_step(system: System, effects: Sequence[Effect], theta: Sequence[float], pairs: Pairs,
             with_features: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Residual ``r (N, nx)`` [state unit / s] and features ``Phi (N, nx, m)`` at ``theta``."""
    effects, theta = list(effects), np.asarray(theta, float).reshape(-1)
    m, nx, N = len(effects), system.nx, len(pairs)
    flt = [i for i, e in enumerate(effects) if e.is_filter]
    dyn = [i for i in range(m) if i not in flt]
    u, du = pairs.filtered(system, [effects[i] for i in flt], theta[flt], with_features)
    step = _step_function(system, [effects[i] for i in dyn], with_features, bool(flt))
    theta_col = np.zeros((max(len(dyn), 1), 1))
    theta_col[:len(dyn), 0] = theta[dyn]
    res = step.map(N)(pairs.x.T, u.T, pairs.dt[None, :], np.repeat(theta_col, N, axis=1))
    res = res if isinstance(res, (list, tuple)) else [res]
    predicted = np.asarray(res[0]).T
    diff = pairs.x_next - predicted
    for name in system.periodic_states:
        i = system.state_names.index(name)
        diff[:, i] = np.angle(np.exp(1j * diff[:, i]))
    r = diff / pairs.dt[:, None]
    if not with_features:
        return matched(pairs, r)[0], np.zeros((N, nx, 0))
    J = np.zeros((N, nx, m))
    J[:, :, dyn] = np.asarray(res[1]).T.reshape(N, len(dyn), nx).transpose(0, 2, 1)  # column-major
    if flt:
        Ju = np.asarray(res[2]).T.reshape(N, system.nu, nx).transpose(0, 2, 1)
        for q, i in enumerate(flt):
            j = system.input_names.index(effects[i].channel.split(":", 1)[1])
            J[:, :, i] = Ju[:, :, j] * du[q][:, None]
    return matched(pairs, r, J / pairs.dt[:, None, None])
