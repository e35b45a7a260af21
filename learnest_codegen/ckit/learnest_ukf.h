/* learnest_ukf.h -- the Unscented Kalman Filter's host-side logic and API (docs/c_api.md).
 *
 * The sigma-point arithmetic is the model's (codegen/ukf.py generates FilterPy's predict and
 * a masked update as CasADi code); this file adds what runs around it: the sample convention
 * (the first sample after init/reset has no transition), missing outputs, the innovation gate
 * and its recovery, the covariance guards, and the API of learnest_api.h.
 *
 * Include after learnest_kit.h with LEARNEST_PREFIX, LEARNEST_NX, LEARNEST_NU, LEARNEST_NY and
 * the model:
 *   struct learnest_model; learnest_model_predict(md, x, P, u, Q, x_prior, P_prior) and
 *   learnest_model_update(md, x, P, u, y, R, mask, x_post, P_post, d2), matrices
 *   column-major, returning 0 on success (learnest_casadi.h gives them for CasADi code).
 */
#ifndef LEARNEST_UKF_H
#define LEARNEST_UKF_H

#include "learnest_dense.h"
#include "learnest_handle.h"

#define LEARNEST_UKF_NXX (LEARNEST_NX * LEARNEST_NX)
#define LEARNEST_UKF_NYY (LEARNEST_NY * LEARNEST_NY)
#define LEARNEST_UKF_NMAX (LEARNEST_NX > LEARNEST_NY ? LEARNEST_NX : LEARNEST_NY)

LEARNEST_HANDLE {
  struct learnest_common c;
  /* Filter state; the model reads matrices column-major, the API speaks row-major. */
  learnest_real x[LEARNEST_NX], P[LEARNEST_UKF_NXX], Q[LEARNEST_UKF_NXX], R[LEARNEST_UKF_NYY];
  struct learnest_model model;
};

struct learnest_ukf_tuning {
  learnest_real P0[LEARNEST_UKF_NXX], Q[LEARNEST_UKF_NXX], R[LEARNEST_UKF_NYY];  /* col-major */
};
typedef struct learnest_ukf_tuning learnest_tuning;

/* One covariance (n x n, row-major) checked: finite, symmetric and positive semidefinite to
 * rounding; dst = its column-major copy. */
LEARNEST_KIT int learnest_ukf_covariance(const learnest_real* A, int n, learnest_real* dst) {
  learnest_real work[LEARNEST_UKF_NMAX * LEARNEST_UKF_NMAX];
  if (!learnest_all_finite(A, n * n)) return LEARNEST_NONFINITE_INPUT;
  if (!learnest_covariance_ok(A, n, work)) return LEARNEST_NOT_POSITIVE_DEFINITE;
  learnest_transpose(dst, A, n);
  return LEARNEST_OK;
}

LEARNEST_KIT int learnest_est_tune(learnest_tuning* t, const learnest_real* P0,
                                   const learnest_real* Q, const learnest_real* R) {
  learnest_tuning c;
  int code = P0 ? learnest_ukf_covariance(P0, LEARNEST_NX, c.P0) : LEARNEST_OK;
  if (code == LEARNEST_OK && Q) code = learnest_ukf_covariance(Q, LEARNEST_NX, c.Q);
  if (code == LEARNEST_OK && R) code = learnest_ukf_covariance(R, LEARNEST_NY, c.R);
  if (code != LEARNEST_OK) return code;
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

/* One sample: predict with u (not on the first sample after init/reset), update with the
 * valid outputs of y, gate them, guard the covariance, recover; commit only on success. */
LEARNEST_KIT int learnest_est_step(LEARNEST_HANDLE* h, const learnest_real* u,
                                   const learnest_real* y, const unsigned char* valid,
                                   int* rejected) {
  learnest_real x_prior[LEARNEST_NX], P_prior[LEARNEST_UKF_NXX], x_post[LEARNEST_NX];
  learnest_real P_post[LEARNEST_UKF_NXX], d2[LEARNEST_NY], mask[LEARNEST_NY], factor;
  learnest_real work[LEARNEST_UKF_NXX];
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
     * rejected, and the update is redone without it. */
    if (rc == 0) any = learnest_gate_test(&h->c.gate, d2, valid, LEARNEST_NY, rejected);
    if (rc == 0 && any) {
      for (i = 0; i < LEARNEST_NY; ++i) mask[i] = valid[i] && !rejected[i];
      rc = learnest_model_update(&h->model, x_prior, P_prior, u, y, h->R, mask, x_post, P_post, d2);
    }
  } else if (rc == 0) {  /* no output: the prediction stands */
    memcpy(x_post, x_prior, sizeof x_post);
    memcpy(P_post, P_prior, sizeof P_post);
  }
  /* A failed Cholesky shows up as NaN (sqrt of a negative pivot): commit finite results only. */
  if (rc != 0 || !learnest_all_finite(x_post, LEARNEST_NX)
      || !learnest_all_finite(P_post, LEARNEST_UKF_NXX)) {
    return LEARNEST_NONFINITE_RESULT;
  }
  /* PSD guard: P - K S K^T can lose symmetry or definiteness from extreme (valid) covariances
   * in rounding; such a P would poison every later step, so it is an error, not an OK. */
  learnest_symmetrise(P_post, LEARNEST_NX);
  if (!learnest_covariance_ok(P_post, LEARNEST_NX, work)) return LEARNEST_NOT_POSITIVE_DEFINITE;
  /* Recovery: the variances (diagonal) grow by the factor, the covariances stay, so the
   * correlations fade and a re-acquired gross innovation moves the measured states only. */
  factor = learnest_gate_record(&h->c.gate, any, any_valid);
  for (i = 0; factor != 1 && i < LEARNEST_NX; ++i) P_post[i * LEARNEST_NX + i] *= factor;
  memcpy(h->x, x_post, sizeof h->x);
  memcpy(h->P, P_post, sizeof h->P);
  return any ? LEARNEST_MEASUREMENT_REJECTED : LEARNEST_OK;
}

#include "learnest_api.h"

int LEARNEST_API(get_covariance)(const LEARNEST_HANDLE* h, learnest_real* P) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (!P) return LEARNEST_BAD_ARGUMENT;
  learnest_transpose(P, h->P, LEARNEST_NX);
  return LEARNEST_OK;
}

#endif /* LEARNEST_UKF_H */
