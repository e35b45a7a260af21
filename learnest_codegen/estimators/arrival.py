"""The arrival covariance of an MHE window that started from a doubtful prior.

The running arrival weight (the settings', by default the inverse of the steady-state Kalman
prior covariance) summarises a long history of samples. A window that starts empty -- after
``reset(x0, P0)``, or after a recovery restart (:mod:`.mhe`) -- has only its first prior,
whose covariance is larger. When such a window slides, the arrival covariance is carried
forward by the extended Kalman filter's covariance recursion (the first stage's accepted
outputs, then the transition), linearised at the window's estimate of the stage that leaves:

    P+ = A (P - P C^T (C P C^T + R)^-1 C P) A^T + Q,

until it is no larger than the running covariance (``P+ <= P_run`` in the positive-
semidefinite order); from then on the running weight applies. Its variances are kept below
:data:`ARRIVAL_CEILING` times the running ones (a long gap would otherwise grow it without
bound). Jumping straight from the
first prior to the steady-state weight instead pins the states the outputs see only through
the dynamics to whatever the first window made of them: after a recovery restart the
cartpole's rates stayed off for hundreds of samples (``docs/reports/reliability.md``).
"""

from __future__ import annotations

import casadi as cs
import numpy as np

#: Relative slack of the "no larger than the running covariance" test (rounding).
SETTLED_RTOL = 1e-9
#: The largest variance of a carried arrival covariance (and of a restart prior's posterior,
#: :mod:`.mhe`) relative to the running one's: its weight then stays within 100 times the
#: running weight, which the float32 Gauss-Newton normal equations resolve (at 1e3 the float32
#: ``mhe_gn`` failed with MAX_ITERATIONS after a gap of 10,000 samples; the C kit's
#: ``LEARNEST_ARRIVAL_CEILING``).
ARRIVAL_CEILING = 100.0


def transition_jacobian(model, name: str = "A") -> cs.Function:
    """``name(x, u) -> A = dF/dx (nx, nx)`` of the discrete model ``F``."""
    x, u = cs.SX.sym("x", model.nx), cs.SX.sym("u", model.nu)
    return cs.Function(name, [x, u], [cs.densify(cs.jacobian(model.F(x, u), x))], ["x", "u"], ["A"])


def propagate(P: np.ndarray, A: np.ndarray, C: np.ndarray, keep: np.ndarray, Q: np.ndarray,
              R: np.ndarray) -> np.ndarray:
    """One step of the recursion in the module docstring.

    ``P (nx, nx)`` the arrival covariance of the stage that leaves; ``C (ny, nx)`` its output
    Jacobian and ``keep (ny,)`` the outputs of that stage the window used; ``A (nx, nx)`` the
    transition to the next stage; ``Q``, ``R`` the process and measurement covariances.
    """
    keep = np.asarray(keep, dtype=bool)
    if keep.any():
        Ck = C[keep]
        S = Ck @ P @ Ck.T + R[np.ix_(keep, keep)]
        K = np.linalg.solve(S, Ck @ P).T
        P = P - K @ Ck @ P
    P = A @ P @ A.T + Q
    return 0.5 * (P + P.T)


def settled(P: np.ndarray, running_weight: np.ndarray) -> bool:
    """Whether ``P <= inv(running_weight)``: the largest eigenvalue of ``W P`` is at most 1."""
    L = np.linalg.cholesky(running_weight)
    return float(np.linalg.eigvalsh(L.T @ P @ L).max()) <= 1.0 + SETTLED_RTOL
