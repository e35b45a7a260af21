/* learnest_gn_groups.h -- the Gauss-Newton core's normal equations group by group, for a model
 * whose Jacobians keep its states apart in LEARNEST_NCOMP > 1 groups (docs/embedded_mhe.md).
 *
 * Included by learnest_gn.h; the tables come from the generated glue (codegen/mhe_gn.py:
 * state_groups). H is then block diagonal in the groups while the weights keep them apart too
 * (learnest_gn_apart, checked at every retuning): each group's block-tridiagonal system is
 * assembled and solved on its own, the same step as the whole window's.
 */
#ifndef LEARNEST_GN_GROUPS_H
#define LEARNEST_GN_GROUPS_H
#if LEARNEST_NCOMP > 1

static const unsigned char learnest_comp_x[LEARNEST_NX] = LEARNEST_COMP_X;
static const unsigned char learnest_comp_nx[LEARNEST_NCOMP] = LEARNEST_COMP_NX;
static const unsigned char learnest_comp_y[LEARNEST_NY] = LEARNEST_COMP_Y;
static const unsigned char learnest_comp_ny[LEARNEST_NCOMP] = LEARNEST_COMP_NY;
static const unsigned char learnest_comp_of_x[LEARNEST_NX] = LEARNEST_COMP_OF_X;
static const unsigned char learnest_comp_of_y[LEARNEST_NY] = LEARNEST_COMP_OF_Y;
#ifdef LEARNEST_COMP_SIZE  /* every group has this many states and LEARNEST_COMP_YSIZE outputs */
#define LEARNEST_GROUP_NX(k) LEARNEST_COMP_SIZE
#define LEARNEST_GROUP_NY(k) LEARNEST_COMP_YSIZE
#else
#define LEARNEST_GROUP_NX(k) learnest_comp_nx[k]
#define LEARNEST_GROUP_NY(k) learnest_comp_ny[k]
#endif

LEARNEST_KIT int learnest_btd_solve_n(int n, int bs, learnest_real* D, learnest_real* E,
                                      learnest_real* LEARNEST_RESTRICT z, int factor);
LEARNEST_KIT_INLINE void learnest_gn_weigh(const learnest_real* W, int n, int diag, const learnest_real* v,
                                           const learnest_real* M, const unsigned char* nz, int cols,
                                           learnest_real* Wv, learnest_real* WM);

/* The n x n block of the ld x ld W at the rows and columns idx: a group's weight. */
LEARNEST_KIT void learnest_gn_block(const learnest_real* W, int ld, const unsigned char* idx, int n,
                                    learnest_real* Wk) {
  int r, c;
  for (c = 0; c < n; ++c) {
    for (r = 0; r < n; ++r) Wk[r + c * n] = W[idx[r] + idx[c] * ld];
  }
}

/* Whether the n x n W couples no two entries of different groups (of: each entry's group). */
LEARNEST_KIT int learnest_gn_apart(const learnest_real* W, int n, const unsigned char* of) {
  int r, c;
  for (c = 0; c < n; ++c) {
    for (r = 0; r < n; ++r) {
      if (of[r] != of[c] && W[r + c * n] != 0) return 0;
    }
  }
  return 1;
}

/* Whether the scaled weights in force keep the groups apart. */
LEARNEST_KIT int learnest_gn_split(const struct learnest_gn* s) {
  return learnest_gn_apart(s->Q, LEARNEST_NX, learnest_comp_of_x)
         && learnest_gn_apart(s->P, LEARNEST_NX, learnest_comp_of_x)
         && learnest_gn_apart(s->R, LEARNEST_NY, learnest_comp_of_y);
}

/* The normal equations of learnest_gn_build for a model whose states, outputs and weights
 * fall apart in groups: H is block diagonal in the groups. Group k's blocks (n_k x n_k) sit at
 * offset sum_{j<k} n_j^2 of each node's D and E slot; g stays in state order; hess = 0: the
 * gradient alone. */
LEARNEST_KIT void learnest_gn_build_split(struct learnest_gn* s, const struct learnest_window* w,
                                          const learnest_real* X, int hess) {
  const struct learnest_lin* L = LEARNEST_GN_LIN(s);
  int i, k, r, c, q, xo = 0, yo = 0, bo = 0;
  if (hess) {
    memset(s->D, 0, sizeof s->D);
    memset(s->E, 0, sizeof s->E);
  }
  memset(s->g, 0, sizeof s->g);
  for (k = 0; k < LEARNEST_NCOMP; ++k) {
    const int n = LEARNEST_GROUP_NX(k), ny = LEARNEST_GROUP_NY(k);
    const unsigned char* S = learnest_comp_x + xo;
    const unsigned char* O = learnest_comp_y + yo;
    learnest_real Qk[LEARNEST_NXX], Rk[LEARNEST_NYY];  /* the group's weights */
    learnest_gn_block(s->Q, LEARNEST_NX, S, n, Qk);
    learnest_gn_block(s->R, LEARNEST_NY, O, ny, Rk);
    for (i = 0; i <= LEARNEST_N; ++i) {
      learnest_real* D = s->D + i * LEARNEST_NXX + bo;
      learnest_real* g = s->g + i * LEARNEST_NX;
      const learnest_real* x = X + i * LEARNEST_NX;
      learnest_real a = i ? 1 - w->mask[i - 1] : 1, m = w->mask[i];
      if (a != 0) {  /* arrival term */
        for (c = 0; c < n; ++c) {
          for (r = s->dp ? c : 0; r < (s->dp ? c + 1 : n); ++r) {
            const learnest_real P = a * s->P[S[r] + S[c] * LEARNEST_NX];
            if (hess && r >= c) D[r + c * n] += P;
            g[S[r]] += P * (x[S[c]] - w->xbar[S[c]]);
          }
        }
      }
      if (m == 0) continue;
      if (ny > 0) {  /* measurement term: the group's outputs and states */
        const learnest_real* Gi = w->G + i * LEARNEST_NY;
        const learnest_real* Ci = L->C + i * LEARNEST_NY * LEARNEST_NX;
        learnest_real C[LEARNEST_NY * LEARNEST_NX], RC[LEARNEST_NY * LEARNEST_NX], Rv[LEARNEST_NY];
        for (r = 0; r < ny; ++r) {
          s->rv[r] = Gi[O[r]] * (w->Y[i * LEARNEST_NY + O[r]] - L->h[i * LEARNEST_NY + O[r]]);
          for (c = 0; c < n; ++c) C[r + c * ny] = Gi[O[r]] * Ci[O[r] + S[c] * LEARNEST_NY];
        }
        learnest_gn_weigh(Rk, ny, s->dr, s->rv, C, 0, hess ? n : 0, Rv, RC);
        for (c = 0; c < n; ++c) {
          for (r = c; hess && r < n; ++r) {
            learnest_real v = 0;
            for (q = 0; q < ny; ++q) v += C[q + r * ny] * RC[q + c * ny];
            D[r + c * n] += m * v;
          }
          for (q = 0; q < ny; ++q) g[S[c]] -= m * C[q + c * ny] * Rv[q];
        }
      }
      if (i < LEARNEST_N) {  /* process term: couples x_i and x_{i+1} within the group */
        const learnest_real* Ai = L->A + i * LEARNEST_NXX;
        learnest_real* Dn = s->D + (i + 1) * LEARNEST_NXX + bo;
        learnest_real* E = s->E + i * LEARNEST_NXX + bo;
        learnest_real* gn = s->g + (i + 1) * LEARNEST_NX;
        learnest_real A[LEARNEST_NXX], QA[LEARNEST_NXX], Qw[LEARNEST_NX];
        for (r = 0; r < n; ++r) {
          s->rw[r] = X[(i + 1) * LEARNEST_NX + S[r]] - L->F[i * LEARNEST_NX + S[r]];
          for (c = 0; c < n; ++c) A[r + c * n] = Ai[S[r] + S[c] * LEARNEST_NX];
        }
        learnest_gn_weigh(Qk, n, s->dq, s->rw, A, 0, hess ? n : 0, Qw, QA);
        for (q = 0; hess && q < n * n; ++q) E[q] = -m * QA[q];  /* H_{i+1,i} = -m Q A */
        for (c = 0; c < n; ++c) {
          for (r = c; hess && r < n; ++r) {
            learnest_real v = 0;
            for (q = 0; q < n; ++q) v += A[q + r * n] * QA[q + c * n];
            D[r + c * n] += m * v;
            if (!s->dq || r == c) Dn[r + c * n] += m * Qk[r + c * n];
          }
          for (q = 0; q < n; ++q) g[S[c]] -= m * A[q + c * n] * Qw[q];
          gn[S[c]] += m * Qw[c];
        }
      }
    }
    xo += n;
    yo += ny;
    bo += n * n;
  }
}

/* Solve the split normal equations group by group (Xt as the groups' right-hand sides);
 * factor = 0: D and E hold the groups' factors already. */
LEARNEST_KIT int learnest_gn_solve_split(struct learnest_gn* s, int factor) {
  int i, k, r, xo = 0, bo = 0;
  for (k = 0; k < LEARNEST_NCOMP; ++k) {
    const int n = LEARNEST_GROUP_NX(k);
    const unsigned char* S = learnest_comp_x + xo;
    learnest_real* z = s->Xt + (LEARNEST_N + 1) * xo;
    for (i = 0; i <= LEARNEST_N; ++i) {
      for (r = 0; r < n; ++r) z[i * n + r] = -s->g[i * LEARNEST_NX + S[r]];
    }
    if (!learnest_btd_solve_n(n, LEARNEST_NXX, s->D + bo, s->E + bo, z, factor)) return 0;
    for (i = 0; i <= LEARNEST_N; ++i) {
      for (r = 0; r < n; ++r) s->dx[i * LEARNEST_NX + S[r]] = z[i * n + r];
    }
    xo += n;
    bo += n * n;
  }
  return 1;
}

#endif /* LEARNEST_NCOMP > 1 */
#endif /* LEARNEST_GN_GROUPS_H */
