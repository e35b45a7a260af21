/* learnest_mhe_api.h -- the API of both MHEs: learnest_api.h's, and the window, the arrival
 * covariance and its run-time tuning. init/reset's P0 is the covariance of the first prior
 * x0 (carried forward while larger than the running arrival covariance, learnest_mhe.h);
 * set_arrival/get_arrival are the running arrival covariance (default: the build's).
 *
 * Included at the end of learnest_mhe_gn.h and learnest_mhe_ipopt.h, whose LEARNEST_HANDLE
 * has struct learnest_mhe m, and which define before it learnest_est_defaults, _start, _step
 * and learnest_est_retuned(h) (called after the weights of h->m.now changed).
 */
#ifndef LEARNEST_MHE_API_H
#define LEARNEST_MHE_API_H

#include "learnest_mhe.h"

/* init/reset: P0 the first prior's covariance, Q, R; the running arrival covariance goes back
 * to the build's default (LEARNEST_DEFAULT_P0, set_arrival changes it). */
LEARNEST_KIT int learnest_est_tune(learnest_tuning* t, const learnest_real* P0,
                                   const learnest_real* Q, const learnest_real* R) {
  static const learnest_real W_cov[LEARNEST_NXX] = LEARNEST_DEFAULT_P0;
  int code = learnest_mhe_tune(t, P0, Q, R);
  if (code != LEARNEST_OK) return code;
  return learnest_mhe_covariance(W_cov, LEARNEST_NX, t->W_cov, t->W);
}

/* Run-time tuning: new covariances for the next steps; the window, its solution and the gate
 * stay. NULL keeps one. P_arr is the running arrival covariance (learnest_mhe_set_tuning). */
LEARNEST_KIT int learnest_mhe_retune(LEARNEST_HANDLE* h, const learnest_real* P_arr,
                                     const learnest_real* Q, const learnest_real* R) {
  struct learnest_mhe_tuning t;
  int code;
  memset(&t, 0, sizeof t);
  code = learnest_mhe_tune(&t, P_arr, Q, R);
  if (code != LEARNEST_OK) return code;
  learnest_mhe_set_tuning(&h->m, &t, P_arr != 0, Q != 0, R != 0);
  learnest_est_retuned(h);
  return LEARNEST_OK;
}

LEARNEST_KIT int learnest_est_set_noise(LEARNEST_HANDLE* h, const learnest_real* Q,
                                        const learnest_real* R) {
  return learnest_mhe_retune(h, 0, Q, R);
}

LEARNEST_KIT const learnest_real* learnest_est_state(const LEARNEST_HANDLE* h) {
  return h->m.X + LEARNEST_N * LEARNEST_NX;
}

#include "learnest_api.h"

int LEARNEST_API(set_arrival)(LEARNEST_HANDLE* h, const learnest_real* P0) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (!P0) return LEARNEST_BAD_ARGUMENT;
  return learnest_mhe_retune(h, P0, 0, 0);
}

int LEARNEST_API(get_arrival)(const LEARNEST_HANDLE* h, learnest_real* P0) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (!P0) return LEARNEST_BAD_ARGUMENT;
  memcpy(P0, h->m.P_cov, sizeof h->m.P_cov);
  return LEARNEST_OK;
}

int LEARNEST_API(get_arrival_weight)(const LEARNEST_HANDLE* h, learnest_real* P) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (!P) return LEARNEST_BAD_ARGUMENT;
  memcpy(P, h->m.now.P, sizeof h->m.now.P);  /* symmetric: row- and column-major alike */
  return LEARNEST_OK;
}

int LEARNEST_API(get_window)(const LEARNEST_HANDLE* h, learnest_real* X) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (!X) return LEARNEST_BAD_ARGUMENT;
  memcpy(X, h->m.X, sizeof h->m.X);
  return LEARNEST_OK;
}

#endif /* LEARNEST_MHE_API_H */
