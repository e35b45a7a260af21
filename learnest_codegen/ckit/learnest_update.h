/* learnest_update.h -- the kit's one masked Kalman update: the EKF's (learnest_ekf.h), the
 * MHEs' carried arrival covariance (learnest_mhe_carry) and their recovery's restart prior
 * (learnest_restart_prior). Covariances at the API, this update on covariances inside.
 *
 * Include after learnest_dense.h with LEARNEST_NX and LEARNEST_NY.
 */
#ifndef LEARNEST_UPDATE_H
#define LEARNEST_UPDATE_H

#include "learnest_dense.h"

/* The Kalman update of the covariance P (NX x NX, symmetric: either storage order) and, when
 * x and z are given, of the mean x by the innovation z, on the outputs keep[j] marks, from
 * PCt = P C' (NX x NY) and S = C P C' + R (NY x NY), both column-major and over every output:
 * with M = diag(keep), K = P C' M (M S M + I - M)^-1, x += K M z and P -= K M C P. Returns 1,
 * or 0 (nothing changed) when M S M + I - M is not positive definite; no output kept: 1. */
LEARNEST_KIT int learnest_masked_gain_update(learnest_real* P, const learnest_real* PCt,
                                             const learnest_real* S, const int* keep,
                                             const learnest_real* z, learnest_real* x) {
  learnest_real K[LEARNEST_NX * LEARNEST_NY], Sm[LEARNEST_NY * LEARNEST_NY];
  learnest_real Si[LEARNEST_NY * LEARNEST_NY], L[LEARNEST_NY * LEARNEST_NY];
  int i, j, k, any = 0;
  for (j = 0; j < LEARNEST_NY; ++j) any |= keep[j];
  if (!any) return 1;
  for (j = 0; j < LEARNEST_NY; ++j) {
    for (k = 0; k < LEARNEST_NY; ++k) {
      Sm[j + k * LEARNEST_NY] = (keep[j] && keep[k]) ? S[j + k * LEARNEST_NY] : (learnest_real)(j == k);
    }
  }
  if (!learnest_spd_inverse(Sm, LEARNEST_NY, Si, L)) return 0;
  LEARNEST_UNROLL_BLOCK for (j = 0; j < LEARNEST_NY; ++j) {  /* K = P C' M S^-1 M, x += K z */
    for (i = 0; i < LEARNEST_NX; ++i) {
      learnest_real v = 0;
      LEARNEST_UNROLL_BLOCK for (k = 0; k < LEARNEST_NY; ++k) {
        if (keep[j] && keep[k]) v += PCt[i + k * LEARNEST_NX] * Si[k + j * LEARNEST_NY];
      }
      K[i + j * LEARNEST_NX] = v;
      if (x && z && keep[j]) x[i] += v * z[j];
    }
  }
  for (i = 0; i < LEARNEST_NX; ++i) {  /* P -= K (P C')' = K M C P (K's dropped columns are 0) */
    LEARNEST_UNROLL_BLOCK for (k = 0; k < LEARNEST_NX; ++k) {
      learnest_real v = 0;
      LEARNEST_UNROLL_BLOCK for (j = 0; j < LEARNEST_NY; ++j) v += K[i + j * LEARNEST_NX] * PCt[k + j * LEARNEST_NX];
      P[i * LEARNEST_NX + k] -= v;
    }
  }
  return 1;
}

/* learnest_masked_gain_update with PCt and S computed from P, C (NY x NX, column-major, its
 * structural nonzeros cnz: LEARNEST_NZ) and R (NY x NY, symmetric). */
LEARNEST_KIT int learnest_masked_update(learnest_real* P, const learnest_real* C,
                                        const unsigned char* cnz, const learnest_real* R,
                                        const int* keep, const learnest_real* z, learnest_real* x) {
  learnest_real PCt[LEARNEST_NX * LEARNEST_NY], S[LEARNEST_NY * LEARNEST_NY];
  int i, j, k;
  LEARNEST_UNROLL_BLOCK for (j = 0; j < LEARNEST_NY; ++j) {  /* PCt = P C' */
    for (i = 0; i < LEARNEST_NX; ++i) {
      learnest_real v = 0;
      LEARNEST_UNROLL_BLOCK for (k = 0; k < LEARNEST_NX; ++k) {
        if (LEARNEST_NZ(cnz, j + k * LEARNEST_NY)) v += P[i * LEARNEST_NX + k] * C[j + k * LEARNEST_NY];
      }
      PCt[i + j * LEARNEST_NX] = v;
    }
  }
  LEARNEST_UNROLL_BLOCK for (j = 0; j < LEARNEST_NY; ++j) {  /* S = C P C' + R */
    for (k = 0; k < LEARNEST_NY; ++k) {
      learnest_real v = R[j * LEARNEST_NY + k];
      LEARNEST_UNROLL_BLOCK for (i = 0; i < LEARNEST_NX; ++i) {
        if (LEARNEST_NZ(cnz, j + i * LEARNEST_NY)) v += C[j + i * LEARNEST_NY] * PCt[i + k * LEARNEST_NX];
      }
      S[j + k * LEARNEST_NY] = v;
    }
  }
  return learnest_masked_gain_update(P, PCt, S, keep, z, x);
}

#endif /* LEARNEST_UPDATE_H */
