/* kit_linear.h -- a linear model x+ = A x + B u, y = C x behind the kit's model hooks, and the
 * glue an estimator's generated file would hold, for tests/test_ckit.py. The matrices are set
 * at run time (kt_set_model, defined by KIT_LINEAR_SET_MODEL after the estimator); the sizes are
 * the test system's (2 states, 1 input, 2 outputs) unless the includer defines LEARNEST_NX,
 * LEARNEST_NY and the defaults of its own size first.
 */
#ifndef KIT_LINEAR_H
#define KIT_LINEAR_H

#ifndef KIT_REAL
#define KIT_REAL double
#endif
#define LEARNEST_REAL KIT_REAL
#ifndef LEARNEST_NX
#define LEARNEST_NX 2
#define LEARNEST_NY 2
#define LEARNEST_DEFAULT_X0 {1.0, 0.0}
#define LEARNEST_DEFAULT_P0 {0.25, 0.0, 0.0, 0.25}
#define LEARNEST_DEFAULT_Q {1e-6, 0.0, 0.0, 1e-4}
#define LEARNEST_DEFAULT_R {0.0025, 0.0, 0.0, 0.01}
#endif
#define LEARNEST_NU 1
#define LEARNEST_DT 0.05
#define LEARNEST_WORKSPACE_BYTES 65536
#define LEARNEST_MAGIC 0x4B495431u
#define LEARNEST_FINGERPRINT "learnest kit test"
#define LEARNEST_DEFAULT_THRESHOLD 50.8
#define LEARNEST_DEFAULT_RECOVER_AFTER 10
#define LEARNEST_DEFAULT_INFLATION 2.0
#define LEARNEST_MAX_INFLATION 1e4
#include "learnest_kit.h"
#include "learnest_dense.h"

typedef learnest_real real;
#define NX LEARNEST_NX
#define NU LEARNEST_NU
#define NY LEARNEST_NY

/* Column-major, as CasADi's Jacobians. */
struct learnest_model {
  real A[NX * NX], B[NX * NU], C[NY * NX];
};

static void kt_matvec(const real* M, int rows, int cols, const real* v, real* out) {
  int i, j;
  for (i = 0; i < rows; ++i) {
    out[i] = 0;
    for (j = 0; j < cols; ++j) out[i] += M[i + j * rows] * v[j];
  }
}

static void learnest_model_F(struct learnest_model* m, const real* x, const real* u, real* F) {
  real Bu[NX];
  int i;
  kt_matvec(m->A, NX, NX, x, F);
  kt_matvec(m->B, NX, NU, u, Bu);
  for (i = 0; i < NX; ++i) F[i] += Bu[i];
}

/* The Gauss-Newton core's and the EKF's hooks: F and A = dF/dx, h and C = dh/dx. */
LEARNEST_KIT void learnest_model_stage(struct learnest_model* m, const real* x, const real* u,
                                       real* F, real* A) {
  learnest_model_F(m, x, u, F);
  memcpy(A, m->A, sizeof m->A);
}

LEARNEST_KIT void learnest_model_node(struct learnest_model* m, const real* x, const real* u,
                                      real* h, real* C) {
  (void)u;
  kt_matvec(m->C, NY, NX, x, h);
  memcpy(C, m->C, sizeof m->C);
}

#ifdef __cplusplus
#define KIT_EXTERN extern "C"
#else
#define KIT_EXTERN
#endif

/* After the estimator's kit file: the model's matrices (column-major) into a handle. */
#define KIT_LINEAR_SET_MODEL                                                                   \
  KIT_EXTERN int kt_set_model(LEARNEST_HANDLE* h, const real* A, const real* B, const real* C) {           \
    if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;                                 \
    memcpy(h->model.A, A, sizeof h->model.A);                                                    \
    memcpy(h->model.B, B, sizeof h->model.B);                                                    \
    memcpy(h->model.C, C, sizeof h->model.C);                                                    \
    return LEARNEST_OK;                                                                          \
  }

#endif /* KIT_LINEAR_H */
