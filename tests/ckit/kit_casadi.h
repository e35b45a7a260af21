/* kit_casadi.h -- the linear model x+ = A x + B u, y = C x written by hand in CasADi's calling
 * convention, f(arg, res, iw, w, mem) (what CasADi's code generator writes for a model), so
 * that learnest_casadi.h's hooks run without generated code (tests/test_ckit.py). The matrices
 * are set at run time (kt_set_model); the sizes are the test system's (2 states, 1 input, 2
 * outputs). The includer names the functions its estimator uses (LEARNEST_MODEL_F kc_F, ...),
 * then includes learnest_casadi.h.
 */
#ifndef KIT_CASADI_H
#define KIT_CASADI_H

#ifndef KIT_REAL
#define KIT_REAL double
#endif
#define casadi_real KIT_REAL
#define casadi_int long long int
#define LEARNEST_REAL casadi_real
#define LEARNEST_NX 2
#define LEARNEST_NU 1
#define LEARNEST_NY 2
#define LEARNEST_DT 0.05
#define LEARNEST_WORKSPACE_BYTES 65536
#define LEARNEST_MAGIC 0x4B495432u
#define LEARNEST_FINGERPRINT "learnest kit casadi test"
#define LEARNEST_DEFAULT_X0 {1.0, 0.0}
#define LEARNEST_DEFAULT_P0 {0.25, 0.0, 0.0, 0.25}
#define LEARNEST_DEFAULT_Q {1e-6, 0.0, 0.0, 1e-4}
#define LEARNEST_DEFAULT_R {0.0025, 0.0, 0.0, 0.01}
#define LEARNEST_DEFAULT_THRESHOLD 50.8
#define LEARNEST_DEFAULT_RECOVER_AFTER 10
#define LEARNEST_DEFAULT_INFLATION 2.0
#define LEARNEST_MAX_INFLATION 1e4
/* The work arrays' sizes, the largest over the functions (an nlpsol: 8 inputs, 6 outputs). */
#define LEARNEST_CASADI_SZ_ARG 8
#define LEARNEST_CASADI_SZ_RES 6
#define LEARNEST_CASADI_SZ_IW 0
#define LEARNEST_CASADI_SZ_W 0
#include "learnest_kit.h"

#define KC_NX LEARNEST_NX
#define KC_NU LEARNEST_NU
#define KC_NY LEARNEST_NY

#ifdef __cplusplus
#define KIT_EXTERN extern "C"
#else
#define KIT_EXTERN
#endif

/* Column-major, as CasADi's Jacobians. */
static casadi_real kc_A[KC_NX * KC_NX], kc_B[KC_NX * KC_NU], kc_C[KC_NY * KC_NX];

/* The model's matrices (column-major); the handle is kit_linear.h's argument, unused: the
 * functions, as CasADi's, hold no state of an estimator. */
KIT_EXTERN int kt_set_model(const void* h, const casadi_real* A, const casadi_real* B,
                            const casadi_real* C) {
  (void)h;
  memcpy(kc_A, A, sizeof kc_A);
  memcpy(kc_B, B, sizeof kc_B);
  memcpy(kc_C, C, sizeof kc_C);
  return 0;
}

LEARNEST_KIT void kc_matvec(const casadi_real* M, int rows, int cols, const casadi_real* v, casadi_real* out) {
  int i, j;
  for (i = 0; i < rows; ++i) {
    out[i] = 0;
    for (j = 0; j < cols; ++j) out[i] += M[i + j * rows] * v[j];
  }
}

/* The model's functions, each with CasADi's signature and its outputs only (as generated code
 * writes no more outputs than its function has). */
#define KC_FUNCTION(name) \
  LEARNEST_KIT int name(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w, int mem)

/* (x, u) -> F = A x + B u */
KC_FUNCTION(kc_F) {
  casadi_real Bu[KC_NX];
  int i;
  (void)iw, (void)w, (void)mem;
  kc_matvec(kc_A, KC_NX, KC_NX, arg[0], res[0]);
  kc_matvec(kc_B, KC_NX, KC_NU, arg[1], Bu);
  for (i = 0; i < KC_NX; ++i) res[0][i] += Bu[i];
  return 0;
}

/* (x, u) -> (F, A = dF/dx) */
KC_FUNCTION(kc_stage) {
  memcpy(res[1], kc_A, sizeof kc_A);
  return kc_F(arg, res, iw, w, mem);
}

/* (x, u) -> h = C x */
KC_FUNCTION(kc_h) {
  (void)iw, (void)w, (void)mem;
  kc_matvec(kc_C, KC_NY, KC_NX, arg[0], res[0]);
  return 0;
}

/* (x, u) -> (h, C = dh/dx) */
KC_FUNCTION(kc_node) {
  memcpy(res[1], kc_C, sizeof kc_C);
  return kc_h(arg, res, iw, w, mem);
}

#endif /* KIT_CASADI_H */
