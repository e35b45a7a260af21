/* learnest_casadi.h -- the kit's model hooks over CasADi-generated functions.
 *
 * CasADi's generated functions share one calling convention, f(arg, res, iw, w, mem), with
 * work arrays sized by the <name>_SZ_ARG/_RES/_IW/_W macros of their header. Include this
 * after the model's header (which defines casadi_real and casadi_int) and after naming the
 * functions the estimator uses; it defines struct learnest_model (the work arrays) and the
 * hooks the kit calls:
 *   LEARNEST_MODEL_STAGE  (x, u) -> (F(x, u), dF/dx)           learnest_model_stage
 *   LEARNEST_MODEL_NODE   (x, u) -> (h(x, u), dh/dx)           learnest_model_node
 *   LEARNEST_MODEL_F      (x, u) -> F(x, u)                    learnest_model_F
 *   LEARNEST_MODEL_H      (x, u) -> h(x, u)                    learnest_model_h
 *   LEARNEST_MODEL_F_BATCH, _F_LANES  F on _LANES points at once  learnest_model_F_batch
 *   LEARNEST_MODEL_STAGE_BATCH, _STAGE_LANES  the same for STAGE  learnest_model_stage_batch
 *                         (the generated lane-parallel copies, learnest_simd.h; used where
 *                         LEARNEST_SIMD is 1)
 *   LEARNEST_MODEL_SOLVER (+ _CHECKOUT, _RELEASE)               the Ipopt MHE's nlpsol
 * and LEARNEST_CASADI_SZ_ARG, _RES, _IW, _W (the largest over them). Every hook is static.
 */
#ifndef LEARNEST_CASADI_H
#define LEARNEST_CASADI_H

#include "learnest_kit.h"

/* + 1: a size may be 0 and ISO C has no zero-size arrays. */
struct learnest_model {
  const casadi_real* arg[LEARNEST_CASADI_SZ_ARG + 1];
  casadi_real* res[LEARNEST_CASADI_SZ_RES + 1];
  casadi_int iw[LEARNEST_CASADI_SZ_IW + 1];
  casadi_real w[LEARNEST_CASADI_SZ_W + 1];
};

typedef int (*learnest_casadi_function)(const casadi_real** arg, casadi_real** res,
                                        casadi_int* iw, casadi_real* w, int mem);

/* f(in..., out...) on the work arrays of md; CasADi's status (SX code: always 0). */
LEARNEST_KIT int learnest_casadi_call(struct learnest_model* md, learnest_casadi_function f,
                                      const learnest_real* const* in, int n_in,
                                      learnest_real* const* out, int n_out) {
  int i;
  for (i = 0; i < n_in; ++i) md->arg[i] = in[i];
  for (i = 0; i < n_out; ++i) md->res[i] = out[i];
  return f(md->arg, md->res, md->iw, md->w, 0);
}

/* A model function's arguments (x, u) and results (a, b; b NULL for one result), in the
 * arrays CasADi's calling convention takes. */
struct learnest_casadi_io {
  const learnest_real* in[2];
  learnest_real* out[2];
};

LEARNEST_KIT_INLINE struct learnest_casadi_io learnest_casadi_io(const learnest_real* x,
                                                                const learnest_real* u,
                                                                learnest_real* a, learnest_real* b) {
  struct learnest_casadi_io io;
  io.in[0] = x, io.in[1] = u, io.out[0] = a, io.out[1] = b;
  return io;
}

/* f(x, u) -> (a, b), or -> a when b is NULL, on the work arrays of md: the model hooks (inlined
 * into each, so every hook calls its CasADi function directly). */
LEARNEST_KIT_INLINE void learnest_casadi_xu(struct learnest_model* md, learnest_casadi_function f,
                                     const learnest_real* x, const learnest_real* u,
                                     learnest_real* a, learnest_real* b) {
  struct learnest_casadi_io io = learnest_casadi_io(x, u, a, b);
  (void)learnest_casadi_call(md, f, io.in, 2, io.out, b ? 2 : 1);
}

/* The hooks: hook(md, x, u, a, b) -> (a, b) = fn(x, u), and hook(md, x, u, a) -> a = fn(x, u). */
#define LEARNEST_CASADI_HOOK2_(hook, fn)                                                      \
  LEARNEST_KIT void hook(struct learnest_model* md, const learnest_real* x, const learnest_real* u, \
                         learnest_real* a, learnest_real* b) {                                \
    learnest_casadi_xu(md, fn, x, u, a, b);                                                  \
  }
#define LEARNEST_CASADI_HOOK1_(hook, fn)                                                      \
  LEARNEST_KIT void hook(struct learnest_model* md, const learnest_real* x, const learnest_real* u, \
                         learnest_real* a) {                                                  \
    learnest_casadi_xu(md, fn, x, u, a, 0);                                                  \
  }

#ifdef LEARNEST_MODEL_STAGE
LEARNEST_CASADI_HOOK2_(learnest_model_stage, LEARNEST_MODEL_STAGE)  /* (F, A = dF/dx) */
#endif
#ifdef LEARNEST_MODEL_NODE
LEARNEST_CASADI_HOOK2_(learnest_model_node, LEARNEST_MODEL_NODE)  /* (h, C = dh/dx) */
#endif
#ifdef LEARNEST_MODEL_F
LEARNEST_CASADI_HOOK1_(learnest_model_F, LEARNEST_MODEL_F)
#endif
#ifdef LEARNEST_MODEL_H
LEARNEST_CASADI_HOOK1_(learnest_model_h, LEARNEST_MODEL_H)
#endif

#if defined(LEARNEST_MODEL_F_BATCH) || defined(LEARNEST_MODEL_STAGE_BATCH)
#include "learnest_simd.h"
#if LEARNEST_SIMD
/* One call of a generated lane-parallel copy (x, u) -> (a, b) (b 0 for a copy of one output):
 * entry j of point l at x[j * lanes + l], the same for u, a and b; each point's outputs the
 * bits the scalar function gives. */
LEARNEST_KIT void learnest_casadi_batch(int (*fn)(const learnest_real**, learnest_real**),
                                        const learnest_real* x, const learnest_real* u,
                                        learnest_real* a, learnest_real* b) {
  struct learnest_casadi_io io = learnest_casadi_io(x, u, a, b);
  (void)fn(io.in, io.out);
}

/* The n entries of points first .. first + lanes - 1 of src (point k at src + k * n), lane
 * by lane: dst[j * lanes + l] = point first + l's entry j; a point past last repeats last (a
 * batch's spare lanes). */
LEARNEST_KIT_INLINE void learnest_lanes_gather(learnest_real* dst, const learnest_real* src, int n,
                                               int first, int last, int lanes) {
  int l, j;
  for (l = 0; l < lanes; ++l) {
    const learnest_real* p = src + (first + l < last ? first + l : last) * n;
    for (j = 0; j < n; ++j) dst[j * lanes + l] = p[j];
  }
}

/* The inverse for the points first .. last of the batch: point first + l's n entries of dst
 * from lane l of src. */
LEARNEST_KIT_INLINE void learnest_lanes_scatter(learnest_real* dst, const learnest_real* src, int n,
                                                int first, int last, int lanes) {
  int l, j;
  for (l = 0; l < lanes && first + l <= last; ++l) {
    for (j = 0; j < n; ++j) dst[(first + l) * n + j] = src[j * lanes + l];
  }
}
#endif
#endif

#if defined(LEARNEST_MODEL_F_BATCH) && LEARNEST_SIMD
/* F at LEARNEST_MODEL_F_LANES points at once. */
LEARNEST_KIT void learnest_model_F_batch(const learnest_real* x, const learnest_real* u,
                                         learnest_real* F) {
  learnest_casadi_batch(LEARNEST_MODEL_F_BATCH, x, u, F, 0);
}
#endif

#if defined(LEARNEST_MODEL_STAGE_BATCH) && LEARNEST_SIMD
/* The stage (F and its Jacobian A) at LEARNEST_MODEL_STAGE_LANES points at once. */
LEARNEST_KIT void learnest_model_stage_batch(const learnest_real* x, const learnest_real* u,
                                             learnest_real* F, learnest_real* A) {
  learnest_casadi_batch(LEARNEST_MODEL_STAGE_BATCH, x, u, F, A);
}
#endif

#ifdef LEARNEST_MODEL_SOLVER
/* The NLP solver: x = argmin of the problem with parameters p from the warm start x0, with
 * the variable bounds lbx and ubx (NULL: none). Its memory is checked out of CasADi's static
 * pool for the call and given back. */
LEARNEST_KIT int learnest_model_solve(struct learnest_model* md, const learnest_real* p,
                                      const learnest_real* x0, const learnest_real* lbx,
                                      const learnest_real* ubx, learnest_real* x) {
  int i, flag, mem = LEARNEST_MODEL_SOLVER_CHECKOUT();
  if (mem < 0) return LEARNEST_NO_MEMORY;
  for (i = 0; i <= LEARNEST_CASADI_SZ_ARG; ++i) md->arg[i] = 0;  /* no multipliers */
  for (i = 0; i <= LEARNEST_CASADI_SZ_RES; ++i) md->res[i] = 0;
  md->arg[0] = x0;
  md->arg[1] = p;
  md->arg[2] = lbx;  /* nlpsol's inputs: x0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0 */
  md->arg[3] = ubx;
  md->res[0] = x;
  flag = LEARNEST_MODEL_SOLVER(md->arg, md->res, md->iw, md->w, mem);
  LEARNEST_MODEL_SOLVER_RELEASE(mem);
  if (flag) return flag == 2 ? LEARNEST_MAX_ITERATIONS : LEARNEST_SOLVER_FAILED;
  return LEARNEST_OK;
}
#endif

#endif /* LEARNEST_CASADI_H */
