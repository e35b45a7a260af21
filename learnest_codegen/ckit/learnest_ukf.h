/* learnest_ukf.h -- the Unscented Kalman Filter's host-side logic and API (docs/c_api.md).
 *
 * The sigma-point arithmetic is the model's (codegen/ukf.py generates FilterPy's predict and
 * a masked update as CasADi code); this file adds what runs around it: the sample convention
 * (the first sample after init/reset has no transition), missing outputs and the innovation
 * gate; the covariance guards, the recovery and the API are learnest_kalman.h's.
 *
 * Include after learnest_kit.h with LEARNEST_PREFIX, LEARNEST_NX, LEARNEST_NU, LEARNEST_NY and
 * the model:
 *   struct learnest_model; learnest_model_predict(md, x, P, u, Q, x_prior, P_prior) and
 *   learnest_model_update(md, x, P, u, y, R, mask, x_post, P_post, d2), matrices
 *   column-major, returning 0 on success (learnest_casadi.h gives them for CasADi code).
 */
#ifndef LEARNEST_UKF_H
#define LEARNEST_UKF_H

#include "learnest_kalman.h"

/* One sample: predict with u (not on the first sample after init/reset), update with the
 * valid outputs of y, gate them, guard the covariance, recover; commit only on success. */
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
  if (rc != 0) return LEARNEST_NONFINITE_RESULT;
  return learnest_kalman_commit(h, x_post, P_post, rejected, valid);
}

#endif /* LEARNEST_UKF_H */
