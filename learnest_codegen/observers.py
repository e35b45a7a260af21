"""Pre-training observers: measurements and inputs to state observations ``zeta`` (Alg. 1, step 1).

* ``kf``  - the paper's observer for the cartpole: one linear Kalman filter per kinematic chain
  (a measured position and its derivatives, see :class:`~learnest_codegen.systems.KinematicChain`)
  with a constant-acceleration model. It needs no dynamics model, so it does not bake the
  prior's error into the training targets.
* ``rts`` - the same filter followed by the Rauch-Tung-Striebel backward pass (a smoother: each
  ``zeta_i`` uses the whole run, not only the past), through FilterPy.
* ``ukf`` - for systems without kinematic chains: a FilterPy UKF on the RK4-discretised prior.
* ``ekf_rts`` - an extended Kalman filter on the RK4-discretised model plus an RTS backward pass.
  With the prior model its accelerations come from physics plus the data, not from a
  kinematic random walk; with a hybrid model (``residual``) it refines the training targets in
  :func:`~learnest_codegen.training.train_on_run`'s alternating scheme.
* ``linear_rts`` - for a prior that is linear (``f = A x``, ``h = C x``, no input): the exact
  Kalman filter and RTS smoother of that model, with white noise driving the derivatives of
  ``system.residual_state_names`` (for the quadrotor: white jerk) and every output used (the
  quadrotor's accelerometer as well as its position). Intensities by maximum likelihood.
* ``ukf_kf`` - the paper's observer for the ground robot, for systems that declare
  ``extra={"planar_pose": (x, y, v, psi)}``: a precursory UKF on a kinematic model extracts the
  position and heading through the system's own ``h``, then a linear constant-acceleration KF
  extracts the speed from those positions. Causal filters only.
* ``ukf_rts`` - the same with an RTS backward pass after each stage (the ground robot's default).

The white-jerk intensity of the kinematic filters is chosen per chain by maximising the
innovation log-likelihood over a log grid, so no tuning is needed for a new system.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter
from scipy.linalg import expm

from .data import Run
from .errors import UnknownNameError
from .integrators import rk4_step
from .systems import KinematicChain, System

JERK_GRID = np.logspace(-2, 8, 21)  # white-jerk spectral densities tried [unit^2 / s^5]


@dataclass(frozen=True)
class Observations:
    """State observations for training.

    Attributes
    ----------
    zeta : (T, nx) state observations.
    variance : (T, nx) their marginal variances, as the observer believes them.
    method : which observer produced them.
    info : per-observer details (e.g. the chosen jerk intensities).
    """

    zeta: np.ndarray
    variance: np.ndarray
    method: str
    info: dict


def observe(run: Run, system: System, method: str | None = None) -> Observations:
    """Turn a run's ``(y, u)`` into state observations with the named observer.

    ``method`` defaults to the system's ``default_observer``.
    """
    method = method or system.default_observer
    if method not in OBSERVERS:
        raise UnknownNameError(f"unknown observer {method!r}; choose from {sorted(OBSERVERS)}")
    return OBSERVERS[method](run, system)


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


def _model_ukf(run: Run, system: System) -> Observations:
    """Forward UKF on the RK4-discretised prior (for systems without kinematic chains)."""
    step: Callable = lambda x, dt, u: rk4_step(lambda s, v: system.f(s, v), x, u, dt)  # noqa: E731
    points = MerweScaledSigmaPoints(system.nx, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(system.nx, system.ny, run.dt, lambda x: x, step, points)
    ukf.hx = lambda x, u: system.h(x, u)
    ukf.x = np.array(system.x0, dtype=float)
    ukf.P = np.diag(np.square(system.noise.initial_std))
    ukf.Q = np.diag(np.square(system.noise.process_std))
    ukf.R = np.diag(np.square(system.noise.measurement_std))
    zeta, var = np.empty((len(run), system.nx)), np.empty((len(run), system.nx))
    for k in range(len(run)):
        if k:
            ukf.predict(dt=run.t[k] - run.t[k - 1], u=run.u[k - 1])
        ukf.update(run.y[k], u=run.u[k - 1] if k else run.u[0])  # same convention as estimators
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
    models whose training states differ; :func:`~learnest_codegen.training.train_on_run` uses
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
    H = cs.jacobian(system.h(x, u), x)
    innov = y - system.h(x, u)
    S = H @ P @ H.T + R
    K = cs.solve(S, H @ P).T
    loglik = -0.5 * (innov.T @ cs.solve(S, innov) + cs.log(cs.det(2 * np.pi * S)))
    update = cs.Function("update", [x, P, u, y, R], [x + K @ innov, (cs.SX.eye(n) - K @ H) @ P, loglik])
    Ak = A(x, u_prev)
    xp, Pp = F(x, u_prev), Ak @ P @ Ak.T + cs.diag(q)
    xu, Pu, ll = update(xp, Pp, u, y, R)
    acc = cs.SX.sym("loglik")
    # accumulated: x, vec(P), loglik; per step also the predictions (x, vec(P))
    step = cs.Function("ekf_step", [x, cs.vec(P), acc, u_prev, u, y, R, q],
                       [xu, cs.vec(Pu), acc + ll, xp, cs.vec(Pp)])
    return update, step.mapaccum("ekf", max(T - 1, 1), 3) if T > 1 else None


def _ekf_forward(run: Run, system: System, update, step, Q, R, x0):
    """Forward EKF; the measurement is linearised by CasADi too. Returns the log-likelihood."""
    T, n = len(run), system.nx
    P0 = np.diag(np.square(system.noise.initial_std))
    x, P, ll = (v.full() for v in update(np.asarray(x0, float), P0, run.u[0], run.y[0], R))
    xs, Ps, xps, Pps = (np.empty((T, n)), np.empty((T, n, n)), np.empty((T, n)), np.empty((T, n, n)))
    xs[0], Ps[0], xps[0], Pps[0] = x.ravel(), P, x0, P0
    if T > 1:
        out = step(x, P.reshape(-1, order="F"), ll, run.u[:-1].T, run.u[1:].T, run.y[1:].T, R,
                   np.diag(Q))
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


# -- linear prior: the exact KF/RTS of f = A x, y = C x ----------------------------------------
LINEAR_BURN_IN = 10  # first innovations left out of the likelihood (diffuse start)


def linear_rts(run: Run, system: System, grid: np.ndarray = JERK_GRID) -> Observations:
    """Kalman filter + RTS smoother of a linear prior ``xdot = A x``, ``y = C x`` (all outputs).

    White noise of spectral density ``q_i`` drives the derivative of each residual state
    (``system.residual_state_names``: where the prior is least sure, and what the residual
    will learn), discretised exactly (Van Loan); each ``q_i`` is chosen on ``grid`` by
    maximising the innovation log-likelihood, one residual state after the other. Unlike the
    per-chain ``rts`` observer, which sees only a chain's measured coordinate, this uses every
    output: for the quadrotor the accelerometer fixes the acceleration that ``rts`` can only
    get from second differences of position. The filter starts diffuse (``x = 0``, ``P = 1e4
    I``), so no ``x0`` is assumed.

    Raises ``ValueError`` when ``f`` or ``h`` is not linear in ``x`` or depends on ``u``.
    """
    A, C = _linear_prior(system)
    R = np.diag(np.square(system.noise.measurement_std))
    rows = [system.state_names.index(n) for n in system.residual_state_names]
    q = dict.fromkeys(rows, float(np.sqrt(grid[0] * grid[-1])))
    for i in rows:
        q[i] = max(grid, key=lambda v: _linear_kf(run, A, C, R, {**q, i: float(v)})[2])
    means, covs, loglik, kf = _linear_kf(run, A, C, R, q)
    means, covs, _, _ = kf.rts_smoother(means[:, :, None], covs)
    info = {"spectral_density": {system.state_names[i]: float(v) for i, v in q.items()},
            "loglik": float(loglik)}
    return Observations(means[:, :, 0], np.diagonal(covs, axis1=1, axis2=2).copy(), "linear_rts", info)


def _linear_prior(system: System) -> tuple[np.ndarray, np.ndarray]:
    """``(A, C)`` of a prior ``f = A x``, ``h = C x``; ``ValueError`` if it is not of that form."""
    import casadi as cs

    x, u = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    out = []
    for what, expr in (("dynamics", system.f(x, u)), ("measurement", system.h(x, u))):
        J = cs.jacobian(expr, x)
        offset = cs.substitute(expr, x, cs.DM.zeros(system.nx))
        nonlinear = cs.depends_on(J, cs.vertcat(x, u)) or cs.depends_on(expr, u)
        if nonlinear or np.any(np.array(cs.DM(cs.evalf(offset))) != 0):
            raise ValueError(f"system {system.name!r}: observer 'linear_rts' needs a prior {what} "
                             "of the form M x (linear in x, no input, no offset); use 'ekf_rts'")
        out.append(np.array(cs.DM(cs.evalf(J))))
    return out[0], out[1]


def _linear_kf(run: Run, A: np.ndarray, C: np.ndarray, R: np.ndarray, q: dict[int, float]):
    """Forward KF with white noise ``q[i]`` on ``xdot_i``; returns means, covs, log-lik, filter."""
    n = len(A)
    van_loan = np.zeros((2 * n, 2 * n))  # exact discrete (F, Q) of dx = A x dt + dW
    van_loan[:n, :n], van_loan[n:, n:] = -A, A.T
    van_loan[list(q), [n + i for i in q]] = list(q.values())
    E = expm(van_loan * run.dt)
    kf = KalmanFilter(dim_x=n, dim_z=len(C))
    kf.F = E[n:, n:].T
    Q = kf.F @ E[:n, n:]
    kf.Q = 0.5 * (Q + Q.T)
    kf.H, kf.R = C, R
    kf.x, kf.P = np.zeros((n, 1)), np.eye(n) * 1e4
    means, covs, means_p, covs_p = kf.batch_filter(run.y[:, :, None])
    innov = run.y - np.einsum("ij,tj->ti", C, means_p[:, :, 0])
    S = np.einsum("ij,tjk,lk->til", C, covs_p, C) + R
    sl = slice(LINEAR_BURN_IN, None)
    white = np.linalg.solve(S[sl], innov[sl, :, None])[..., 0]
    loglik = -0.5 * float(np.sum(np.einsum("ti,ti->t", innov[sl], white)
                                 + np.linalg.slogdet(2 * np.pi * S[sl])[1]))
    return means[:, :, 0], covs, loglik, kf


# -- planar pose: the paper's two-stage observer for the ground robot ----------------------------
#
# Stage 1 is a UKF on a kinematic model in the world frame, state ``[x, y, vx, vy, psi, r]``: the
# position with a white-acceleration (random-walk) velocity and the heading with a random-walk
# turn rate ``r``. It measures through the system's own ``h`` (the state it hands to ``h`` has
# the speed ``|(vx, vy)|``), so it knows the sensors but nothing of the dynamics: no input and
# no drag, hence no prior model error, enters the training targets. Its two intensities are
# chosen by maximising the innovation log-likelihood, one coordinate at a time over a log grid.
# Stage 2 extracts the speed from the stage-1 positions: one constant-acceleration (white-jerk)
# linear KF per axis, jerk intensity (shared by both axes: the motion has no preferred world
# direction) again by maximum innovation likelihood. Its measurement variance is that of a
# single-sample position fix from the sensors, ``inv(J' R^-1 J)`` with ``J = dh/d(x, y)`` at the
# stage-1 estimate, not the stage-1 filter variance: the stage-1 errors are correlated in time,
# and treating them as white with their (small) filter variance overstates what each sample
# says, which makes the likelihood pick a far too large jerk intensity (on seed 1 of the ground
# robot: speed MSE 3e-3 instead of 3e-4 after smoothing). The speed is the norm of the (vx, vy)
# estimate, which is the bicycle's speed whatever the slip angle (the projection on the heading
# would be v cos(beta)).
PLANAR_POSE = "planar_pose"
ACCEL_GRID = np.logspace(-2, 3, 6)  # white-acceleration densities tried, stage 1 [m^2 / s^3]
TURN_GRID = np.logspace(-3, 2, 6)  # white angular-acceleration densities [rad^2 / s^3]
STAGE1_TUNING_SAMPLES = 1000  # the likelihood grid of stage 1 runs on the first samples only


def planar_pose_indices(system: System) -> tuple[int, int, int, int]:
    """Indices of the states ``(x, y, v, psi)`` named by ``system.extra["planar_pose"]``."""
    names = system.extra.get(PLANAR_POSE)
    if names is None:
        raise ValueError(f"system {system.name!r} declares no planar pose: the 'ukf_kf' and "
                         f"'ukf_rts' observers need extra={{'{PLANAR_POSE}': (x, y, v, psi)}} "
                         "naming its position, speed and heading states")
    names = tuple(names)
    unknown = [n for n in names if n not in system.state_names]
    if len(names) != 4 or unknown:
        raise ValueError(f"system {system.name!r}: extra['{PLANAR_POSE}'] must name 4 states "
                         f"(x, y, v, psi) among {system.state_names}, got {names}")
    if len(set(names)) != 4 or system.nx != 4:
        raise ValueError(f"system {system.name!r}: the planar-pose observers estimate exactly "
                         f"the 4 distinct states (x, y, v, psi); the system has {system.state_names}")
    return tuple(system.state_names.index(n) for n in names)


def _pose_to_state(system: System, pose: np.ndarray, indices=None) -> np.ndarray:
    """Stage-1 states ``[x, y, vx, vy, psi, r]`` ``(..., 6)`` as system states ``(..., nx)``."""
    ix, iy, iv, ipsi = indices or planar_pose_indices(system)
    x = np.empty((*pose.shape[:-1], system.nx))
    x[..., ix], x[..., iy], x[..., ipsi] = pose[..., 0], pose[..., 1], pose[..., 4]
    x[..., iv] = np.hypot(pose[..., 2], pose[..., 3])
    return x


def _pose_ukf(run: Run, system: System, q_accel: float, q_turn: float, T: int | None = None):
    """Stage-1 UKF over the first ``T`` samples; returns means, covariances, log-lik, filter."""
    ix, iy, iv, ipsi = planar_pose_indices(system)
    dt = run.dt
    block = np.array([[1.0, dt], [0.0, 1.0]])
    F = np.zeros((6, 6))
    for sl in ((0, 2), (1, 3), (4, 5)):  # (position, rate) pairs of [x, y, vx, vy, psi, r]
        F[np.ix_(sl, sl)] = block
    Q = np.zeros((6, 6))
    for sl, q in (((0, 2), q_accel), ((1, 3), q_accel), ((4, 5), q_turn)):
        Q[np.ix_(sl, sl)] = Q_continuous_white_noise(dim=2, dt=dt, spectral_density=q)

    def to_system(s):
        return _pose_to_state(system, s, (ix, iy, iv, ipsi))

    points = MerweScaledSigmaPoints(6, alpha=0.1, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(6, system.ny, dt, hx=lambda s, u: system.h(to_system(s), u),
                                fx=lambda s, dt: F @ s, points=points)
    ukf.Q, ukf.R = Q, np.diag(np.square(system.noise.measurement_std))
    x0, std0 = np.asarray(system.x0, float), np.asarray(system.noise.initial_std, float)
    ukf.x = np.array([x0[ix], x0[iy], x0[iv] * np.cos(x0[ipsi]), x0[iv] * np.sin(x0[ipsi]),
                      x0[ipsi], 0.0])
    ukf.P = np.diag([std0[ix] ** 2, std0[iy] ** 2, std0[iv] ** 2 + 1.0, std0[iv] ** 2 + 1.0,
                     std0[ipsi] ** 2, 1.0])  # + (1 m/s)^2, (1 rad/s)^2: the direction is unknown
    T = len(run) if T is None else T
    means, covs = np.empty((T, 6)), np.empty((T, 6, 6))
    loglik = 0.0
    for k in range(T):
        if k:
            ukf.predict()
        else:  # no predict before sample 0: draw the sigma points update() transforms
            ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
        ukf.update(run.y[k], u=run.u[k])  # y[k] = h(x[k], u[k]), the simulator's convention
        loglik -= 0.5 * (ukf.y @ np.linalg.solve(ukf.S, ukf.y) + np.linalg.slogdet(2 * np.pi * ukf.S)[1])
        means[k], covs[k] = ukf.x, ukf.P
    return means, covs, loglik, ukf


def _speed_kf(pos: np.ndarray, var: np.ndarray, dt: float, q: float):
    """Stage 2: constant-acceleration KF on one position coordinate with per-sample variances."""
    kf = KalmanFilter(dim_x=3, dim_z=1)
    kf.F = expm(np.diag(np.full(2, dt), 1))
    kf.Q = Q_continuous_white_noise(dim=3, dt=dt, spectral_density=q)
    kf.H = np.eye(1, 3)
    kf.x = np.array([[pos[0]], [0.0], [0.0]])
    kf.P = np.diag([var[0], 1e4, 1e4])
    Rs = [np.array([[r]]) for r in var]
    means, covs, means_p, covs_p = kf.batch_filter(pos[:, None], Rs=Rs)
    innov = pos - means_p[:, 0, 0]
    s = covs_p[:, 0, 0] + var
    loglik = -0.5 * float(np.sum(np.log(2 * np.pi * s) + innov**2 / s))
    return means[:, :, 0], covs, loglik, kf


def _position_fix_variance(run: Run, system: System, pose: np.ndarray) -> np.ndarray:
    """(T, 2) variances of a one-sample position fix, ``diag(inv(J' R^-1 J))``, J = dh/d(x, y).

    ``pose`` holds stage-1 states ``[x, y, vx, vy, psi, r]`` at which ``J`` is evaluated.
    """
    import casadi as cs

    ix, iy, iv, ipsi = planar_pose_indices(system)
    xs, us = cs.SX.sym("x", system.nx), cs.SX.sym("u", system.nu)
    J = cs.Function("J", [xs, us], [cs.jacobian(system.h(xs, us), xs)[:, [ix, iy]]])
    X = _pose_to_state(system, pose)
    # map() stacks the (ny, 2) Jacobians side by side: (ny, 2 T), column 2 t + i.
    Js = np.asarray(J.map(len(pose))(X.T, run.u.T)).reshape(system.ny, len(pose), 2)
    Js = Js.transpose(1, 0, 2)  # (T, ny, 2)
    w = 1.0 / np.square(np.asarray(system.noise.measurement_std, float))
    info = np.einsum("tki,k,tkj->tij", Js, w, Js)
    if np.any(np.linalg.det(info) <= 1e-12 * np.einsum("tii->t", info) ** 2):
        raise ValueError(f"system {system.name!r}: the measurements do not fix the position "
                         "(x, y) at some samples; the planar-pose observers need them to")
    return np.diagonal(np.linalg.inv(info), axis1=1, axis2=2).copy()


def _two_stage(run: Run, system: System, smooth: bool) -> Observations:
    """The paper's pre-training observer for a planar robot: a UKF, then a linear KF (see above)."""
    ix, iy, iv, ipsi = planar_pose_indices(system)
    tune = dict(T=min(len(run), STAGE1_TUNING_SAMPLES))
    mid_turn = float(np.sqrt(TURN_GRID[0] * TURN_GRID[-1]))
    q_accel = max(ACCEL_GRID, key=lambda q: _pose_ukf(run, system, q, mid_turn, **tune)[2])
    q_turn = max(TURN_GRID, key=lambda q: _pose_ukf(run, system, q_accel, q, **tune)[2])
    means, covs, _, ukf = _pose_ukf(run, system, q_accel, q_turn)
    if smooth:
        means, covs, _ = ukf.rts_smoother(means, covs)
    dt = run.dt
    pos, pos_var = means[:, :2], covs[:, [0, 1], [0, 1]]
    fix_var = _position_fix_variance(run, system, means)
    q_jerk = max(JERK_GRID[::2], key=lambda q: sum(_speed_kf(pos[:, j], fix_var[:, j], dt, q)[2]
                                                       for j in range(2)))
    vel, vel_var = np.empty((len(run), 2)), np.empty((len(run), 2))
    for j in range(2):
        m, c, _, kf = _speed_kf(pos[:, j], fix_var[:, j], dt, q_jerk)
        if smooth:
            m, c, _, _ = kf.rts_smoother(m[:, :, None], c)
            m = m[:, :, 0]
        vel[:, j], vel_var[:, j] = m[:, 1], c[:, 1, 1]
    speed = np.hypot(vel[:, 0], vel[:, 1])
    speed_var = np.sum(vel**2 * vel_var, axis=1) / np.maximum(speed, 1e-9) ** 2  # delta method
    zeta, var = np.empty((len(run), system.nx)), np.empty((len(run), system.nx))
    zeta[:, ix], zeta[:, iy], zeta[:, iv], zeta[:, ipsi] = means[:, 0], means[:, 1], speed, means[:, 4]
    var[:, ix], var[:, iy], var[:, iv], var[:, ipsi] = pos_var[:, 0], pos_var[:, 1], speed_var, covs[:, 4, 4]
    info = {"accel_spectral_density": float(q_accel), "turn_spectral_density": float(q_turn),
            "jerk_spectral_density": float(q_jerk)}
    return Observations(zeta, var, "ukf_rts" if smooth else "ukf_kf", info)


OBSERVERS: dict[str, Callable[[Run, System], Observations]] = {
    "kf": lambda run, system: _kinematic(run, system, smooth=False),
    "rts": lambda run, system: _kinematic(run, system, smooth=True),
    "ukf": _model_ukf,
    "ekf_rts": lambda run, system: ekf_rts(run, system),
    "linear_rts": linear_rts,
    "ukf_kf": lambda run, system: _two_stage(run, system, smooth=False),
    "ukf_rts": lambda run, system: _two_stage(run, system, smooth=True),
}


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
