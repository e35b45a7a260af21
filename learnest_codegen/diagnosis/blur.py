"""The one-step residual seen through the observer: the model's prediction blurred as the data are.

With state observations from a kinematic smoother (observers ``rts`` and ``kf``), the observed
velocity is the true one low-passed by the smoother: a torque step becomes a ramp over several
samples. The plain one-step residual compares that blurred increment ``z_{k+1} - z_k`` with the
model's sharp prediction, so every step of the input leaves a residual that no effect of the
library can explain, and an input delay and an input advance of half a sample fit it equally
well (the smoother's blur is symmetric in time): a sub-sample delay is lost in the blur, and a
blur is fitted as a delay. On a torque-limited swing-up sampled at 6 ms the blur's residual is
several times the residual of the true model seen the same way.

The smoother is linear in its measurements once its intensity is fixed (the one the observer
chose on the run), so the model's predicted increments can be passed through the same filter:
the increments of a chain's last state, integrated up the chain (held over each step, exactly),
measured as the run's outputs measure the chain, and smoothed. The residual is then

    r_k = (z_{k+1} - z_k - S(d)_k) / dt,   d_k = RK4(z_k, u_k) - z_k   (the chain's last state)

and a feature ``Phi`` becomes ``S(Phi)``. ``S`` is linear with zero initial state, so ``S`` of the
true increments is the observed increment up to the measurement noise and ``S`` never adds any:
the true model leaves the smoothed noise only, and a delay moves the prediction's blur as it
moves the data's. Other rows (a chain's lower states, states in no chain) keep the plain residual.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import expm

from ..systems import System

#: the observers whose output is a linear smoother of the measurements, per kinematic chain
LINEAR_OBSERVERS = {"rts": True, "kf": False}


@dataclass(frozen=True)
class ChainBlur:
    """One chain's linear smoother with its intensity fixed: the residual state it ends in
    (``state``), the filter's transition ``F`` and measurement ``H``, per-sample gains
    ``gain (T, n, m)`` and RTS gains ``back (T - 1, n, n)`` (``None`` for the causal ``kf``), and
    the exact one-step integration of the chain, ``lift (L, L)`` and ``push (L,)``."""

    state: int
    F: np.ndarray
    H: np.ndarray
    gain: np.ndarray
    back: np.ndarray | None
    lift: np.ndarray
    push: np.ndarray
    filters: dict = field(default_factory=dict, compare=False, repr=False)  # A's key -> transfer functions

    def apply(self, increments: np.ndarray) -> np.ndarray:
        """``(T - 1, B)`` increments of the chain's last state, one per step -> the increments of
        the smoothed last state when the chain moves by them (zero initial state)."""
        T, B, chain = len(self.gain), increments.shape[1], len(self.push)
        F, H, n = self.F, self.H, self.F.shape[0]
        y = np.zeros((T, B, H.shape[0]))  # the chain integrated exactly, its last state's slope held
        y[1:] = self._recursion("lift", self.lift, increments[:, :, None] * self.push[None, None, :]) \
            @ H[:, :chain].T
        k0 = self.steady_from
        x, means = np.zeros((B, n)), np.empty((T, B, n))
        for k in range(k0):  # predict, then update (the observer's order), while the gain settles
            x = x @ F.T
            x = x + (y[k] - x @ H.T) @ self.gain[k].T
            means[k] = x
        if k0 < T:  # then a fixed linear recursion: x_k = A x_{k-1} + K y_k
            K = self.gain[-1]
            w = y[k0:] @ K.T
            w[0] += x @ (F - K @ H @ F).T
            means[k0:] = self._recursion("forward", F - K @ H @ F, w)
        if self.back is not None:
            G = self.back[-1]
            tail = means[max(k0, 1) - 1:]  # m_k = G m_{k+1} + (I - G F) x_k, run backwards in time
            w = tail[::-1] @ (np.eye(n) - G @ F).T
            w[0] = tail[-1]
            means[max(k0, 1) - 1:] = self._recursion("back", G, w)[::-1]
            for k in range(max(k0, 1) - 2, -1, -1):
                means[k] = means[k] + (means[k + 1] - means[k] @ F.T) @ self.back[k].T
        return np.diff(means[:, :, chain - 1], axis=0)

    def _recursion(self, key: str, A: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``x_k = A x_{k-1} + w_k`` from ``x_{-1} = 0`` over the first axis of ``w (T, B, n)``, as
        ``n`` x ``n`` linear filters (``scipy.signal.lfilter``, transfer functions kept per ``key``)
        instead of a loop over time."""
        from scipy.signal import lfilter, ss2tf

        n = A.shape[0]
        if key not in self.filters:  # x = (I - A z^-1)^-1 w: state x_{k-1}, output A x_{k-1} + w_k
            self.filters[key] = [ss2tf(A, np.eye(n)[:, [j]], A, np.eye(n)[:, [j]]) for j in range(n)]
        columns = np.ascontiguousarray(np.moveaxis(w, 0, -1))  # (B, n, T): time last and contiguous
        out = np.zeros(columns.shape)
        for j, (num, den) in enumerate(self.filters[key]):
            for i in range(n):
                if np.any(num[i]):
                    out[:, i] += lfilter(num[i], den, columns[:, j], axis=-1)
        return np.moveaxis(out, -1, 0)

    @property
    def steady_from(self) -> int:
        """The first sample from which the filter's and the smoother's gains no longer change."""
        def changing(g):
            return np.any(np.abs(g - g[-1]) > 1e-12 * np.abs(g[-1]).max(), axis=(1, 2))

        moving = changing(self.gain)
        if self.back is not None:
            moving[:-1] |= changing(self.back)
        return int(np.flatnonzero(moving)[-1]) + 1 if moving.any() else 0


def chain_blur(state: int, T: int, dt: float, chain: int, rows: tuple[int, ...], q: float,
               r: np.ndarray, smooth: bool) -> ChainBlur:
    """The smoother of a chain of ``chain`` states measured at the derivative orders ``rows``
    (variances ``r``), white-noise intensity ``q``, over ``T`` samples ``dt`` apart: the gains the
    observer ran with (:func:`~learnest_codegen.observers.kinematic.chain_passes`; they do not
    depend on the measurements' values)."""
    from ..observers.kalman import rts_smoother  # noqa: F401 - the same model as the observer's
    from ..observers.kinematic import chain_passes

    order = chain + 1
    passes, model = chain_passes(np.zeros((T, len(rows))), dt, order, [q], np.asarray(r, float), rows)
    H, R = model.H, model.R[0]
    Pp, P = passes.covs_p[:, 0], passes.covs[:, 0]
    S = H[None] @ Pp @ H.T[None] + R[None]
    gain = Pp @ H.T[None] @ np.linalg.inv(S)
    back = None
    if smooth:
        back = np.swapaxes(np.linalg.solve(np.swapaxes(Pp[1:], -1, -2),
                                           model.F @ np.swapaxes(P[:-1], -1, -2)), -1, -2)
    M = expm(np.diag(np.full(chain, dt), 1))  # the chain plus its last state's slope, held
    return ChainBlur(state, model.F, H, gain, back, M[:chain, :chain], M[:chain, chain] / dt)


def run_blur(system: System, T: int, dt: float, method: str, info: dict) -> tuple[ChainBlur, ...]:
    """The chains of a run observed by the linear smoother ``method`` (``info``: the observer's,
    with each chain's chosen intensity) whose last state is a residual state; ``()`` for any
    other observer."""
    if method not in LINEAR_OBSERVERS:
        return ()
    from ..observers.kinematic import chain_groups, kinematic_chains

    out = []
    std = np.asarray(system.noise.measurement_std, float)
    for chain, measured in chain_groups(system, kinematic_chains(system)):
        last = chain.states[-1]
        entry = info.get(chain.output)
        if last not in system.residual_state_names or not entry:
            continue
        rows = tuple(k for _, k in measured)
        r = np.square(std[[o for o, _ in measured]])
        out.append(chain_blur(system.state_names.index(last), T, dt, len(chain.states), rows,
                              float(entry["jerk_spectral_density"]), r, LINEAR_OBSERVERS[method]))
    return tuple(out)


def matched(pairs, r: np.ndarray, J: np.ndarray | None = None):
    """The residual ``r (N, nx)`` and features ``J (N, nx, m)`` of ``pairs`` with each blurred run's
    chains seen through its smoother (see the module docstring); unchanged elsewhere. A run whose
    pairs are not all consecutive (missing states) keeps the plain residual."""
    if not any(pairs.blur):
        return r, J
    r = r.copy()
    J = None if J is None else J.copy()
    for s, chains in enumerate(pairs.blur):
        rows = np.flatnonzero(pairs.segment == s)
        complete = len(rows) == len(chains[0].gain) - 1 if chains else False
        if not complete or np.any(pairs.k[rows] != np.arange(len(rows))):
            continue
        dt = pairs.dt[rows]
        for c in chains:
            i = c.state
            seen = pairs.x_next[rows, i] - pairs.x[rows, i]
            predicted = seen - r[rows, i] * dt
            cols = [predicted[:, None]] + ([] if J is None else [J[rows, i, :] * dt[:, None]])
            out = c.apply(np.concatenate(cols, axis=1))
            r[rows, i] = (seen - out[:, 0]) / dt
            if J is not None:
                J[rows, i, :] = out[:, 1:] / dt[:, None]
    return r, J
