/* learnest_ukf.h -- the Unscented Kalman Filter's host-side logic and API (docs/c_api.md).
 *
 * The sigma-point arithmetic is the model's (codegen/ukf.py generates FilterPy's predict and
 * a masked update as CasADi code); this file adds what runs around it: the sample convention
 * (the first sample after init/reset has no transition), missing outputs and the innovation
 * gate; the covariance guards, the recovery and the API are learnest_kalman.h's.
 *
 * Include after learnest_kit.h with LEARNEST_PREFIX, LEARNEST_NX, LEARNEST_NU, LEARNEST_NY and
 * the model, either as the two halves of the filter
 *   struct learnest_model; learnest_model_predict(md, x, P, u, Q, x_prior, P_prior) and
 *   learnest_model_update(md, x, P, u, y, R, mask, x_post, P_post, d2), matrices
 *   column-major, returning 0 on success,
 * or (LEARNEST_UKF_ALPHA, _BETA, _KAPPA defined: what codegen/ukf.py generates) as the model
 * alone, learnest_model_F(md, x, u, F) and learnest_model_h(md, x, u, h), around which this
 * file runs the sigma points through a loop over one compiled model call (one copy of the
 * model in flash instead of 2 NX + 1; learnest_casadi.h gives the hooks for CasADi code), or,
 * where the model has a batch copy of F (LEARNEST_MODEL_F_BATCH) and the compiler vectors
 * (learnest_simd.h), through F on LEARNEST_MODEL_F_LANES points a call: the same bits.
 */
#ifndef LEARNEST_UKF_H
#define LEARNEST_UKF_H

#include "learnest_kalman.h"

#ifdef LEARNEST_UKF_ALPHA
/* FilterPy 2.0.0's predict and update on Merwe scaled sigma points, operation for operation
 * as codegen/ukf.py writes them for CasADi (its functions are the tested reference). */
#define LEARNEST_UKF_NS (2 * LEARNEST_NX + 1)
#define LEARNEST_UKF_LAMBDA \
  (LEARNEST_UKF_ALPHA * LEARNEST_UKF_ALPHA * (LEARNEST_NX + LEARNEST_UKF_KAPPA) - LEARNEST_NX)
#define LEARNEST_UKF_SCALE ((learnest_real)(LEARNEST_UKF_LAMBDA + LEARNEST_NX))
#define LEARNEST_UKF_WM0 ((learnest_real)(LEARNEST_UKF_LAMBDA / (LEARNEST_NX + LEARNEST_UKF_LAMBDA)))
#define LEARNEST_UKF_WC0 ((learnest_real)(LEARNEST_UKF_LAMBDA / (LEARNEST_NX + LEARNEST_UKF_LAMBDA) \
                          + (1 - LEARNEST_UKF_ALPHA * LEARNEST_UKF_ALPHA + LEARNEST_UKF_BETA)))
#define LEARNEST_UKF_WI ((learnest_real)(0.5 / (LEARNEST_NX + LEARNEST_UKF_LAMBDA)))

/* Upper U with A = U'U from A's upper triangle (n x n, column-major; U's lower part is not
 * written); a non-positive pivot gives NaN, which the step reports. */
LEARNEST_KIT void learnest_ukf_chol_upper(const learnest_real* A, int n, learnest_real* U) {
  int i, j, k;
  for (j = 0; j < n; ++j) {
    learnest_real t = 0;
    LEARNEST_UNROLL for (k = 0; k < j; ++k) t += U[k + j * n] * U[k + j * n];
    U[j + j * n] = LEARNEST_SQRT(A[j + j * n] - t);
    for (i = j + 1; i < n; ++i) {
      t = 0;
      LEARNEST_UNROLL for (k = 0; k < j; ++k) t += U[k + j * n] * U[k + i * n];
      U[j + i * n] = (A[j + i * n] - t) / U[j + j * n];
    }
  }
}

/* The 2 NX + 1 sigma points of (x, P): x, x + U[k, :], x - U[k, :], U = chol((lambda+n) P). */
LEARNEST_KIT void learnest_ukf_sigmas(const learnest_real* x, const learnest_real* P,
                                      learnest_real* sig) {
  learnest_real A[LEARNEST_KF_NXX], U[LEARNEST_KF_NXX];
  int i, k, c;
  for (i = 0; i < LEARNEST_KF_NXX; ++i) A[i] = LEARNEST_UKF_SCALE * P[i];
  learnest_ukf_chol_upper(A, LEARNEST_NX, U);
  memcpy(sig, x, LEARNEST_NX * sizeof(learnest_real));
  for (k = 0; k < LEARNEST_NX; ++k) {
    learnest_real* plus = sig + (1 + k) * LEARNEST_NX;
    learnest_real* minus = sig + (1 + LEARNEST_NX + k) * LEARNEST_NX;
    for (c = 0; c < LEARNEST_NX; ++c) {
      plus[c] = c < k ? x[c] : x[c] + U[k + c * LEARNEST_NX];
      minus[c] = c < k ? x[c] : x[c] - U[k + c * LEARNEST_NX];
    }
  }
}

/* mean (m) = sum Wm_s Y_s of the NS points Y (m each); Y <- Y - mean; cov += sum Wc_s d_s d_s'
 * (d = Y - mean; each product is symmetric in r, c, so the lower triangle is mirrored). */
LEARNEST_KIT void learnest_ukf_transform(learnest_real* Y, int m, learnest_real* mean,
                                         learnest_real* cov) {
  int s, r, c;
  for (r = 0; r < m; ++r) {
    learnest_real t = LEARNEST_UKF_WM0 * Y[r];
    LEARNEST_UNROLL for (s = 1; s < LEARNEST_UKF_NS; ++s) t += LEARNEST_UKF_WI * Y[s * m + r];
    mean[r] = t;
  }
  for (s = 0; s < LEARNEST_UKF_NS; ++s) {
    for (r = 0; r < m; ++r) Y[s * m + r] -= mean[r];
  }
  for (c = 0; c < m; ++c) {
    for (r = c; r < m; ++r) {
      learnest_real t = LEARNEST_UKF_WC0 * (Y[r] * Y[c]);
      LEARNEST_UNROLL for (s = 1; s < LEARNEST_UKF_NS; ++s) t += LEARNEST_UKF_WI * (Y[s * m + r] * Y[s * m + c]);
      cov[r + c * m] = t + cov[r + c * m];
      if (r != c) cov[c + r * m] = t + cov[c + r * m];
    }
  }
}

#if defined(LEARNEST_MODEL_F_BATCH) && LEARNEST_SIMD
/* Y_s = F(sig_s, u) for the NS sigma points, LEARNEST_MODEL_F_LANES at a time through the
 * model's batch copy (the last batch's spare lanes repeat the last point). */
LEARNEST_KIT void learnest_ukf_propagate(struct learnest_model* md, const learnest_real* sig,
                                         const learnest_real* u, learnest_real* Y) {
  enum { NX = LEARNEST_NX, L = LEARNEST_MODEL_F_LANES };
  learnest_real xs[NX * L], us[LEARNEST_NU * L + 1], Fs[NX * L];
  int s0;
  learnest_lanes_gather(us, u, LEARNEST_NU, 0, 0, L);  /* every point's input is u */
  for (s0 = 0; s0 < LEARNEST_UKF_NS; s0 += L) {
    learnest_lanes_gather(xs, sig, NX, s0, LEARNEST_UKF_NS - 1, L);
    learnest_model_F_batch(xs, us, Fs);
    learnest_lanes_scatter(Y, Fs, NX, s0, LEARNEST_UKF_NS - 1, L);
  }
  (void)md;
}
#else
/* Y_s = F(sig_s, u) for the NS sigma points, one model call each. */
LEARNEST_KIT void learnest_ukf_propagate(struct learnest_model* md, const learnest_real* sig,
                                         const learnest_real* u, learnest_real* Y) {
  int s;
  for (s = 0; s < LEARNEST_UKF_NS; ++s) {
    learnest_model_F(md, sig + s * LEARNEST_NX, u, Y + s * LEARNEST_NX);
  }
}
#endif

LEARNEST_KIT int learnest_model_predict(struct learnest_model* md, const learnest_real* x,
                                        const learnest_real* P, const learnest_real* u,
                                        const learnest_real* Q, learnest_real* x_prior,
                                        learnest_real* P_prior) {
  learnest_real sig[LEARNEST_UKF_NS * LEARNEST_NX], Y[LEARNEST_UKF_NS * LEARNEST_NX];
  learnest_ukf_sigmas(x, P, sig);
  learnest_ukf_propagate(md, sig, u, Y);
  memcpy(P_prior, Q, LEARNEST_KF_NXX * sizeof(learnest_real));
  learnest_ukf_transform(Y, LEARNEST_NX, x_prior, P_prior);
  return 0;
}

/* The update on the outputs mask keeps (S -> M S M + I - M, Pxz -> Pxz M, nu -> M nu) and
 * every output's d2 = nu_j^2 / S_jj; K = Pxz S^-1 with S^-1 = V V', V = U^-1, S = U'U. */
LEARNEST_KIT int learnest_model_update(struct learnest_model* md, const learnest_real* x,
                                       const learnest_real* P, const learnest_real* u,
                                       const learnest_real* y, const learnest_real* R,
                                       const learnest_real* mask, learnest_real* x_post,
                                       learnest_real* P_post, learnest_real* d2) {
  enum { NX = LEARNEST_NX, NY = LEARNEST_NY };
  learnest_real sig[LEARNEST_UKF_NS * NX], Z[LEARNEST_UKF_NS * NY], zp[NY], S[NY * NY];
  learnest_real Pxz[NX * NY], nu[NY], U[NY * NY], V[NY * NY], Si[NY * NY], K[NX * NY];
  learnest_real SK[NY * NX];
  int s, r, c, k;
  learnest_ukf_sigmas(x, P, sig);
  for (s = 0; s < LEARNEST_UKF_NS; ++s) learnest_model_h(md, sig + s * NX, u, Z + s * NY);
  memcpy(S, R, sizeof S);
  learnest_ukf_transform(Z, NY, zp, S);
  for (s = 0; s < LEARNEST_UKF_NS; ++s) {  /* sig <- sig - x (Z is already Z - zp) */
    for (r = 0; r < NX; ++r) sig[s * NX + r] -= x[r];
  }
  for (c = 0; c < NY; ++c) {
    for (r = 0; r < NX; ++r) {
      learnest_real t = LEARNEST_UKF_WC0 * (sig[r] * Z[c]);
      LEARNEST_UNROLL for (s = 1; s < LEARNEST_UKF_NS; ++s) t += LEARNEST_UKF_WI * (sig[s * NX + r] * Z[s * NY + c]);
      Pxz[r + c * NX] = t * mask[c];
    }
  }
  for (r = 0; r < NY; ++r) {
    nu[r] = y[r] - zp[r];
    d2[r] = nu[r] * nu[r] / S[r + r * NY];
    nu[r] = mask[r] * nu[r];
  }
  for (c = 0; c < NY; ++c) {
    for (r = 0; r < NY; ++r) {
      S[r + c * NY] = mask[r] * (S[r + c * NY] * mask[c]) + (r == c ? 1 - mask[r] : 0);
    }
  }
  learnest_ukf_chol_upper(S, NY, U);
  for (c = 0; c < NY; ++c) {  /* V = U^-1, upper triangular */
    V[c + c * NY] = 1 / U[c + c * NY];
    for (r = c - 1; r >= 0; --r) {
      learnest_real t = 0;
      for (k = r + 1; k <= c; ++k) t += U[r + k * NY] * V[k + c * NY];
      V[r + c * NY] = -t / U[r + r * NY];
    }
    for (r = c + 1; r < NY; ++r) V[r + c * NY] = 0;
  }
  learnest_mat_mul_t(V, V, NY, NY, NY, Si);
  learnest_mat_mul(Pxz, Si, NX, NY, NY, K);
  for (r = 0; r < NX; ++r) {
    learnest_real t = 0;
    for (k = 0; k < NY; ++k) t += K[r + k * NX] * nu[k];
    x_post[r] = x[r] + t;
  }
  learnest_mat_mul_t(S, K, NY, NY, NX, SK);  /* S K' */
  learnest_mat_mul(K, SK, NX, NY, NX, P_post);
  for (k = 0; k < NX * NX; ++k) P_post[k] = P[k] - P_post[k];
  return 0;
}
#endif

/* One sample: predict with u (not on the first sample after init/reset), update with the
 * valid outputs of y, gate them (or re-seed), guard and cap the covariance, recover; commit
 * only on success. */
LEARNEST_KIT int learnest_est_step(LEARNEST_HANDLE* h, const learnest_real* u,
                                   const learnest_real* y, const unsigned char* valid,
                                   int* rejected) {
  learnest_real x_prior[LEARNEST_NX], P_prior[LEARNEST_KF_NXX], x_post[LEARNEST_NX];
  learnest_real P_post[LEARNEST_KF_NXX], d2[LEARNEST_NY], mask[LEARNEST_NY];
  int rc = 0, i, any = 0, any_valid = learnest_any_valid(valid, LEARNEST_NY);
  if (h->c.samples == 0) {
    memcpy(x_prior, h->x, sizeof x_prior);
    memcpy(P_prior, h->P, sizeof P_prior);
  } else {
    rc = learnest_model_predict(&h->model, h->x, h->P, u, h->Q, x_prior, P_prior);
  }
  for (i = 0; i < LEARNEST_NY; ++i) rejected[i] = 0;
  if (rc == 0 && any_valid) {
    for (i = 0; i < LEARNEST_NY; ++i) mask[i] = valid[i];
    rc = learnest_model_update(&h->model, x_prior, P_prior, u, y, h->R, mask, x_post, P_post, d2);
    /* Gate: a valid output whose d2 = (y - zp)^2 / S_jj exceeds the threshold (or is NaN) is
     * rejected, and the update is redone without it; a lost estimate re-seeds instead: the
     * update is redone from the prior covariance diag(ceiling) with every valid output. */
    if (rc == 0) any = learnest_gate_test(&h->c.gate, d2, valid, LEARNEST_NY, rejected);
    if (rc == 0 && any && learnest_gate_reseeds(&h->c.gate, rejected)) {
      learnest_kalman_reseed(P_prior);
      rc = learnest_model_update(&h->model, x_prior, P_prior, u, y, h->R, mask, x_post, P_post, d2);
    } else if (rc == 0 && any) {
      for (i = 0; i < LEARNEST_NY; ++i) mask[i] = valid[i] && !rejected[i];
      rc = learnest_model_update(&h->model, x_prior, P_prior, u, y, h->R, mask, x_post, P_post, d2);
    }
  } else if (rc == 0) {  /* no output: the prediction stands */
    memcpy(x_post, x_prior, sizeof x_post);
    memcpy(P_post, P_prior, sizeof P_post);
  }
  /* A failed Cholesky shows up as NaN (sqrt of a negative pivot): commit finite results only. */
  if (rc != 0) return LEARNEST_NONFINITE_RESULT;
  return learnest_kalman_commit(h, x_post, P_post, rejected, valid);
}

#endif /* LEARNEST_UKF_H */
