/* kit_ukf.c -- the UKF of the C kit (learnest_ukf.h) over a linear model whose predict and
 * masked update are the Kalman filter's (the sigma-point arithmetic is CasADi's in a generated
 * estimator; here the kit's host logic is under test): prefix tukf. */
#include "kit_linear.h"

#define LEARNEST_PREFIX tukf

/* x' = A x + B u, P' = A P A' + Q. */
static int learnest_model_predict(struct learnest_model* m, const real* x, const real* P,
                                  const real* u, const real* Q, real* x_prior, real* P_prior) {
  real AP[NX * NX];
  int i, j, k;
  learnest_model_F(m, x, u, x_prior);
  for (i = 0; i < NX; ++i) {
    for (j = 0; j < NX; ++j) {
      AP[i + j * NX] = 0;
      for (k = 0; k < NX; ++k) AP[i + j * NX] += m->A[i + k * NX] * P[k + j * NX];
    }
  }
  for (i = 0; i < NX; ++i) {
    for (j = 0; j < NX; ++j) {
      real v = Q[i + j * NX];
      for (k = 0; k < NX; ++k) v += AP[i + k * NX] * m->A[j + k * NX];
      P_prior[i + j * NX] = v;
    }
  }
  return 0;
}

/* The Kalman update on the outputs mask keeps (M S M + (I - M), P C' M: the generated UKF's
 * rule), and d2_j = (y - C x)_j^2 / S_jj. */
static int learnest_model_update(struct learnest_model* m, const real* x, const real* P,
                                 const real* u, const real* y, const real* R, const real* mask,
                                 real* x_post, real* P_post, real* d2) {
  real PCt[NX * NY], S[NY * NY], Si[NY * NY], L[NY * NY], K[NX * NY], nu[NY], yhat[NY];
  int i, j, k;
  (void)u;
  kt_matvec(m->C, NY, NX, x, yhat);
  for (i = 0; i < NX; ++i) {
    for (j = 0; j < NY; ++j) {
      PCt[i + j * NX] = 0;
      for (k = 0; k < NX; ++k) PCt[i + j * NX] += P[i + k * NX] * m->C[j + k * NY];
    }
  }
  for (i = 0; i < NY; ++i) {
    for (j = 0; j < NY; ++j) {
      real v = R[i + j * NY];
      for (k = 0; k < NX; ++k) v += m->C[i + k * NY] * PCt[k + j * NX];
      S[i + j * NY] = v;
    }
    nu[i] = y[i] - yhat[i];
  }
  for (i = 0; i < NY; ++i) d2[i] = nu[i] * nu[i] / S[i + i * NY];
  for (i = 0; i < NY; ++i) {
    for (j = 0; j < NY; ++j) S[i + j * NY] = mask[i] * mask[j] * S[i + j * NY] + (i == j) * (1 - mask[i]);
  }
  if (!learnest_spd_inverse(S, NY, Si, L)) return 1;
  for (i = 0; i < NX; ++i) {
    for (j = 0; j < NY; ++j) {
      K[i + j * NX] = 0;
      for (k = 0; k < NY; ++k) K[i + j * NX] += PCt[i + k * NX] * mask[k] * Si[k + j * NY];
    }
  }
  for (i = 0; i < NX; ++i) {
    x_post[i] = x[i];
    for (j = 0; j < NY; ++j) x_post[i] += K[i + j * NX] * mask[j] * nu[j];
  }
  for (i = 0; i < NX; ++i) {  /* P - K S K' = P - K M C P (M S M K' = M C P) */
    for (j = 0; j < NX; ++j) {
      real v = P[i + j * NX];
      for (k = 0; k < NY; ++k) v -= K[i + k * NX] * mask[k] * PCt[j + k * NX];
      P_post[i + j * NX] = v;
    }
  }
  return 0;
}

#include "learnest_ukf.h"

KIT_LINEAR_SET_MODEL
