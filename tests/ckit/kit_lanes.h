/* kit_lanes.h -- a nonlinear model written by hand in CasADi's calling convention, in the
 * scalar form and in the lane-parallel form a generated model's batch copy has
 * (codegen/casadi_c.py), so that the kit's lane-parallel paths (learnest_simd.h's routines,
 * learnest_casadi.h's batch hooks and lane gather/scatter, the UKF's batched sigma points, the
 * embedded MHE's batched stages) run without generated code (tests/test_ckit.py).
 *
 * A damped pendulum with a drag term, one explicit Euler step of dt (the sizes, defaults and
 * work arrays of kit_casadi.h: 2 states, 1 input, 2 outputs):
 *   F0 = x0 + dt x1
 *   F1 = x1 + dt ((b u) cos x0 - g sin x0 - (c tanh x1 + d x1 |x1|))
 *   h  = (x0, x1)
 * Each expression is written once (KL_F0, KL_F1, KL_A10, KL_A11) over the names of its
 * routines, and instantiated with learnest_math.h's scalar routines and with learnest_simd.h's
 * vector ones: lane by lane the same operations, so the batch gives the scalar bits.
 *
 * The batch functions, kl_F_batch and kl_stage_batch, take entry j of point l at
 * arg[.][j * KL_LANES + l] and write results the same way (KL_LANES: 4 doubles or 8 floats);
 * they exist where learnest_simd.h has vectors (LEARNEST_SIMD 1: GCC, C, x86-64).
 */
#ifndef KIT_LANES_H
#define KIT_LANES_H

#include "kit_casadi.h"
#include "learnest_simd.h"

#define KL_G ((casadi_real)4.0)
#define KL_B ((casadi_real)1.0)
#define KL_C ((casadi_real)0.5)
#define KL_D ((casadi_real)0.1)
#define KL_DT ((casadi_real)LEARNEST_DT)
#define KL_ONE ((casadi_real)1.0)
#define KL_TWO ((casadi_real)2.0)

/* The model's expressions over the routines SIN, COS, TANH, FABS and SQ (x * x). */
#define KL_F0(x0, x1) (x0 + KL_DT * x1)
#define KL_F1(x0, x1, u, SIN, COS, TANH, FABS) \
  (x1 + KL_DT * (((KL_B * u) * COS(x0) - KL_G * SIN(x0)) - (KL_C * TANH(x1) + KL_D * (x1 * FABS(x1)))))
#define KL_A10(x0, u, SIN, COS) (KL_DT * (-(KL_G * COS(x0)) - (KL_B * u) * SIN(x0)))
#define KL_A11(x1, TANH, FABS, SQ) \
  (KL_ONE + KL_DT * (-(KL_C * (KL_ONE - SQ(TANH(x1)))) - (KL_TWO * KL_D) * FABS(x1)))

LEARNEST_KIT casadi_real kl_sq(casadi_real x) { return x * x; }

/* (x, u) -> F */
KC_FUNCTION(kl_F) {
  const casadi_real* x = arg[0];
  casadi_real u = arg[1][0];
  (void)iw, (void)w, (void)mem;
  res[0][0] = KL_F0(x[0], x[1]);
  res[0][1] = KL_F1(x[0], x[1], u, learnest_sin, learnest_cos, learnest_tanh, learnest_fabs);
  return 0;
}

/* (x, u) -> (F, A = dF/dx), A column-major */
KC_FUNCTION(kl_stage) {
  const casadi_real* x = arg[0];
  casadi_real u = arg[1][0];
  (void)iw, (void)w, (void)mem;
  res[1][0] = KL_ONE;
  res[1][1] = KL_A10(x[0], u, learnest_sin, learnest_cos);
  res[1][2] = KL_DT;
  res[1][3] = KL_A11(x[1], learnest_tanh, learnest_fabs, kl_sq);
  return kl_F(arg, res, iw, w, mem);
}

/* (x, u) -> h = x */
KC_FUNCTION(kl_h) {
  (void)arg, (void)iw, (void)w, (void)mem;
  memcpy(res[0], arg[0], KC_NX * sizeof(casadi_real));
  return 0;
}

/* (x, u) -> (h, C = dh/dx = I) */
KC_FUNCTION(kl_node) {
  res[1][0] = res[1][3] = 1, res[1][1] = res[1][2] = 0;
  return kl_h(arg, res, iw, w, mem);
}

#if LEARNEST_SIMD
#define KL_CAT_(a, b) a##b
#define KL_CAT(a, b) KL_CAT_(a, b)
#define KL_FLOAT_float 1
#if KL_CAT(KL_FLOAT_, KIT_REAL)
#define KL_LANES 8
#define KL_V(name) learnest_v##name##_f
typedef learnest_v8f kl_vec;
#else
#define KL_LANES 4
#define KL_V(name) learnest_v##name##_d
typedef learnest_v4d kl_vec;
#endif

/* F on KL_LANES points at once. */
LEARNEST_SIMD_BATCH int kl_F_batch(const casadi_real** arg, casadi_real** res) {
  kl_vec x0, x1, u, F0, F1;
  memcpy(&x0, arg[0], sizeof x0);
  memcpy(&x1, arg[0] + KL_LANES, sizeof x1);
  memcpy(&u, arg[1], sizeof u);
  F0 = KL_F0(x0, x1);
  F1 = KL_F1(x0, x1, u, KL_V(sin), KL_V(cos), KL_V(tanh), KL_V(fabs));
  memcpy(res[0], &F0, sizeof F0);
  memcpy(res[0] + KL_LANES, &F1, sizeof F1);
  return 0;
}

/* (F, A) on KL_LANES points at once. */
LEARNEST_SIMD_BATCH int kl_stage_batch(const casadi_real** arg, casadi_real** res) {
  kl_vec x0, x1, u, A00 = KL_V(dup)(KL_ONE), A10, A01 = KL_V(dup)(KL_DT), A11;
  memcpy(&x0, arg[0], sizeof x0);
  memcpy(&x1, arg[0] + KL_LANES, sizeof x1);
  memcpy(&u, arg[1], sizeof u);
  A10 = KL_A10(x0, u, KL_V(sin), KL_V(cos));
  A11 = KL_A11(x1, KL_V(tanh), KL_V(fabs), KL_V(sq));
  memcpy(res[1], &A00, sizeof A00);
  memcpy(res[1] + KL_LANES, &A10, sizeof A10);
  memcpy(res[1] + 2 * KL_LANES, &A01, sizeof A01);
  memcpy(res[1] + 3 * KL_LANES, &A11, sizeof A11);
  return kl_F_batch(arg, res);
}

#define LEARNEST_MODEL_F_BATCH kl_F_batch
#define LEARNEST_MODEL_F_LANES KL_LANES
#define LEARNEST_MODEL_STAGE_BATCH kl_stage_batch
#define LEARNEST_MODEL_STAGE_LANES KL_LANES
#endif

#define LEARNEST_MODEL_STAGE kl_stage
#define LEARNEST_MODEL_NODE kl_node
#define LEARNEST_MODEL_F kl_F
#define LEARNEST_MODEL_H kl_h
#include "learnest_casadi.h"

/* The model's hooks on n points (point k's x at X + k NX, u at U + k NU; F and A likewise, A
 * NULL: F only), through the lane-parallel hooks batch by batch as the estimators call them
 * (lanes = 1: one scalar hook call a point). Returns the lanes used: 0 where the build has no
 * vectors (and lanes > 1 was asked). */
KIT_EXTERN int kl_model_points(int lanes, int n, const casadi_real* X, const casadi_real* U,
                               casadi_real* F, casadi_real* A) {
  static struct learnest_model md;
  int k;
  if (lanes == 1) {
    for (k = 0; k < n; ++k) {
      if (A) {
        learnest_model_stage(&md, X + k * KC_NX, U + k * KC_NU, F + k * KC_NX, A + k * KC_NX * KC_NX);
      } else {
        learnest_model_F(&md, X + k * KC_NX, U + k * KC_NU, F + k * KC_NX);
      }
    }
    return 1;
  }
#if LEARNEST_SIMD
  {
    casadi_real xb[KC_NX * KL_LANES], ub[KC_NU * KL_LANES], Fb[KC_NX * KL_LANES];
    casadi_real Ab[KC_NX * KC_NX * KL_LANES];
    for (k = 0; k < n; k += KL_LANES) {
      learnest_lanes_gather(xb, X, KC_NX, k, n - 1, KL_LANES);
      learnest_lanes_gather(ub, U, KC_NU, k, n - 1, KL_LANES);
      if (A) {
        learnest_model_stage_batch(xb, ub, Fb, Ab);
        learnest_lanes_scatter(A, Ab, KC_NX * KC_NX, k, n - 1, KL_LANES);
      } else {
        learnest_model_F_batch(xb, ub, Fb);
      }
      learnest_lanes_scatter(F, Fb, KC_NX, k, n - 1, KL_LANES);
    }
    return KL_LANES;
  }
#else
  return 0;
#endif
}

#endif /* KIT_LANES_H */
