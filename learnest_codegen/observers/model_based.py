"""Model-based observers: a FilterPy UKF on the RK4 prior (``ukf``) and the EKF-RTS smoother
(``ekf_rts``, also through a hybrid model in the refinement rounds of training) with its
innovation likelihood."""

from __future__ import annotations

from typing import Callable

import numpy as np

from ..data import Run
from ..integrators import rk4_step, rk4_step_jacobian
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
    """EKF + RTS smoother through ``RK4(f_prior + residual)``; Q's scale chosen by likelihood
    (every scale's filter keeps its likelihood alone, the chosen one's runs again for the
    estimates the smoother needs).

    ``residual(x_sx, u_sx) -> SX`` adds a learned term (a net's CasADi form) to the prior.
    """
    scores, stage = _ekf_passes(run, system, residual, q_scales, states=False)
    scale = max(scores, key=lambda s: scores[s][-1])
    xs, Ps, xps, Pps, _ = _ekf_passes(run, system, residual, (scale,), stage=stage)[0][scale]
    zeta, covs = _rts_backward(xs, Ps, xps, Pps, stage, run.u)
    return Observations(zeta, np.diagonal(covs, axis1=1, axis2=2).copy(), "ekf_rts",
                        {"q_scale": scale, "refined": residual is not None})


def innovation_loglik(run: Run, system: System, residual: Callable | None = None,
                      q_scales: tuple[float, ...] = (0.1, 1.0, 10.0, 100.0)) -> float:
    """Log-likelihood of the run's measurements under ``RK4(f_prior + residual)``.

    The EKF's innovation log-likelihood, maximised over the process-noise scale as
    :func:`ekf_rts` chooses it. It scores a model by its measurements alone, so it compares
    models whose training states differ; :func:`~learnest_codegen.learning.training.train_on_run` uses
    it to choose between restarts. The filter keeps only the likelihood (no estimates).
    """
    with np.errstate(all="ignore"):
        passes, _ = _ekf_passes(run, system, residual, q_scales, states=False)
    scores = [p[-1] for p in passes.values() if np.isfinite(p[-1])]
    return max(scores) if scores else -np.inf


def _ekf_passes(run: Run, system: System, residual, q_scales, states: bool = True, stage=None):
    """Forward EKF passes through ``RK4(f_prior + residual)``, one per process-noise scale
    (``{scale: (xs, Ps, xps, Pps, loglik)}``), and ``stage``, the step with its state Jacobian
    (:func:`_discrete_with_jacobian`; built unless given). Without ``states`` each pass keeps
    the log-likelihood alone (``(None, None, None, None, loglik)``: a ``fold`` of the recursion,
    no estimates stored or converted)."""
    stage = stage or _discrete_with_jacobian(system, residual, run.dt)
    R = np.diag(np.square(system.noise.measurement_std))
    q0 = np.square(system.noise.process_std)
    x0 = run.x[0] if run.x is not None else np.asarray(system.x0, float)
    update, step = _ekf_functions(system, stage, len(run), states)
    return {float(s): _ekf_forward(run, system, update, step, np.diag(q0 * s), R, x0)
            for s in q_scales}, stage


def _discrete_with_jacobian(system: System, residual, dt: float):
    """``stage(x, u) -> (F, A)``: one RK4 step of ``f_prior + residual`` and its state Jacobian
    ``A = dF/dx``, by the chain rule through the RK4 stages
    (:func:`~learnest_codegen.integrators.rk4_step_jacobian`, as the embedded MHE's model), the
    two sharing their common subexpressions (``cs.cse``). The EKF evaluates both at every
    sample: on the KNODE cartpole they take 2700 operations where the step and CasADi's AD of
    the whole step took 5200 (the same values to rounding)."""
    import casadi as cs

    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    xdot = system.f(x, u) + (residual(x, u) if residual else 0)
    f_jac = cs.Function("f_jac", [x, u], [xdot, cs.jacobian(xdot, x)])
    F, A = rk4_step_jacobian(f_jac, x, u, dt, cs.SX.eye(system.nx))
    n = system.nx
    both = cs.cse(cs.vertcat(F, cs.vec(cs.densify(A))))
    return cs.Function("stage", [x, u], [both[:n], cs.reshape(both[n:], n, n)], ["x", "u"], ["F", "A"])


def _ekf_functions(system: System, stage, T: int, states: bool = True):
    """The EKF's measurement update and its whole forward recursion as CasADi functions.

    ``update(x, P, u, y, R) -> (x, P, loglik)`` linearises the measurement with CasADi.
    ``step`` is the predict-then-update step accumulated over the run's ``T - 1`` steps
    (``mapaccum``): the recursion runs in CasADi's virtual machine, not step by step in
    Python (about two orders of magnitude faster on the cartpole's 5000 steps). Without
    ``states``, ``step`` returns the filter's final state and likelihood alone (``fold``).
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
    xp, Ak = stage(x, u_prev)
    Pp = Ak @ P @ Ak.T + cs.diag(q)
    xu, Pu, ll = update(xp, Pp, u, y, R, present)
    acc = cs.SX.sym("loglik")
    # accumulated: x, vec(P), loglik; per step also the predictions (x, vec(P))
    inputs = [x, cs.vec(P), acc, u_prev, u, y, R, q, present]
    if T < 2:
        return update, None
    if not states:  # one accumulated vector [x; vec(P); loglik], folded to its final value
        z = cs.vertcat(x, cs.vec(P), acc)
        packed = cs.Function("ekf_step", [z, *inputs[3:]], [cs.substitute(
            cs.vertcat(xu, cs.vec(Pu), acc + ll), cs.vertcat(*inputs[:3]), z)])
        return update, packed.fold(T - 1)
    step = cs.Function("ekf_step", inputs, [xu, cs.vec(Pu), acc + ll, xp, cs.vec(Pp)])
    return update, step.mapaccum("ekf", T - 1, 3)


def _ekf_forward(run: Run, system: System, update, step, Q, R, x0):
    """Forward EKF; the measurement is linearised by CasADi too. Returns the filtered and
    predicted states and covariances and the log-likelihood; with a ``fold`` step (see
    :func:`_ekf_functions`) the log-likelihood alone, as ``(None, None, None, None, loglik)``."""
    T, n = len(run), system.nx
    P0 = np.diag(np.square(system.noise.initial_std))
    present = np.isfinite(run.y)
    y = np.where(present, run.y, 0.0)
    present = present.astype(float)
    x, P, ll = (v.full() for v in update(np.asarray(x0, float), P0, run.u[0], y[0], R, present[0]))
    if T < 2:
        return x.T, P[None], np.asarray(x0, float)[None], P0[None], float(ll[0, 0])
    inputs = (run.u[:-1].T, run.u[1:].T, y[1:].T, R, np.diag(Q), present[1:].T)
    if step.n_out() == 1:  # fold: the likelihood accumulated after the last step
        final = step(np.concatenate([x.ravel(), P.ravel(order="F"), ll.ravel()]), *inputs)
        return None, None, None, None, float(final[-1])
    xs_, Ps_, ll, xps_, Pps_ = (v.full() for v in step(x, P.reshape(-1, order="F"), ll, *inputs))
    xs, Ps, xps, Pps = (np.empty((T, n)), np.empty((T, n, n)), np.empty((T, n)), np.empty((T, n, n)))
    xs[0], Ps[0], xps[0], Pps[0] = x.ravel(), P, x0, P0
    xs[1:], xps[1:] = xs_.T, xps_.T
    Ps[1:] = Ps_.T.reshape(T - 1, n, n).transpose(0, 2, 1)  # column-major vec per step
    Pps[1:] = Pps_.T.reshape(T - 1, n, n).transpose(0, 2, 1)
    return xs, Ps, xps, Pps, float(ll[0, -1])  # the accumulated value after the last step


def _rts_backward(xs, Ps, xps, Pps, stage, U):
    """Rauch-Tung-Striebel pass over an extended Kalman filter's estimates (one CasADi
    ``mapaccum`` over the run, backwards); ``stage(x, u) -> (F, A)`` as
    :func:`_discrete_with_jacobian`'s."""
    import casadi as cs

    T, n = xs.shape
    zeta, covs = xs.copy(), Ps.copy()
    if T < 2:
        return zeta, covs
    nu = U.shape[1]
    z_next, C_next = cs.SX.sym("z_next", n), cs.SX.sym("C_next", n, n)
    x, P, xp, Pp, u = (cs.SX.sym("x", n), cs.SX.sym("P", n, n), cs.SX.sym("xp", n),
                       cs.SX.sym("Pp", n, n), cs.SX.sym("u", nu))
    G = cs.solve(Pp, stage(x, u)[1] @ P).T
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
