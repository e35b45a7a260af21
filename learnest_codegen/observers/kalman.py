"""A Kalman filter and RTS smoother over a batch of linear-Gaussian models at once, with
missing measurements.

The kinematic observers search a grid of noise intensities for the one with the highest
innovation likelihood: every grid point is one member of the batch, and one pass over the run
filters them all (numpy on ``(B, n, n)`` arrays instead of one FilterPy filter per point).
While every output is present the covariance recursion does not depend on the data; once it
has converged, the filter runs on its steady-state gain, two array operations per sample.

Missing measurements are NaN in ``z``: the filter predicts through them and updates with the
outputs that are present, as a Kalman filter of the same model given only those outputs does
(and contributes only those outputs to the likelihood).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ShapeError

#: a predicted covariance whose every entry changed over one full-measurement step by less than
#: this share of its scale ``sqrt(P_ii P_jj)`` is taken as converged; the filter then runs on the
#: steady-state gain
STEADY_TOLERANCE = 1e-14


@dataclass(frozen=True)
class LinearGaussian:
    """``x[k+1] = F x[k] + w``, ``w ~ N(0, Q)``; ``z[k] = H x[k] + v``, ``v ~ N(0, R)``."""

    F: np.ndarray
    Q: np.ndarray
    H: np.ndarray
    R: np.ndarray


@dataclass(frozen=True)
class FilterPasses:
    """What :func:`kalman_filter` returns for a batch of ``B`` models over ``T`` samples.

    Attributes
    ----------
    means, covs : (T, B, n), (T, B, n, n) filtered (after the update of sample k).
    means_p, covs_p : the same, predicted (before the update of sample k).
    loglik : (B,) innovation log-likelihood of the present measurements.
    """

    means: np.ndarray
    covs: np.ndarray
    means_p: np.ndarray
    covs_p: np.ndarray
    loglik: np.ndarray

    def member(self, b: int) -> "FilterPasses":
        """Member ``b`` of the batch alone (a batch of one)."""
        s = slice(b, b + 1)
        return FilterPasses(self.means[:, s], self.covs[:, s], self.means_p[:, s],
                            self.covs_p[:, s], self.loglik[s])


def kalman_filter(F: np.ndarray, H: np.ndarray, Q: np.ndarray, R: np.ndarray, z: np.ndarray,
                  x0: np.ndarray, P0: np.ndarray, *, burn_in: int = 0) -> FilterPasses:
    """Predict-then-update Kalman filter (FilterPy's ``batch_filter`` order: the first sample is
    predicted from ``x0``, ``P0`` too) of ``B`` models sharing ``F`` and ``H``.

    Parameters
    ----------
    F : (n, n) transition.
    H : (m, n) measurement matrix.
    Q : (B, n, n) process noise of each member.
    R : (m, m), (B, m, m) or, varying in time, (T, B, m, m) measurement noise.
    z : (T, m) shared or (T, B, m) per member; NaN marks a missing measurement.
    x0, P0 : (B, n), (B, n, n) before the first prediction.
    burn_in : first samples left out of the likelihood.

    The covariance update is Joseph's form, as FilterPy's.
    """
    F, H = np.asarray(F, float), np.asarray(H, float)
    n, m = F.shape[0], H.shape[0]
    Q = np.asarray(Q, float)
    B = Q.shape[0]
    z = np.asarray(z, float)
    T = z.shape[0]
    z = np.broadcast_to(z[:, None, :] if z.ndim == 2 else z, (T, B, m))
    R = np.asarray(R, float)
    varying_r = R.ndim == 4
    Rb = R if varying_r else np.broadcast_to(R, (B, m, m))
    if Q.shape != (B, n, n) or H.shape != (m, n) or np.shape(x0) != (B, n) or np.shape(P0) != (B, n, n):
        raise ShapeError(f"kalman_filter: expected F (n, n), H (m, n), Q (B, n, n), x0 (B, n), P0 "
                         f"(B, n, n) with n={n}, m={m}, B={B}; got {F.shape}, {H.shape}, {Q.shape}, "
                         f"{np.shape(x0)}, {np.shape(P0)}")
    present = np.isfinite(z)
    full = present.all(axis=(1, 2))
    zero_z = np.where(present, z, 0.0)
    FT, HT, eye = F.T, H.T, np.eye(n)

    # 1. the covariances and gains (they depend on which outputs are present, not on their values)
    covs, covs_p = np.empty((T, B, n, n)), np.empty((T, B, n, n))
    gains, S_all = np.empty((T, B, n, m)), np.empty((T, B, m, m))
    P = np.array(P0, float)
    steady = None  # (P, Pp, K, S) once converged
    previous = None
    gaps = np.append(np.flatnonzero(~full), T)  # the samples with a missing output, then T
    k = 0
    while k < T:
        if steady is not None and full[k]:  # until the next missing output
            end = int(gaps[np.searchsorted(gaps, k)])
            covs[k:end], covs_p[k:end], gains[k:end], S_all[k:end] = steady
            k = end
            continue
        Pp = F @ P @ FT + Q
        Rk = Rb[k] if varying_r else Rb
        if full[k]:
            Hk, HkT, Rk_eff = H, HT, Rk
        else:  # a missing row: zero in H, 1/(2 pi) in R (adds nothing to the likelihood)
            mask = present[k].astype(float)  # (B, m)
            Hk = H[None] * mask[:, :, None]
            HkT = Hk.transpose(0, 2, 1)
            Rk_eff = Rk * (mask[:, :, None] * mask[:, None, :]) + (1.0 - mask)[:, :, None] * \
                np.eye(m) / (2 * np.pi)
        PHT = Pp @ HkT
        S = Hk @ PHT + Rk_eff
        K = PHT / S if m == 1 else PHT @ np.linalg.inv(S)
        IKH = eye - K @ Hk
        P = IKH @ Pp @ IKH.transpose(0, 2, 1) + K @ Rk_eff @ K.transpose(0, 2, 1)
        covs[k], covs_p[k], gains[k], S_all[k] = P, Pp, K, S
        if not full[k] or varying_r:  # the covariance left the steady state: converge again first
            steady, previous = None, None
        elif previous is not None and k % 8 == 0:
            if _converged(Pp, previous):
                steady = (P, Pp, K, S)
        if full[k] and not varying_r:
            previous = Pp
        k += 1

    # 2. the means: x[k] = (F - K[k] H F) x[k-1] + K[k] z[k], two array operations per sample
    # (a missing output's column of K is zero, so the full H serves every sample)
    A = F - gains @ (H @ F)
    drive = np.einsum("tbnm,tbm->tbn", gains, zero_z)
    means = np.empty((T, B, n))
    x = np.array(x0, float)[:, :, None]
    for j in range(T):
        x = A[j] @ x
        x += drive[j][:, :, None]
        means[j] = x[:, :, 0]
    means_p = np.empty((T, B, n))
    means_p[0] = np.asarray(x0, float) @ FT
    means_p[1:] = means[:-1] @ FT
    innov = np.where(present, zero_z - means_p @ HT, 0.0)
    e, S = innov[burn_in:], S_all[burn_in:]
    quad = np.einsum("tbm,tbm->tb", e, np.linalg.solve(S, e[..., None])[..., 0])
    loglik = -0.5 * (quad + np.linalg.slogdet(2 * np.pi * S)[1]).sum(axis=0)
    return FilterPasses(means, covs, means_p, covs_p, loglik)


def _converged(P: np.ndarray, previous: np.ndarray) -> bool:
    """Whether every member's covariance ``P`` (B, n, n) equals ``previous`` to
    :data:`STEADY_TOLERANCE` of each entry's scale."""
    d = np.sqrt(np.abs(np.diagonal(P, axis1=1, axis2=2)))
    scale = d[:, :, None] * d[:, None, :]
    return bool(np.all(np.abs(P - previous) <= STEADY_TOLERANCE * scale))


def rts_smoother(F: np.ndarray, passes: FilterPasses) -> tuple[np.ndarray, np.ndarray]:
    """Rauch-Tung-Striebel pass over :func:`kalman_filter`'s result: smoothed means
    ``(T, B, n)`` and covariances ``(T, B, n, n)``."""
    F = np.asarray(F, float)
    xs, Ps = passes.means.copy(), passes.covs.copy()
    T = len(xs)
    if T < 2:
        return xs, Ps
    # gains G[k] = P[k] F' inv(Pp[k+1]) of every step at once: solve(Pp', F P') transposed
    G = np.swapaxes(np.linalg.solve(np.swapaxes(passes.covs_p[1:], -1, -2),
                                    F @ np.swapaxes(passes.covs[:-1], -1, -2)), -1, -2)
    GT = np.swapaxes(G, -1, -2)
    for k in range(T - 2, -1, -1):
        xs[k] += np.einsum("bij,bj->bi", G[k], xs[k + 1] - passes.means_p[k + 1])
        Ps[k] += G[k] @ (Ps[k + 1] - passes.covs_p[k + 1]) @ GT[k]
    return xs, Ps


def integrator_chain(order: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """The exact discretisation over ``dt`` of a chain of ``order`` integrators driven by unit
    white noise on its last derivative: ``F = expm(A dt)`` (``F[i, j] = dt^(j-i) / (j-i)!``) and
    the covariance of the noise it adds (``Q[i, j] = dt^(2n-1-i-j) / ((n-1-i)! (n-1-j)!
    (2n-1-i-j))`` for ``n = order``; FilterPy's ``Q_continuous_white_noise`` for 2-4), closed
    forms that spare the pre-training observers scipy's ``expm`` and FilterPy's import."""
    n = order
    i, j = np.indices((n, n))
    lag = j - i
    fact = np.array([math.factorial(k) for k in range(2 * n)], float)
    F = np.where(lag >= 0, dt ** np.maximum(lag, 0) / fact[np.maximum(lag, 0)], 0.0)
    power = 2 * n - 1 - i - j
    Q = dt ** power / (fact[n - 1 - i] * fact[n - 1 - j] * power)
    return F, Q
