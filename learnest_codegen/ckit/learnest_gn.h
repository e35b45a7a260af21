/* learnest_gn.h -- the structured Gauss-Newton core of the embedded MHE (docs/embedded_mhe.md).
 *
 * The unknowns are the window states X = x_0..x_N; the residuals of eq. (2) are the arrival
 * term a_i |x_i - xbar|^2_P (a_i = 1 - m_{i-1}), the process terms m_i |x_{i+1} - F(x_i,
 * u_{i+1})|^2_Q and the measurement terms m_i |G_i (y_i - h(x_i, u_i))|^2_R. Each iteration
 * linearises F and h at every stage, assembles the block-tridiagonal normal equations,
 * factorises them by a block Cholesky recursion (O(N NX^3), no dense matrix) and takes the
 * longest step of 1, 1/2, 1/4, ... that satisfies Armijo's condition on the cost (relaxed by a
 * bound on the cost's round-off).
 *
 * Include after learnest_mhe.h, with the model declared before:
 *   struct learnest_model;   (whatever the model needs; the kit passes a pointer through)
 *   static void learnest_model_stage(struct learnest_model*, const learnest_real* x,
 *       const learnest_real* u, learnest_real* F, learnest_real* A);   F(x, u), A = dF/dx
 *   static void learnest_model_node(struct learnest_model*, const learnest_real* x,
 *       const learnest_real* u, learnest_real* h, learnest_real* C);   h(x, u), C = dh/dx
 * with A (NX x NX) and C (NY x NX) column-major (learnest_casadi.h gives them for CasADi code).
 *
 * A model that keeps its states apart in LEARNEST_NCOMP > 1 groups (no entry of A or C couples
 * two groups: the generator reads it off the Jacobians' structure) also defines
 * LEARNEST_COMP_X (the states, group by group), LEARNEST_COMP_NX (each group's size),
 * LEARNEST_COMP_Y, LEARNEST_COMP_NY (the outputs likewise), LEARNEST_COMP_OF_X and
 * LEARNEST_COMP_OF_Y (each state's and output's group). While the weights keep the groups apart
 * too, the normal equations are block diagonal in the groups and are solved group by group
 * (learnest_gn_groups.h): the same step, for a fraction of the work (docs/embedded_mhe.md).
 */
#ifndef LEARNEST_GN_H
#define LEARNEST_GN_H

#include <float.h>

#include "learnest_mhe.h"

#define LEARNEST_GN_CONVERGED 0
#define LEARNEST_GN_RTI 1
#define LEARNEST_GN_ARMIJO ((learnest_real)1e-4)
#define LEARNEST_GN_MAX_HALVINGS 30
#define LEARNEST_GN_EPS ((learnest_real)(LEARNEST_IS_FLOAT ? FLT_EPSILON : DBL_EPSILON))
/* The residuals the cost sums (arrival, process and measurement terms of every node). */
#define LEARNEST_GN_TERMS ((LEARNEST_N + 1) * (2 * LEARNEST_NX + LEARNEST_NY))

#ifndef LEARNEST_NCOMP
#define LEARNEST_NCOMP 1
#endif


/* F, A at each stage (x_i, u_{i+1}); h, C at each node (x_i, u_i); column-major blocks. */
struct learnest_lin {
  learnest_real F[LEARNEST_N * LEARNEST_NX], A[LEARNEST_N * LEARNEST_NXX];
  learnest_real h[(LEARNEST_N + 1) * LEARNEST_NY], C[(LEARNEST_N + 1) * LEARNEST_NY * LEARNEST_NX];
};

struct learnest_gn {
  int mode, max_iter, iterations, lin_valid;
  int dq, dr, dp;  /* Q, R, P diagonal (the usual tuning): their zero terms are skipped */
  int split;       /* the weights keep the model's groups apart: solve group by group */
  learnest_real tol;
  learnest_real cost;  /* the cost at the point learnest_gn_build last assembled */
  learnest_real Q[LEARNEST_NXX], R[LEARNEST_NYY], P[LEARNEST_NXX];  /* weights / the largest */
  struct learnest_lin lin[2];  /* at the iterate (lin[cur]) and at the line search's point */
  int cur;
  learnest_real Xt[LEARNEST_NW];
  learnest_real D[(LEARNEST_N + 1) * LEARNEST_NXX];  /* diagonal blocks, then their factors */
  learnest_real E[LEARNEST_N * LEARNEST_NXX];  /* blocks (i+1, i), then the factor's */
  learnest_real g[LEARNEST_NW], dx[LEARNEST_NW], rw[LEARNEST_NX], rv[LEARNEST_NY];
#if LEARNEST_BOUNDED
  /* the bounded step's quadratic program (learnest_gn_box_step): the normal equations kept,
   * its feasible point, H times a vector, its working set */
  learnest_real Dh[(LEARNEST_N + 1) * LEARNEST_NXX], Eh[LEARNEST_N * LEARNEST_NXX];
  learnest_real p[LEARNEST_NW], q[LEARNEST_NW];
  signed char act[LEARNEST_NW];
#endif
};

/* The linearisation at the iterate. */
#define LEARNEST_GN_LIN(s) (&(s)->lin[(s)->cur])

#include "learnest_gn_groups.h"

/* The weights of p divided by their largest diagonal entry, as the Ipopt MHE scales its cost. */
LEARNEST_KIT void learnest_gn_scale(struct learnest_gn* s, const struct learnest_mhe_problem* p) {
  learnest_real big = 0;
  int i;
  for (i = 0; i < LEARNEST_NX; ++i) big = p->Q[i * LEARNEST_NX + i] > big ? p->Q[i * LEARNEST_NX + i] : big;
  for (i = 0; i < LEARNEST_NY; ++i) big = p->R[i * LEARNEST_NY + i] > big ? p->R[i * LEARNEST_NY + i] : big;
  for (i = 0; i < LEARNEST_NX; ++i) big = p->P[i * LEARNEST_NX + i] > big ? p->P[i * LEARNEST_NX + i] : big;
  big = 1 / big;
  for (i = 0; i < LEARNEST_NXX; ++i) s->Q[i] = big * p->Q[i];
  for (i = 0; i < LEARNEST_NYY; ++i) s->R[i] = big * p->R[i];
  for (i = 0; i < LEARNEST_NXX; ++i) s->P[i] = big * p->P[i];
  s->dq = learnest_is_diagonal(s->Q, LEARNEST_NX);
  s->dr = learnest_is_diagonal(s->R, LEARNEST_NY);
  s->dp = learnest_is_diagonal(s->P, LEARNEST_NX);
#if LEARNEST_NCOMP > 1
  s->split = LEARNEST_BOUNDED ? 0 : learnest_gn_split(s);  /* bounds: learnest_gn_box_step */
#else
  s->split = 0;
#endif
}

/* Linearise every stage and node of window w that holds a sample at the states X into L. A
 * stage without one (mask 0: the empty stages of a window that is filling, after init or a
 * restart) is not evaluated: the assembly and the cost read a stage's F, A, h and C only
 * under its mask, and an empty stage stays empty until it leaves the window (the masks move
 * with their stages, learnest_window_shift), so its entries of L are never read. The empty
 * stages are the oldest: the loops start at the first stage that holds a sample. */
LEARNEST_KIT void learnest_gn_linearise(struct learnest_model* md, const struct learnest_window* w,
                                        const learnest_real* X, struct learnest_lin* L) {
  int i, first = 0;
  while (first < LEARNEST_N && w->mask[first] == 0) ++first;
#if defined(LEARNEST_MODEL_STAGE_BATCH) && LEARNEST_SIMD
  /* The stages LEARNEST_MODEL_STAGE_LANES at a time (the same bits; spare lanes repeat the
   * last stage). */
  enum { B = LEARNEST_MODEL_STAGE_LANES };
  learnest_real xb[LEARNEST_NX * B], ub[LEARNEST_NU * B + 1], Fb[LEARNEST_NX * B];
  learnest_real Ab[LEARNEST_NXX * B];
  for (i = first; i < LEARNEST_N; i += B) {  /* stage i: x_i and u_{i+1} */
    learnest_lanes_gather(xb, X, LEARNEST_NX, i, LEARNEST_N - 1, B);
    learnest_lanes_gather(ub, w->U + LEARNEST_NU, LEARNEST_NU, i, LEARNEST_N - 1, B);
    learnest_model_stage_batch(xb, ub, Fb, Ab);
    learnest_lanes_scatter(L->F, Fb, LEARNEST_NX, i, LEARNEST_N - 1, B);
    learnest_lanes_scatter(L->A, Ab, LEARNEST_NXX, i, LEARNEST_N - 1, B);
  }
#else
  for (i = first; i < LEARNEST_N; ++i) {
    learnest_model_stage(md, X + i * LEARNEST_NX, w->U + (i + 1) * LEARNEST_NU, L->F + i * LEARNEST_NX,
                         L->A + i * LEARNEST_NXX);
  }
#endif
  for (i = first; i <= LEARNEST_N; ++i) {
    learnest_model_node(md, X + i * LEARNEST_NX, w->U + i * LEARNEST_NU, L->h + i * LEARNEST_NY,
                        L->C + i * LEARNEST_NY * LEARNEST_NX);
  }
}

/* The linearisation of the window after learnest_mhe_advance: the shifted stages keep theirs
 * (stage i of the new window is stage i+1 of the old one, same x and u) when it is valid,
 * and the new last stage and node are evaluated; otherwise the whole window. */
LEARNEST_KIT void learnest_gn_advance(struct learnest_gn* s, struct learnest_model* md,
                                      const struct learnest_window* w, const learnest_real* X,
                                      int has_previous) {
  struct learnest_lin* L = LEARNEST_GN_LIN(s);
  if (!(s->lin_valid && has_previous)) {
    learnest_gn_linearise(md, w, X, L);
    return;
  }
  learnest_shift(L->F, LEARNEST_NX, LEARNEST_N);
  learnest_shift(L->A, LEARNEST_NXX, LEARNEST_N);
  learnest_shift(L->h, LEARNEST_NY, LEARNEST_N + 1);
  learnest_shift(L->C, LEARNEST_NY * LEARNEST_NX, LEARNEST_N + 1);
  learnest_model_stage(md, X + (LEARNEST_N - 1) * LEARNEST_NX, w->U + LEARNEST_N * LEARNEST_NU,
                       L->F + (LEARNEST_N - 1) * LEARNEST_NX, L->A + (LEARNEST_N - 1) * LEARNEST_NXX);
  learnest_model_node(md, X + LEARNEST_N * LEARNEST_NX, w->U + LEARNEST_N * LEARNEST_NU,
                      L->h + LEARNEST_N * LEARNEST_NY, L->C + LEARNEST_N * LEARNEST_NY * LEARNEST_NX);
}

/* r' W r for the n x n W; diag: W is diagonal (its zero terms skipped). */
LEARNEST_KIT_INLINE learnest_real learnest_gn_quad(const learnest_real* W, int diag,
                                                   const learnest_real* r, int n) {
  learnest_real acc = 0;
  int i;
  if (!diag) return learnest_quad(W, r, n);
  LEARNEST_UNROLL_BLOCK for (i = 0; i < n; ++i) acc += W[i + i * n] * r[i] * r[i];
  return acc;
}

/* learnest_gn_quad(W, diag, r, n) given Wr = W r (learnest_gn_weigh): for a diagonal W the same
 * products (W_ii r_i) r_i in the same order, so the same bits. */
LEARNEST_KIT_INLINE learnest_real learnest_gn_quad_weighed(const learnest_real* W, int diag,
                                                           const learnest_real* r, const learnest_real* Wr,
                                                           int n) {
  learnest_real acc = 0;
  int i;
  if (!diag) return learnest_quad(W, r, n);
  LEARNEST_UNROLL_BLOCK for (i = 0; i < n; ++i) acc += Wr[i] * r[i];
  return acc;
}

/* The cost of window w at X with linearisation L (scaled weights). */
LEARNEST_KIT learnest_real learnest_gn_cost(struct learnest_gn* s, const struct learnest_window* w,
                                            const learnest_real* X, const struct learnest_lin* L) {
  learnest_real c = 0;
  int i, j;
  for (i = 0; i <= LEARNEST_N; ++i) {
    const learnest_real* x = X + i * LEARNEST_NX;
    learnest_real a = i ? 1 - w->mask[i - 1] : 1;
    if (a != 0) {
      for (j = 0; j < LEARNEST_NX; ++j) s->rw[j] = x[j] - w->xbar[j];
      c += a * learnest_gn_quad(s->P, s->dp, s->rw, LEARNEST_NX);
    }
    if (w->mask[i] != 0) {
      for (j = 0; j < LEARNEST_NY; ++j) {
        s->rv[j] = w->G[i * LEARNEST_NY + j] * (w->Y[i * LEARNEST_NY + j] - L->h[i * LEARNEST_NY + j]);
      }
      c += w->mask[i] * learnest_gn_quad(s->R, s->dr, s->rv, LEARNEST_NY);
      if (i < LEARNEST_N) {
        for (j = 0; j < LEARNEST_NX; ++j) s->rw[j] = X[(i + 1) * LEARNEST_NX + j] - L->F[i * LEARNEST_NX + j];
        c += w->mask[i] * learnest_gn_quad(s->Q, s->dq, s->rw, LEARNEST_NX);
      }
    }
  }
  return c;
}

/* Wv = W v and WM = W M (M: n x cols, column-major, structure nz) for the n x n W; diag: W is
 * diagonal (its zero terms are skipped, and WM has M's structure). M's entries at its
 * structural zeros are not read. */
LEARNEST_KIT_INLINE void learnest_gn_weigh(const learnest_real* W, int n, int diag, const learnest_real* v,
                                           const learnest_real* M, const unsigned char* nz, int cols,
                                           learnest_real* Wv, learnest_real* WM) {
  int r, c, k;
  LEARNEST_UNROLL_BLOCK for (r = 0; r < n; ++r) {
    if (diag) {
      Wv[r] = W[r + r * n] * v[r];
      LEARNEST_UNROLL_BLOCK for (c = 0; c < cols; ++c) {
        WM[r + c * n] = LEARNEST_NZ(nz, r + c * n) ? W[r + r * n] * M[r + c * n] : 0;
      }
      continue;
    }
    Wv[r] = 0;
    LEARNEST_UNROLL_BLOCK for (k = 0; k < n; ++k) Wv[r] += W[r + k * n] * v[k];
    LEARNEST_UNROLL_BLOCK for (c = 0; c < cols; ++c) {
      learnest_real t = 0;
      LEARNEST_UNROLL_BLOCK for (k = 0; k < n; ++k) {
        if (LEARNEST_NZ(nz, k + c * n)) t += W[r + k * n] * M[k + c * n];
      }
      WM[r + c * n] = t;
    }
  }
}

/* A term m |W^(1/2) r|^2 of a node's residual r (n of them) with Jacobian J (n x NX,
 * structure nz) in the normal equations: D += m J' W J (its lower triangle; hess = 0: D is
 * left) and g -= m J' W r, given WJ = W J and Wr = W r (learnest_gn_weigh; diag: W is
 * diagonal, so WJ has J's structure). */
LEARNEST_KIT_INLINE void learnest_gn_term(int n, const learnest_real* J, const unsigned char* nz, int diag,
                                          const learnest_real* WJ, const learnest_real* Wr,
                                          learnest_real m, int hess, learnest_real* D, learnest_real* g) {
  int r, c, k;
  LEARNEST_UNROLL_BLOCK for (c = 0; c < LEARNEST_NX; ++c) {
    if (hess) {
      LEARNEST_UNROLL_BLOCK for (r = c; r < LEARNEST_NX; ++r) {
        learnest_real v = 0;
        int any = 0;  /* a structural zero of J'WJ adds nothing */
        LEARNEST_UNROLL_BLOCK for (k = 0; k < n; ++k) {
          if (LEARNEST_NZ(nz, k + r * n) && (!diag || LEARNEST_NZ(nz, k + c * n))) {
            v += J[k + r * n] * WJ[k + c * n];
            any = 1;
          }
        }
        if (any) D[r + c * LEARNEST_NX] += m * v;
      }
    }
    LEARNEST_UNROLL_BLOCK for (k = 0; k < n; ++k) {
      if (LEARNEST_NZ(nz, k + c * n)) g[c] -= m * J[k + c * n] * Wr[k];
    }
  }
}

/* The normal equations H dx = -g of the Gauss-Newton model at X (half the cost's Hessian and
 * gradient): diagonal blocks D_i (their lower triangles: all the factorisation reads), blocks
 * E_i = H_{i+1, i}, gradient g; hess = 0: the gradient alone (D and E are left as they are);
 * and the cost at X (learnest_gn_cost's sum, term by term in its order: the same bits).
 * Diagonal weights (the usual tuning) skip their zero terms. */
LEARNEST_KIT_INLINE void learnest_gn_build(struct learnest_gn* s, const struct learnest_window* w,
                                           const learnest_real* X, int hess) {
  const struct learnest_lin* L = LEARNEST_GN_LIN(s);
  const int dq = s->dq, dr = s->dr, dp = s->dp;
  int i, r, c, k;
  if (hess) {  /* D_0 from 0; each stage sets D_{i+1}'s lower triangle and E_i whole below */
    LEARNEST_UNROLL_BLOCK for (k = 0; k < LEARNEST_NXX; ++k) s->D[k] = 0;
  }
  memset(s->g, 0, sizeof s->g);
  s->cost = 0;
  for (i = 0; i <= LEARNEST_N; ++i) {
    learnest_real* D = s->D + i * LEARNEST_NXX;
    learnest_real* g = s->g + i * LEARNEST_NX;
    const learnest_real* x = X + i * LEARNEST_NX;
    learnest_real a = i ? 1 - w->mask[i - 1] : 1, m = w->mask[i];
    if (a != 0) {  /* arrival term a |x_i - xbar|^2_P */
      LEARNEST_UNROLL_BLOCK for (k = 0; k < LEARNEST_NX; ++k) s->rw[k] = x[k] - w->xbar[k];
      s->cost += a * learnest_gn_quad(s->P, dp, s->rw, LEARNEST_NX);
      LEARNEST_UNROLL_BLOCK for (c = 0; c < LEARNEST_NX; ++c) {
        if (dp) {
          if (hess) D[c + c * LEARNEST_NX] += a * s->P[c + c * LEARNEST_NX];
          g[c] += a * s->P[c + c * LEARNEST_NX] * s->rw[c];
          continue;
        }
        LEARNEST_UNROLL_BLOCK for (r = 0; r < LEARNEST_NX; ++r) {
          if (hess && r >= c) D[r + c * LEARNEST_NX] += a * s->P[r + c * LEARNEST_NX];
          g[r] += a * s->P[r + c * LEARNEST_NX] * s->rw[c];
        }
      }
    }
    if (m == 0) {  /* the stage couples nothing: E_i = 0, D_{i+1} starts from 0 */
      if (hess && i < LEARNEST_N) {
        memset(s->D + (i + 1) * LEARNEST_NXX, 0, LEARNEST_NXX * sizeof *s->D);
        memset(s->E + i * LEARNEST_NXX, 0, LEARNEST_NXX * sizeof *s->E);
      }
      continue;
    }
    {  /* measurement term m |G (y_i - h(x_i))|^2_R: D += C'RC, g -= C'R v (C, v weighted) */
      const learnest_real* Gi = w->G + i * LEARNEST_NY;
      learnest_real C[LEARNEST_NY * LEARNEST_NX], RC[LEARNEST_NY * LEARNEST_NX], Rv[LEARNEST_NY];
      LEARNEST_UNROLL_BLOCK for (c = 0; c < LEARNEST_NX; ++c) {
        LEARNEST_UNROLL_BLOCK for (r = 0; r < LEARNEST_NY; ++r) {
          if (!LEARNEST_NZ(LEARNEST_C_NZ, r + c * LEARNEST_NY)) continue;
          C[r + c * LEARNEST_NY] = Gi[r] * L->C[i * LEARNEST_NY * LEARNEST_NX + r + c * LEARNEST_NY];
        }
      }
      LEARNEST_UNROLL_BLOCK for (k = 0; k < LEARNEST_NY; ++k) {
        s->rv[k] = Gi[k] * (w->Y[i * LEARNEST_NY + k] - L->h[i * LEARNEST_NY + k]);
      }
      if (hess) {  /* apart, so that each call's column count is a constant (loops unrolled whole) */
        learnest_gn_weigh(s->R, LEARNEST_NY, dr, s->rv, C, LEARNEST_C_NZ, LEARNEST_NX, Rv, RC);
      } else {
        learnest_gn_weigh(s->R, LEARNEST_NY, dr, s->rv, C, LEARNEST_C_NZ, 0, Rv, RC);
      }
      s->cost += m * learnest_gn_quad_weighed(s->R, dr, s->rv, Rv, LEARNEST_NY);
      learnest_gn_term(LEARNEST_NY, C, LEARNEST_C_NZ, dr, RC, Rv, m, hess, D, g);
    }
    if (i < LEARNEST_N) {  /* process term m |x_{i+1} - F(x_i)|^2_Q: couples x_i and x_{i+1} */
      const learnest_real* A = L->A + i * LEARNEST_NXX;
      learnest_real* Dn = s->D + (i + 1) * LEARNEST_NXX;
      learnest_real* E = s->E + i * LEARNEST_NXX;
      learnest_real* gn = s->g + (i + 1) * LEARNEST_NX;
      learnest_real QA[LEARNEST_NXX], Qw[LEARNEST_NX];
      LEARNEST_UNROLL_BLOCK for (k = 0; k < LEARNEST_NX; ++k) s->rw[k] = X[(i + 1) * LEARNEST_NX + k] - L->F[i * LEARNEST_NX + k];
      if (hess) {
        learnest_gn_weigh(s->Q, LEARNEST_NX, dq, s->rw, A, LEARNEST_A_NZ, LEARNEST_NX, Qw, QA);
      } else {
        learnest_gn_weigh(s->Q, LEARNEST_NX, dq, s->rw, A, LEARNEST_A_NZ, 0, Qw, QA);
      }
      s->cost += m * learnest_gn_quad_weighed(s->Q, dq, s->rw, Qw, LEARNEST_NX);
      if (hess) {  /* H_{i+1,i} = -m Q A (0 where a diagonal Q leaves A's structural zeros) */
        LEARNEST_UNROLL_BLOCK for (c = 0; c < LEARNEST_NX; ++c) {  /* by block: the pattern a constant */
          LEARNEST_UNROLL_BLOCK for (r = 0; r < LEARNEST_NX; ++r) {
            k = r + c * LEARNEST_NX;
            E[k] = !dq || LEARNEST_NZ(LEARNEST_A_NZ, k) ? -m * QA[k] : 0;
          }
        }
      }
      learnest_gn_term(LEARNEST_NX, A, LEARNEST_A_NZ, dq, QA, Qw, m, hess, D, g);
      LEARNEST_UNROLL_BLOCK for (c = 0; c < LEARNEST_NX; ++c) {
        if (hess) {
          LEARNEST_UNROLL_BLOCK for (r = c; r < LEARNEST_NX; ++r) {
            Dn[r + c * LEARNEST_NX] = !dq || r == c ? m * s->Q[r + c * LEARNEST_NX] : 0;
          }
        }
        gn[c] += m * Qw[c];
      }
    }
  }
}

/* Solve H z = b in place for the symmetric block-tridiagonal H of N+1 diagonal blocks D_i
 * (n x n, column-major, at D + i bs; lower triangles read; n <= LEARNEST_NX) and N blocks
 * E_i = H_{i+1, i} (at E + i bs), z_i at z + i n (apart from D and E), by the block Cholesky
 * recursion L_i L_i' = D_i - B_{i-1} B_{i-1}', B_i = E_i L_i^-T (solved column by column in
 * place, each entry's sum kept in a register). The row of L_i that column c of B_i reuses is
 * copied to a local array first (D and E may overlap as far as the compiler knows, so it would
 * reload the row after every store), and so is the row of B_{i-1} that D_i's update reuses
 * when the block loops are unrolled whole (LEARNEST_BLOCK_WHOLE; otherwise, for groups of
 * states and under clang, that copy costs more than it saves). D and E are overwritten by the
 * factor; factor = 0: they hold it already (from an earlier call), and only the substitutions
 * run. 0 if H is not positive definite. */
LEARNEST_KIT int learnest_btd_solve_n(int n, int bs, learnest_real* D, learnest_real* E,
                                      learnest_real* LEARNEST_RESTRICT z, int factor) {
  int i, r, c, k;
  for (i = 0; factor && i <= LEARNEST_N; ++i) {
    learnest_real* Di = D + i * bs;
    if (i > 0) {  /* D_i -= B_{i-1} B_{i-1}' (lower triangle) */
      const learnest_real* B = E + (i - 1) * bs;
      LEARNEST_UNROLL_BLOCK for (c = 0; c < n; ++c) {
        learnest_real row[LEARNEST_NX];  /* row c of B, copied when the loops are unrolled whole */
        const learnest_real* Bc = LEARNEST_BLOCK_WHOLE ? row : B + c;
        const int step = LEARNEST_BLOCK_WHOLE ? 1 : n;
        if (LEARNEST_BLOCK_WHOLE) {
          LEARNEST_UNROLL_BLOCK for (k = 0; k < n; ++k) row[k] = B[c + k * n];
        }
        LEARNEST_UNROLL_BLOCK for (r = c; r < n; ++r) {
          learnest_real v = 0;
          LEARNEST_UNROLL_BLOCK for (k = 0; k < n; ++k) v += B[r + k * n] * Bc[k * step];
          Di[r + c * n] -= v;
        }
      }
    }
    if (!learnest_cholesky(Di, n)) return 0;
    if (i < LEARNEST_N) {  /* B_i L_i' = E_i: column c of B from the columns before it */
      learnest_real* B = E + i * bs;
      LEARNEST_UNROLL_BLOCK for (c = 0; c < n; ++c) {
        const learnest_real inv = 1 / Di[c + c * n];
        learnest_real row[LEARNEST_NX];  /* row c of L_i: a local copy, which no store to E can change */
        LEARNEST_UNROLL_BLOCK for (k = 0; k < c; ++k) row[k] = Di[c + k * n];
        LEARNEST_UNROLL_BLOCK for (r = 0; r < n; ++r) {  /* entry (r, c) kept in a register */
          learnest_real v = B[r + c * n];
          LEARNEST_UNROLL_BLOCK for (k = 0; k < c; ++k) v -= B[r + k * n] * row[k];
          B[r + c * n] = v * inv;
        }
      }
    }
  }
  for (i = 0; i <= LEARNEST_N; ++i) {  /* forward: z_i = L_i^-1 (b_i - B_{i-1} z_{i-1}) */
    learnest_real* zi = z + i * n;
    if (i > 0) {
      const learnest_real* B = E + (i - 1) * bs;
      LEARNEST_UNROLL_BLOCK for (r = 0; r < n; ++r) {
        LEARNEST_UNROLL_BLOCK for (k = 0; k < n; ++k) zi[r] -= B[r + k * n] * zi[k - n];
      }
    }
    learnest_forward_subst(D + i * bs, n, zi);
  }
  for (i = LEARNEST_N; i >= 0; --i) {  /* backward: z_i = L_i^-T (z_i - B_i' z_{i+1}) */
    learnest_real* zi = z + i * n;
    if (i < LEARNEST_N) {
      const learnest_real* B = E + i * bs;
      LEARNEST_UNROLL_BLOCK for (r = 0; r < n; ++r) {
        LEARNEST_UNROLL_BLOCK for (k = 0; k < n; ++k) zi[r] -= B[k + r * n] * zi[n + k];
      }
    }
    learnest_backward_subst(D + i * bs, n, zi);
  }
  return 1;
}

/* Solve H dx = -g for the whole window's H (blocks NX x NX): learnest_btd_solve_n. */
LEARNEST_KIT int learnest_btd_solve(learnest_real* D, learnest_real* E, const learnest_real* g,
                                    learnest_real* dx) {
  int j;
  for (j = 0; j < LEARNEST_NW; ++j) dx[j] = -g[j];
  return learnest_btd_solve_n(LEARNEST_NX, LEARNEST_NXX, D, E, dx, 1);
}

#if LEARNEST_BOUNDED
/* y = H v for the window's symmetric block-tridiagonal H (D: the lower triangles of the
 * diagonal blocks; E_i = H_{i+1,i}). */
LEARNEST_KIT void learnest_btd_multiply(const learnest_real* D, const learnest_real* E, const learnest_real* v,
                                        learnest_real* y) {
  int i, r, c;
  for (i = 0; i <= LEARNEST_N; ++i) {
    const learnest_real* Di = D + i * LEARNEST_NXX;
    for (r = 0; r < LEARNEST_NX; ++r) {
      learnest_real acc = 0;
      for (c = 0; c < LEARNEST_NX; ++c) {
        acc += (r >= c ? Di[r + c * LEARNEST_NX] : Di[c + r * LEARNEST_NX]) * v[i * LEARNEST_NX + c];
        if (i > 0) acc += E[(i - 1) * LEARNEST_NXX + r + c * LEARNEST_NX] * v[(i - 1) * LEARNEST_NX + c];
        if (i < LEARNEST_N) acc += E[i * LEARNEST_NXX + c + r * LEARNEST_NX] * v[(i + 1) * LEARNEST_NX + c];
      }
      y[i * LEARNEST_NX + r] = acc;
    }
  }
}

/* At most this many working sets per step (each adds or drops one bound). */
#define LEARNEST_GN_QP_MAX (2 * LEARNEST_NW + 2)

/* The step dx that solves the Gauss-Newton model's box-constrained quadratic program
 *   min g'dx + dx'H dx / 2   subject to   lo <= X + dx <= hi
 * exactly, on the one linearisation in D, E, g (built at X, which is inside the box), by a
 * primal active set: from dx = 0 and the bounds whose gradient points out of the box, each
 * iteration solves H dx = -g with the working set's variables fixed on their bound (the block
 * Cholesky recursion on the normal equations with those rows and columns the identity's); a
 * solution outside the box is followed only up to the first bound it crosses, which joins the
 * set; one inside it is the answer when every fixed variable's multiplier (the model's
 * gradient H dx + g there) pushes out of the box, and otherwise the variable pushed furthest
 * in leaves the set. g is left as it is (the line search's slope); D and E hold the last
 * factor. */
LEARNEST_KIT int learnest_gn_box_step(struct learnest_gn* s, const learnest_real* X) {
  int it, j, block;
  learnest_real t, r, worst, lo, hi, m;
  memcpy(s->Dh, s->D, sizeof s->Dh);
  memcpy(s->Eh, s->E, sizeof s->Eh);
  learnest_box_active(X, s->g, s->act);
  memset(s->p, 0, sizeof s->p);
  for (it = 0; it < LEARNEST_GN_QP_MAX; ++it) {
    /* the right side: -g - H p_fixed on the free rows, the fixed values on the fixed rows */
    for (j = 0; j < LEARNEST_NW; ++j) s->q[j] = s->act[j] ? s->p[j] : 0;
    learnest_btd_multiply(s->Dh, s->Eh, s->q, s->dx);
    for (j = 0; j < LEARNEST_NW; ++j) s->dx[j] = s->act[j] ? s->p[j] : -s->g[j] - s->dx[j];
    memcpy(s->D, s->Dh, sizeof s->Dh);
    memcpy(s->E, s->Eh, sizeof s->Eh);
    learnest_box_fix(s->D, s->E, s->act);
    if (!learnest_btd_solve_n(LEARNEST_NX, LEARNEST_NXX, s->D, s->E, s->dx, 1)) {
      return LEARNEST_NOT_POSITIVE_DEFINITE;
    }
    if (!learnest_all_finite(s->dx, LEARNEST_NW)) return LEARNEST_NONFINITE_RESULT;
    t = 1;
    block = -1;
    for (j = 0; j < LEARNEST_NW; ++j) {  /* the first bound on the way from p to dx */
      if (s->act[j]) continue;
      lo = learnest_state_lo[j % LEARNEST_NX] - X[j];
      hi = learnest_state_hi[j % LEARNEST_NX] - X[j];
      if (s->dx[j] < lo || s->dx[j] > hi) {
        r = ((s->dx[j] < lo ? lo : hi) - s->p[j]) / (s->dx[j] - s->p[j]);
        if (r < t || block < 0) {
          t = r;
          block = j;
        }
      }
    }
    if (block >= 0) {
      t = t < 0 ? 0 : t;
      for (j = 0; j < LEARNEST_NW; ++j) {
        if (!s->act[j]) s->p[j] += t * (s->dx[j] - s->p[j]);
      }
      lo = learnest_state_lo[block % LEARNEST_NX] - X[block];
      s->act[block] = (signed char)(s->dx[block] < lo ? -1 : 1);
      s->p[block] = s->act[block] < 0 ? lo : learnest_state_hi[block % LEARNEST_NX] - X[block];
      continue;
    }
    memcpy(s->p, s->dx, sizeof s->p);
    learnest_btd_multiply(s->Dh, s->Eh, s->p, s->q);  /* the multipliers: (H p + g) on the set */
    block = -1;
    worst = 0;
    for (j = 0; j < LEARNEST_NW; ++j) {
      m = s->act[j] * (s->q[j] + s->g[j]);  /* > 0: the cost falls into the box */
      if (m > worst) {
        worst = m;
        block = j;
      }
    }
    if (block < 0) break;
    s->act[block] = 0;
  }
  memcpy(s->dx, s->p, sizeof s->p);
  return LEARNEST_OK;
}
#endif

/* The Gauss-Newton step dx at X (linearised in lin); *big = max |dx_j|. hess = 0: the step
 * from the gradient at X and the factor of the Hessian the last call built (at the previous
 * iterate; the Gauss-Newton Hessian moves with the Jacobians, so this step differs from X's own
 * by a relative O(|last step|)): the gradient's cost and two substitutions, no factorisation. */
LEARNEST_KIT_INLINE int learnest_gn_direction(struct learnest_gn* s, const struct learnest_window* w,
                                              const learnest_real* X, int hess, learnest_real* big) {
  int j;
#if LEARNEST_NCOMP > 1
  if (s->split) {
    learnest_gn_build_split(s, w, X, hess);
    if (!learnest_gn_solve_split(s, hess)) return LEARNEST_NOT_POSITIVE_DEFINITE;
  } else
#endif
  {
#if LEARNEST_BOUNDED
    /* under state bounds every step solves its bounded quadratic program, from a Hessian of
     * its own (a factor of another working set is not reused) */
    (void)hess;
    learnest_gn_build(s, w, X, 1);
    j = learnest_gn_box_step(s, X);
    if (j != LEARNEST_OK) return j;
#else
    learnest_gn_build(s, w, X, hess);
    for (j = 0; j < LEARNEST_NW; ++j) s->dx[j] = -s->g[j];
    if (!learnest_btd_solve_n(LEARNEST_NX, LEARNEST_NXX, s->D, s->E, s->dx, hess)) {
      return LEARNEST_NOT_POSITIVE_DEFINITE;
    }
#endif
  }
  if (!learnest_all_finite(s->dx, LEARNEST_NW)) return LEARNEST_NONFINITE_RESULT;
  *big = 0;
  for (j = 0; j < LEARNEST_NW; ++j) {
    if (LEARNEST_FABS(s->dx[j]) > *big) *big = LEARNEST_FABS(s->dx[j]);
  }
  return LEARNEST_OK;
}

/* A bound on the round-off of the cost at X: each residual, a difference of numbers of size up
 * to 1 + |X|, is off by up to eps (1 + |X|), which moves its term w r^2 by 2 w |r| eps (1 + |X|);
 * over the n terms (scaled weights <= 1, Cauchy-Schwarz) at most 2 eps (1 + |X|) sqrt(n cost). */
LEARNEST_KIT learnest_real learnest_gn_noise(const learnest_real* X, learnest_real cost) {
  learnest_real top = 0;
  int j;
  for (j = 0; j < LEARNEST_NW; ++j) {
    if (LEARNEST_FABS(X[j]) > top) top = LEARNEST_FABS(X[j]);
  }
  return 2 * LEARNEST_GN_EPS * (1 + top) * LEARNEST_SQRT(LEARNEST_GN_TERMS * cost);
}

/* Move X along dx by the longest of 1, 1/2, 1/4, ... that satisfies Armijo's condition on the
 * cost; the linearisation at the new point (needed by the next iteration, or by the next
 * sample in RTI mode) comes from the line search's own evaluation. */
LEARNEST_KIT int learnest_gn_line_search(struct learnest_gn* s, struct learnest_model* md,
                                         const struct learnest_window* w, learnest_real* X,
                                         learnest_real big) {
  learnest_real cost, slope = 0, alpha = 1, noise = -1, bound, trial_cost;
  int j, halvings;
  struct learnest_lin* trial = &s->lin[1 - s->cur];
#if LEARNEST_NCOMP > 1
  cost = s->split ? learnest_gn_cost(s, w, X, LEARNEST_GN_LIN(s)) : s->cost;
#else
  cost = s->cost;  /* summed at X by the step's assembly */
#endif
  for (j = 0; j < LEARNEST_NW; ++j) slope += s->g[j] * s->dx[j];  /* half the cost's slope */
  for (halvings = 0; halvings <= LEARNEST_GN_MAX_HALVINGS; ++halvings) {
    for (j = 0; j < LEARNEST_NW; ++j) s->Xt[j] = X[j] + alpha * s->dx[j];
    learnest_box_clamp(s->Xt, LEARNEST_N + 1);  /* a projected step under state bounds */
    learnest_gn_linearise(md, w, s->Xt, trial);
    if (alpha * big <= s->tol) break;  /* a step below tol is taken whole */
    /* Armijo, relaxed by the cost's round-off (without it, a step whose decrease is below
     * round-off is halved on noise, and the iteration crawls in many short steps). */
    bound = cost + 2 * LEARNEST_GN_ARMIJO * alpha * slope;
    trial_cost = learnest_gn_cost(s, w, s->Xt, trial);
    if (trial_cost <= bound) break;
    if (noise < 0) noise = learnest_gn_noise(X, cost);
    if (trial_cost <= bound + noise) break;
    alpha *= (learnest_real)0.5;
  }
  if (halvings > LEARNEST_GN_MAX_HALVINGS) return LEARNEST_LINE_SEARCH_FAILED;
  memcpy(X, s->Xt, sizeof s->Xt);
  s->cur = 1 - s->cur;  /* the trial's linearisation becomes the iterate's */
  return LEARNEST_OK;
}

/* Converged mode: Gauss-Newton steps until the next one moves no state by more than tol
 * (that step is not taken), at most max_iter steps (LEARNEST_MAX_ITERATIONS). The test at a
 * new iterate is its stationarity first: the gradient scaled by the last factorised Hessian
 * (learnest_gn_direction with hess = 0), which is the next step to a relative O(|last step|);
 * only when that is above tol is the Hessian rebuilt and factorised (and the test repeated on
 * the exact step). RTI mode: one step. X (the warm start, linearised in lin) becomes the
 * solution; *steps = the steps taken. */
LEARNEST_KIT int learnest_gn_solve(struct learnest_gn* s, struct learnest_model* md,
                                   const struct learnest_window* w, learnest_real* X, int* steps) {
  const int converged = s->mode == LEARNEST_GN_CONVERGED;
  int code;
  learnest_real big;
  *steps = 0;
  for (;;) {
    if (converged && *steps > 0) {
      code = learnest_gn_direction(s, w, X, 0, &big);
      if (code != LEARNEST_OK) return code;
      if (big <= s->tol) return LEARNEST_OK;
    }
    code = learnest_gn_direction(s, w, X, 1, &big);
    if (code != LEARNEST_OK) return code;
    if (converged && big <= s->tol) return LEARNEST_OK;
    if (converged && *steps == s->max_iter) return LEARNEST_MAX_ITERATIONS;
    code = learnest_gn_line_search(s, md, w, X, big);
    if (code != LEARNEST_OK) return code;
    ++*steps;
    if (!converged) return LEARNEST_OK;
  }
}

#endif /* LEARNEST_GN_H */
