/* learnest_ekf.h -- an extended Kalman filter on the kit: the worked example of docs/c_kit.md's
 * "add an estimator" recipe (the UKF's conventions and guards, learnest_kalman.h, with the
 * model's Jacobians where the UKF has sigma points). tests/test_ckit.py builds it over a linear
 * model, where it must equal FilterPy's Kalman filter; no generator uses it yet.
 *
 * Include after learnest_kit.h with LEARNEST_PREFIX, LEARNEST_NX, LEARNEST_NU, LEARNEST_NY and
 * the model hooks of learnest_gn.h: learnest_model_stage (F, A = dF/dx) and
 * learnest_model_node (h, C = dh/dx), column-major.
 */
#ifndef LEARNEST_EKF_H
#define LEARNEST_EKF_H

#include "learnest_kalman.h"
#include "learnest_update.h"

/* The predicted outputs' covariance S = C P C' + R and P C' (column-major) of the prior P. */
LEARNEST_KIT void learnest_ekf_innovation(const LEARNEST_HANDLE* h, const learnest_real* P,
                                          const learnest_real* C, learnest_real* PCt,
                                          learnest_real* S) {
  int j, k;
  learnest_mat_mul_t(P, C, LEARNEST_NX, LEARNEST_NX, LEARNEST_NY, PCt);
  learnest_mat_mul(C, PCt, LEARNEST_NY, LEARNEST_NX, LEARNEST_NY, S);
  for (j = 0; j < LEARNEST_NY; ++j) {
    for (k = 0; k < LEARNEST_NY; ++k) S[j + k * LEARNEST_NY] += h->R[j + k * LEARNEST_NY];
  }
}

/* One sample: x = F(x, u), P = A P A' + Q (not on the first sample), then the Kalman update on
 * the valid outputs the gate keeps (learnest_masked_gain_update); a lost estimate re-seeds: the
 * update of the prior covariance diag(ceiling) by every valid output. */
LEARNEST_KIT int learnest_est_step(LEARNEST_HANDLE* h, const learnest_real* u,
                                   const learnest_real* y, const unsigned char* valid,
                                   int* rejected) {
  learnest_real x[LEARNEST_NX], P[LEARNEST_KF_NXX], A[LEARNEST_KF_NXX], AP[LEARNEST_KF_NXX];
  learnest_real hx[LEARNEST_NY], C[LEARNEST_NY * LEARNEST_NX], PCt[LEARNEST_NX * LEARNEST_NY];
  learnest_real S[LEARNEST_KF_NYY], z[LEARNEST_NY], d2[LEARNEST_NY];
  int i, j, keep[LEARNEST_NY];
  memcpy(x, h->x, sizeof x);
  memcpy(P, h->P, sizeof P);
  if (h->c.samples > 0) {
    learnest_model_stage(&h->model, h->x, u, x, A);
    learnest_mat_mul(A, h->P, LEARNEST_NX, LEARNEST_NX, LEARNEST_NX, AP);
    learnest_mat_mul_t(AP, A, LEARNEST_NX, LEARNEST_NX, LEARNEST_NX, P);
    for (i = 0; i < LEARNEST_KF_NXX; ++i) P[i] += h->Q[i];
  }
  learnest_model_node(&h->model, x, u, hx, C);
  learnest_ekf_innovation(h, P, C, PCt, S);
  for (j = 0; j < LEARNEST_NY; ++j) {
    z[j] = y[j] - hx[j];
    d2[j] = z[j] * z[j] / S[j + j * LEARNEST_NY];
  }
  if (learnest_gate_test(&h->c.gate, d2, valid, LEARNEST_NY, rejected)
      && learnest_gate_reseeds(&h->c.gate, rejected)) {
    learnest_kalman_reseed(P);
    learnest_ekf_innovation(h, P, C, PCt, S);
  }
  for (j = 0; j < LEARNEST_NY; ++j) keep[j] = valid[j] && !rejected[j];
  if (!learnest_masked_gain_update(P, PCt, S, keep, z, x)) return LEARNEST_NOT_POSITIVE_DEFINITE;
  return learnest_kalman_commit(h, x, P, rejected, valid);
}

#endif /* LEARNEST_EKF_H */
