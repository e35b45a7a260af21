/* learnest_bounds.h -- box bounds on the states of an MHE's window (MHESettings.state_bounds).
 *
 * The generated glue gives LEARNEST_STATE_LO and LEARNEST_STATE_HI, NX initialisers each
 * (-HUGE_VAL / HUGE_VAL: that side open). Every state of the window then stays in the box:
 * the warm start is clamped into it (learnest_box_clamp; estimators/mhe.py clamps its guess
 * alike), Ipopt gets the box as variable bounds (learnest_box_tile), and each Gauss-Newton step
 * of the embedded MHE is the exact solution of its box-constrained quadratic model
 * (learnest_gn_box_step, learnest_gn.h: an active set started from the variables that sit on
 * a bound with the gradient pushing out of the box, learnest_box_active, whose rows and
 * columns of the normal equations become the identity's, learnest_box_fix). Its fixed point
 * is a KKT point of the bounded problem, the problem Ipopt solves. Without the macros every
 * function here does nothing.
 *
 * Include after learnest_kit.h with LEARNEST_NX and LEARNEST_N.
 */
#ifndef LEARNEST_BOUNDS_H
#define LEARNEST_BOUNDS_H

#ifdef LEARNEST_STATE_LO
#define LEARNEST_BOUNDED 1
static const learnest_real learnest_state_lo[LEARNEST_NX] = LEARNEST_STATE_LO;
static const learnest_real learnest_state_hi[LEARNEST_NX] = LEARNEST_STATE_HI;
#else
#define LEARNEST_BOUNDED 0
#endif

/* The nodes x_0..x_{nodes-1} of X (NX each) clamped into the box. */
LEARNEST_KIT void learnest_box_clamp(learnest_real* X, int nodes) {
#if LEARNEST_BOUNDED
  int i, j;
  for (i = 0; i < nodes; ++i) {
    for (j = 0; j < LEARNEST_NX; ++j) {
      learnest_real* v = X + i * LEARNEST_NX + j;
      *v = *v < learnest_state_lo[j] ? learnest_state_lo[j] : *v > learnest_state_hi[j] ? learnest_state_hi[j] : *v;
    }
  }
#else
  (void)X;
  (void)nodes;
#endif
}

/* lo and hi (nodes x NX each) of the window's variables; 0 without bounds (none given). */
LEARNEST_KIT int learnest_box_tile(learnest_real* lo, learnest_real* hi, int nodes) {
#if LEARNEST_BOUNDED
  int i;
  for (i = 0; i < nodes; ++i) {
    memcpy(lo + i * LEARNEST_NX, learnest_state_lo, sizeof learnest_state_lo);
    memcpy(hi + i * LEARNEST_NX, learnest_state_hi, sizeof learnest_state_hi);
  }
  return 1;
#else
  (void)lo;
  (void)hi;
  (void)nodes;
  return 0;
#endif
}

/* act[v] of each variable of X (N+1 nodes, inside the box) with gradient g: -1 (+1) when it
 * sits on its lower (upper) bound with g pushing it out of the box, else 0. */
LEARNEST_KIT void learnest_box_active(const learnest_real* X, const learnest_real* g, signed char* act) {
#if LEARNEST_BOUNDED
  int v;
  for (v = 0; v < (LEARNEST_N + 1) * LEARNEST_NX; ++v) {
    const int j = v % LEARNEST_NX;
    act[v] = (signed char)(X[v] <= learnest_state_lo[j] && g[v] > 0 ? -1
                           : X[v] >= learnest_state_hi[j] && g[v] < 0 ? 1 : 0);
  }
#else
  (void)X;
  (void)g;
  (void)act;
#endif
}

/* In the normal equations H dx = b (diagonal blocks D_i, lower triangles, and E_i = H_{i+1,i},
 * NX x NX column-major) the row and column of each variable with act[v] != 0 become the
 * identity's, so the solve returns b_v for it and the others do not see it. */
LEARNEST_KIT void learnest_box_fix(learnest_real* D, learnest_real* E, const signed char* act) {
#if LEARNEST_BOUNDED
  int i, j, k;
  for (i = 0; i <= LEARNEST_N; ++i) {
    learnest_real* Di = D + i * LEARNEST_NX * LEARNEST_NX;
    for (j = 0; j < LEARNEST_NX; ++j) {
      if (!act[i * LEARNEST_NX + j]) continue;
      for (k = 0; k < LEARNEST_NX; ++k) {
        Di[j + k * LEARNEST_NX] = 0;
        Di[k + j * LEARNEST_NX] = 0;
        if (i < LEARNEST_N) E[i * LEARNEST_NX * LEARNEST_NX + k + j * LEARNEST_NX] = 0;  /* H_{i+1,i}[:, j] */
        if (i > 0) E[(i - 1) * LEARNEST_NX * LEARNEST_NX + j + k * LEARNEST_NX] = 0;   /* H_{i,i-1}[j, :] */
      }
      Di[j + j * LEARNEST_NX] = 1;
    }
  }
#else
  (void)D;
  (void)E;
  (void)act;
#endif
}

#endif /* LEARNEST_BOUNDS_H */
