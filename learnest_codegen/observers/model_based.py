"""Model-based observers: a FilterPy UKF on the RK4 prior (``ukf``) and the EKF-RTS smoother
(``ekf_rts``, also through a hybrid model in the refinement rounds of training) with its
innovation likelihood."""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..data import Run
from ..integrators import rk4_step
from ..systems import System
from .base import Observations


def _model_ukf(run: Run, system: System) -> Observations:
    """Forward UKF on the RK4-discretised prior (for systems without kinematic chains); an
    output missing at a sample (NaN) is left out of its update."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter  # only this observer's

    step: Callable = lambda x, dt, u: rk4_step(lambda s, v: system.f(s, v), x, u, dt)  # noqa: E731
    points = MerweScaledSigmaPoints(system.nx, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(system.nx, system.ny, run.dt, lambda x: x, step, points)
    ukf.hx = lambda x, u: system.h(x, u)
    ukf.x = np.array(system.x0, dtype=float)
    ukf.P = np.diag(np.square(system.noise.initial_std))
    ukf.Q = np.diag(np.square(system.noise.process_std))
    ukf.R = np.diag(np.square(system.noise.measurement_std))
    zeta, var = np.empty((len(run), system.nx)), np.empty((len(run), system.nx))
    present = np.isfinite(run.y)
    for k in range(len(run)):
        if k:
            ukf.predict(dt=run.t[k] - run.t[k - 1], u=run.u[k - 1])
        u = run.u[k - 1] if k else run.u[0]  # same convention as estimators
        rows = np.flatnonzero(present[k])
        if len(rows) == system.ny:
            ukf.update(run.y[k], u=u)
        elif len(rows):  # update with the outputs present only
            ukf.update(run.y[k, rows], R=ukf.R[np.ix_(rows, rows)],
                       hx=lambda x, u, rows=rows: system.h(x, u)[rows], u=u)
        zeta[k], var[k] = ukf.x, np.diag(ukf.P)
    return Observations(zeta, var, "ukf", {})


def ekf_rts(run: Run, system: System, residual: Callable | None = None,
            q_scales: np.ndarray = np.logspace(-1, 3, 9)) -> Observations:
    """EKF + RTS smoother through ``RK4(f_prior + residual)``; Q's scale chosen by likelihood.

    ``residual(x_sx, u_sx) -> SX`` adds a learned term (a net's CasADi form) to the prior.
    """
    passes, A = _ekf_passes(run, system, residual, q_scales)
    scale = max(passes, key=lambda s: passes[s][-1])
    xs, Ps, xps, Pps, _ = passes[scale]
    zeta, covs = _rts_backward(xs, Ps, xps, Pps, A, run.u)
    return Observations(zeta, np.diagonal(covs, axis1=1, axis2=2).copy(), "ekf_rts",
                        {"q_scale": scale, "refined": residual is not None})


def innovation_loglik(run: Run, system: System, residual: Callable | None = None,
                      q_scales: tuple[float, ...] = (0.1, 1.0, 10.0, 100.0)) -> float:
    """Log-likelihood of the run's measurements under ``RK4(f_prior + residual)``.

    The EKF's innovation log-likelihood, maximised over the process-noise scale as
    :func:`ekf_rts` chooses it. It scores a model by its measurements alone, so it compares
    models whose training states differ; :func:`~learnest_codegen.learning.training.train_on_run` uses
    it to choose between restarts.
    """
    with np.errstate(all="ignore"):
        passes, _ = _ekf_passes(run, system, residual, q_scales)
    scores = [p[-1] for p in passes.values() if np.isfinite(p[-1])]
    return max(scores) if scores else -np.inf


def _ekf_passes(run: Run, system: System, residual, q_scales):
    """Forward EKF passes through ``RK4(f_prior + residual)``, one per process-noise scale
    (``{scale: (xs, Ps, xps, Pps, loglik)}``), and the step's state Jacobian ``A``."""
    F, A = _discrete_with_jacobian(system, residual, run.dt)
    R = np.diag(np.square(system.noise.measurement_std))
    q0 = np.square(system.noise.process_std)
    x0 = run.x[0] if run.x is not None else np.asarray(system.x0, float)
    update, step = _ekf_functions(system, F, A, len(run))
    return {float(s): _ekf_forward(run, system, update, step, np.diag(q0 * s), R, x0)
            for s in q_scales}, A


def _discrete_with_jacobian(system: System, residual, dt: float):
    import casadi as cs

    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    f = lambda s, v: system.f(s, v) + (residual(s, v) if residual else 0)  # noqa: E731
    xn = rk4_step(f, x, u, dt)
    F = cs.Function("F", [x, u], [xn])
    A = cs.Function("A", [x, u], [cs.jacobian(xn, x)])
    return F, A


def _ekf_functions(system: System, F, A, T: int):
    """The EKF's measurement update and its whole forward recursion as CasADi functions.

    ``update(x, P, u, y, R) -> (x, P, loglik)`` linearises the measurement with CasADi.
    ``step`` is the predict-then-update step accumulated over the run's ``T - 1`` steps
    (``mapaccum``): the recursion runs in CasADi's virtual machine, not step by step in
    Python (about two orders of magnitude faster on the cartpole's 5000 steps).
    """
    import casadi as cs

    n, nu, ny = system.nx, system.nu, len(system.noise.measurement_std)
    x, u, u_prev = cs.SX.sym("x", n), cs.SX.sym("u", nu), cs.SX.sym("u_prev", nu)
    y, P = cs.SX.sym("y", ny), cs.SX.sym("P", n, n)
    R, q = cs.SX.sym("R", ny, ny), cs.SX.sym("q", n)  # q: the diagonal of Q
    present = cs.SX.sym("present", ny)  # 1: the output was measured; 0: missing (y holds 0)
    # a missing output: its row of H and its innovation are zero and its variance 1 / (2 pi),
    # so it moves nothing and adds nothing to the likelihood (R is diagonal)
    H = cs.diag(present) @ cs.jacobian(system.h(x, u), x)
    innov = present * (y - system.h(x, u))
    S = H @ P @ H.T + cs.diag(present) @ R @ cs.diag(present) + cs.diag(1 - present) / (2 * np.pi)
    K = cs.solve(S, H @ P).T
    loglik = -0.5 * (innov.T @ cs.solve(S, innov) + cs.log(cs.det(2 * np.pi * S)))
    update = cs.Function("update", [x, P, u, y, R, present],
                         [x + K @ innov, (cs.SX.eye(n) - K @ H) @ P, loglik])
    Ak = A(x, u_prev)
    xp, Pp = F(x, u_prev), Ak @ P @ Ak.T + cs.diag(q)
    xu, Pu, ll = update(xp, Pp, u, y, R, present)
    acc = cs.SX.sym("loglik")
    # accumulated: x, vec(P), loglik; per step also the predictions (x, vec(P))
    step = cs.Function("ekf_step", [x, cs.vec(P), acc, u_prev, u, y, R, q, present],
                       [xu, cs.vec(Pu), acc + ll, xp, cs.vec(Pp)])
    return update, step.mapaccum("ekf", max(T - 1, 1), 3) if T > 1 else None


def _ekf_forward(run: Run, system: System, update, step, Q, R, x0):
    """Forward EKF; the measurement is linearised by CasADi too. Returns the log-likelihood."""
    T, n = len(run), system.nx
    P0 = np.diag(np.square(system.noise.initial_std))
    present = np.isfinite(run.y)
    y = np.where(present, run.y, 0.0)
    present = present.astype(float)
    x, P, ll = (v.full() for v in update(np.asarray(x0, float), P0, run.u[0], y[0], R, present[0]))
    xs, Ps, xps, Pps = (np.empty((T, n)), np.empty((T, n, n)), np.empty((T, n)), np.empty((T, n, n)))
    xs[0], Ps[0], xps[0], Pps[0] = x.ravel(), P, x0, P0
    if T > 1:
        out = step(x, P.reshape(-1, order="F"), ll, run.u[:-1].T, run.u[1:].T, y[1:].T, R,
                   np.diag(Q), present[1:].T)
        xs_, Ps_, ll, xps_, Pps_ = (v.full() for v in out)
        xs[1:], xps[1:] = xs_.T, xps_.T
        Ps[1:] = Ps_.T.reshape(T - 1, n, n).transpose(0, 2, 1)  # column-major vec per step
        Pps[1:] = Pps_.T.reshape(T - 1, n, n).transpose(0, 2, 1)
        ll = ll[:, -1]  # the accumulated value after the last step
    return xs, Ps, xps, Pps, float(np.ravel(ll)[-1])


def _rts_backward(xs, Ps, xps, Pps, A, U):
    """Rauch-Tung-Striebel pass over an extended Kalman filter's estimates (one CasADi
    ``mapaccum`` over the run, backwards)."""
    import casadi as cs

    T, n = xs.shape
    zeta, covs = xs.copy(), Ps.copy()
    if T < 2:
        return zeta, covs
    nu = U.shape[1]
    z_next, C_next = cs.SX.sym("z_next", n), cs.SX.sym("C_next", n, n)
    x, P, xp, Pp, u = (cs.SX.sym("x", n), cs.SX.sym("P", n, n), cs.SX.sym("xp", n),
                       cs.SX.sym("Pp", n, n), cs.SX.sym("u", nu))
    G = cs.solve(Pp, A(x, u) @ P).T
    z, C = x + G @ (z_next - xp), P + G @ (C_next - Pp) @ G.T
    back = cs.Function("rts_step", [z_next, cs.vec(C_next), x, cs.vec(P), xp, cs.vec(Pp), u],
                       [z, cs.vec(C)]).mapaccum("rts", T - 1, 2)
    vec = lambda M: M.transpose(0, 2, 1).reshape(len(M), -1).T  # noqa: E731  column-major vecs
    rev = slice(None, None, -1)  # steps k = T-2 ... 0
    zs, Cs = back(xs[-1], Ps[-1].reshape(-1, order="F"), xs[:-1][rev].T, vec(Ps[:-1][rev]),
                  xps[1:][rev].T, vec(Pps[1:][rev]), U[:T - 1][rev].T)
    zeta[:-1] = zs.full().T[rev]
    covs[:-1] = Cs.full().T.reshape(T - 1, n, n).transpose(0, 2, 1)[rev]
    return zeta, covs
