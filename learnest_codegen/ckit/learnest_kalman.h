/* learnest_kalman.h -- what the Kalman filters of the kit (the UKF, learnest_ukf.h; the EKF,
 * learnest_ekf.h) share: the handle (the state, its covariance, the noise covariances, the
 * model), their tuning from covariances, run-time tuning, the covariance guard, ceiling,
 * recovery and re-seed of a step, the API of learnest_api.h and get_covariance.
 *
 * Ceiling: no variance of P exceeds LEARNEST_MAX_INFLATION times the build's initial variance
 * (LEARNEST_DEFAULT_P0, the settings' initial_std squared): a long run of predictions, or the
 * recovery's inflation, grows P up to it and no further (P's rows and columns are scaled, so
 * the correlations stay). Unbounded, the cartpole UKF's P went from 16 to 1e44 within 1,000
 * predictions and the state to 6e12. A re-seed (learnest_gate.h) updates the prediction from
 * the prior covariance diag(ceiling).
 *
 * Include after learnest_kit.h with LEARNEST_PREFIX, LEARNEST_NX, LEARNEST_NU, LEARNEST_NY and
 * the model (struct learnest_model); the including file then defines learnest_est_step.
 */
#ifndef LEARNEST_KALMAN_H
#define LEARNEST_KALMAN_H

#include "learnest_dense.h"
#include "learnest_handle.h"

#define LEARNEST_KF_NXX (LEARNEST_NX * LEARNEST_NX)
#define LEARNEST_KF_NYY (LEARNEST_NY * LEARNEST_NY)
#define LEARNEST_KF_NMAX (LEARNEST_NX > LEARNEST_NY ? LEARNEST_NX : LEARNEST_NY)

LEARNEST_HANDLE {
  struct learnest_common c;
  /* Filter state; the model reads matrices column-major, the API speaks row-major. */
  learnest_real x[LEARNEST_NX], P[LEARNEST_KF_NXX], Q[LEARNEST_KF_NXX], R[LEARNEST_KF_NYY];
  struct learnest_model model;
};

struct learnest_kalman_tuning {
  learnest_real P0[LEARNEST_KF_NXX], Q[LEARNEST_KF_NXX], R[LEARNEST_KF_NYY];  /* col-major */
};
typedef struct learnest_kalman_tuning learnest_tuning;

/* 1 when no variance (diagonal entry) of the n x n A is negative: the PSD check's rounding
 * allowance (a tiny absolute shift) must not let -1e-40 I pass as a float32 covariance. */
LEARNEST_KIT int learnest_kalman_variances_ok(const learnest_real* A, int n) {
  int i;
  for (i = 0; i < n; ++i) {
    if (A[i * n + i] < 0) return 0;
  }
  return 1;
}

/* P0, Q, R (NULL: left alone) checked by learnest_covariance_in into t (column-major; P0 and Q
 * positive semidefinite, no variance below zero; R positive definite, as the update inverts
 * it), every variance in the precision's range (P0's and Q's may be 0; else
 * LEARNEST_BAD_ARGUMENT); nothing is written unless every given one is valid. */
LEARNEST_KIT int learnest_est_tune(learnest_tuning* t, const learnest_real* P0,
                                   const learnest_real* Q, const learnest_real* R) {
  learnest_real w[LEARNEST_KF_NMAX * LEARNEST_KF_NMAX];
  learnest_tuning c;
  int code = P0 ? learnest_covariance_in(P0, LEARNEST_NX, c.P0, w) : LEARNEST_OK;
  if (code == LEARNEST_OK && Q) code = learnest_covariance_in(Q, LEARNEST_NX, c.Q, w);
  if (code == LEARNEST_OK && R) code = learnest_covariance_in(R, LEARNEST_NY, c.R, w);
  if (code != LEARNEST_OK) return code;
  if ((P0 && !learnest_kalman_variances_ok(P0, LEARNEST_NX)) ||  /* the diagonal: either order */
      (Q && !learnest_kalman_variances_ok(Q, LEARNEST_NX)) ||
      (R && !learnest_kalman_variances_ok(R, LEARNEST_NY))) {
    return LEARNEST_NOT_POSITIVE_DEFINITE;
  }
  if (R) {  /* R positive definite: its Cholesky factor exists */
    memcpy(w, c.R, sizeof c.R);
    if (!learnest_cholesky(w, LEARNEST_NY)) return LEARNEST_NOT_POSITIVE_DEFINITE;
  }
  if ((P0 && !learnest_variances_ok(P0, LEARNEST_NX, 0)) ||
      (Q && !learnest_variances_ok(Q, LEARNEST_NX, 0)) ||
      (R && !learnest_variances_ok(R, LEARNEST_NY, 1))) {
    return LEARNEST_BAD_ARGUMENT;
  }
  if (P0) memcpy(t->P0, c.P0, sizeof c.P0);
  if (Q) memcpy(t->Q, c.Q, sizeof c.Q);
  if (R) memcpy(t->R, c.R, sizeof c.R);
  return LEARNEST_OK;
}

LEARNEST_KIT void learnest_est_defaults(LEARNEST_HANDLE* h) { (void)h; }

LEARNEST_KIT void learnest_est_start(LEARNEST_HANDLE* h, const learnest_real* x0,
                                     const learnest_tuning* t) {
  memcpy(h->x, x0, sizeof h->x);
  memcpy(h->P, t->P0, sizeof h->P);
  memcpy(h->Q, t->Q, sizeof h->Q);
  memcpy(h->R, t->R, sizeof h->R);
}

LEARNEST_KIT int learnest_est_set_noise(LEARNEST_HANDLE* h, const learnest_real* Q,
                                        const learnest_real* R) {
  learnest_tuning t;
  int code = learnest_est_tune(&t, 0, Q, R);
  if (code != LEARNEST_OK) return code;
  if (Q) memcpy(h->Q, t.Q, sizeof h->Q);
  if (R) memcpy(h->R, t.R, sizeof h->R);
  return LEARNEST_OK;
}

LEARNEST_KIT const learnest_real* learnest_est_state(const LEARNEST_HANDLE* h) { return h->x; }

/* 1 when the symmetric NX x NX P (column-major; only its lower triangle is read) has a
 * Cholesky factor whose every pivot keeps a margin, d_j > margin P_jj: a P that factorises
 * only by a rounding error's width here may not in another factorisation of it (the next
 * prediction's, in the model code). work: NX x NX. */
LEARNEST_KIT int learnest_kalman_factorises(const learnest_real* P, learnest_real margin,
                                            learnest_real* work) {
  int i, j, k;
  for (j = 0; j < LEARNEST_NX; ++j) {
    learnest_real d = P[j + j * LEARNEST_NX];
    for (k = 0; k < j; ++k) d -= work[j + k * LEARNEST_NX] * work[j + k * LEARNEST_NX];
    if (!(d > margin * P[j + j * LEARNEST_NX])) return 0;
    d = LEARNEST_SQRT(d);
    work[j + j * LEARNEST_NX] = d;
    for (i = j + 1; i < LEARNEST_NX; ++i) {
      learnest_real v = P[i + j * LEARNEST_NX];
      for (k = 0; k < j; ++k) v -= work[i + k * LEARNEST_NX] * work[j + k * LEARNEST_NX];
      work[i + j * LEARNEST_NX] = v / d;
    }
  }
  return 1;
}

/* Keep the symmetric NX x NX P (column-major) positive definite with a margin, so the next
 * prediction can take its Cholesky factor: an exact measurement (R = 0, tiny, or rank-deficient)
 * makes P - K S K^T singular, and rounding leaves its smallest eigenvalue at +-1e-8 relative
 * in float32, +-1e-17 in float64, i.e. indefinite or too close to it. When P does not factorise
 * with pivots above 4 NX epsilon of their variance (learnest_kalman_factorises), the diagonal
 * is loaded, P_ii += d s with s the largest variance and d = NX epsilon, 10 NX epsilon, ...
 * below ten times learnest_covariance_ok's tolerance (each rung replacing the last), until it
 * does. Returns the rung used (0: P untouched), or -1 if none helped. */
LEARNEST_KIT int learnest_kalman_keep_pd(learnest_real* P, learnest_real* work) {
  const learnest_real eps = LEARNEST_IS_FLOAT ? (learnest_real)1.1920929e-7
                                              : (learnest_real)2.220446049250313e-16;
  const learnest_real top = LEARNEST_IS_FLOAT ? (learnest_real)1e-4 : (learnest_real)1e-9;
  const learnest_real tiny = LEARNEST_IS_FLOAT ? (learnest_real)1e-30 : (learnest_real)1e-300;
  const learnest_real margin = 4 * LEARNEST_NX * eps;
  learnest_real d = LEARNEST_NX * eps, scale = 0, diagonal[LEARNEST_NX];
  int rung, i;
  if (learnest_kalman_factorises(P, margin, work)) return 0;
  for (i = 0; i < LEARNEST_NX; ++i) {
    diagonal[i] = P[i * LEARNEST_NX + i];
    scale = diagonal[i] > scale ? diagonal[i] : scale;
  }
  for (rung = 1; d < top; ++rung, d *= 10) {
    for (i = 0; i < LEARNEST_NX; ++i) P[i * LEARNEST_NX + i] = diagonal[i] + (d * scale + tiny);
    if (learnest_kalman_factorises(P, margin, work)) return rung;
  }
  return -1;
}

/* The covariance ceiling (NX variances): LEARNEST_MAX_INFLATION times the build's initial
 * variances. */
LEARNEST_KIT void learnest_kalman_ceiling(learnest_real* ceiling) {
  static const learnest_real P0[LEARNEST_KF_NXX] = LEARNEST_DEFAULT_P0;
  int i;
  for (i = 0; i < LEARNEST_NX; ++i) {
    ceiling[i] = (learnest_real)LEARNEST_MAX_INFLATION * P0[i * LEARNEST_NX + i];
  }
}

/* A re-seed's prior covariance: P = diag(ceiling) (column-major or row-major alike). */
LEARNEST_KIT void learnest_kalman_reseed(learnest_real* P) {
  learnest_real ceiling[LEARNEST_NX];
  int i;
  learnest_kalman_ceiling(ceiling);
  for (i = 0; i < LEARNEST_KF_NXX; ++i) P[i] = 0;
  for (i = 0; i < LEARNEST_NX; ++i) P[i * LEARNEST_NX + i] = ceiling[i];
}

/* The end of a step: x_post and P_post (column-major, overwritten) must be finite, P_post
 * symmetric (it is symmetrised) and positive semidefinite to rounding (P - K S K^T can lose it
 * from extreme but valid covariances; such a P would poison every later step, so it is an
 * error, not an OK), and it is kept positive definite (learnest_kalman_keep_pd: a P that is
 * singular to rounding gets its diagonal loaded by a few epsilons); then the gate books the
 * step (rejected, valid: NY flags each), its recovery grows the variances (the covariances
 * stay, so stale correlations fade), the variances are capped at the ceiling and the step is
 * committed. */
LEARNEST_KIT int learnest_kalman_commit(LEARNEST_HANDLE* h, const learnest_real* x_post,
                                        learnest_real* P_post, const int* rejected,
                                        const unsigned char* valid) {
  learnest_real work[LEARNEST_KF_NXX], ceiling[LEARNEST_NX], factor;
  int i, any = 0;
  if (!learnest_all_finite(x_post, LEARNEST_NX) || !learnest_all_finite(P_post, LEARNEST_KF_NXX)) {
    return LEARNEST_NONFINITE_RESULT;
  }
  learnest_symmetrise(P_post, LEARNEST_NX);
  if (!learnest_covariance_ok(P_post, LEARNEST_NX, work)) return LEARNEST_NOT_POSITIVE_DEFINITE;
  if (learnest_kalman_keep_pd(P_post, work) < 0) return LEARNEST_NOT_POSITIVE_DEFINITE;
  for (i = 0; i < LEARNEST_NY; ++i) any |= rejected[i];
  factor = learnest_gate_record(&h->c.gate, rejected, valid);
  for (i = 0; factor != 1 && i < LEARNEST_NX; ++i) P_post[i * LEARNEST_NX + i] *= factor;
  learnest_kalman_ceiling(ceiling);
  (void)learnest_cap_variances(P_post, LEARNEST_NX, ceiling, work);
  memcpy(h->x, x_post, sizeof h->x);
  memcpy(h->P, P_post, sizeof h->P);
  return any ? LEARNEST_MEASUREMENT_REJECTED : LEARNEST_OK;
}

/* Defined by the including file (learnest_ukf.h, learnest_ekf.h). */
LEARNEST_KIT int learnest_est_step(LEARNEST_HANDLE* h, const learnest_real* u,
                                   const learnest_real* y, const unsigned char* valid,
                                   int* rejected);

#include "learnest_api.h"

int LEARNEST_API(get_covariance)(const LEARNEST_HANDLE* h, learnest_real* P) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (!P) return LEARNEST_BAD_ARGUMENT;
  learnest_transpose(P, h->P, LEARNEST_NX);
  return LEARNEST_OK;
}

#endif /* LEARNEST_KALMAN_H */
