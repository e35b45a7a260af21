/* learnest_window.h -- the moving-horizon window of every MHE (the Ipopt MHE and the
 * embedded Gauss-Newton MHE), mirrored line by line by learnest_codegen/estimators/
 * mhe_window.py (tests/test_ckit.py compares the two on random sequences).
 *
 * Define before including (after learnest_kit.h): LEARNEST_NX, LEARNEST_NU, LEARNEST_NY and
 * LEARNEST_N (the horizon: the window holds N+1 stages, oldest first).
 *
 * The window holds what the cost of eq. (2) reads (estimators/mhe_problem.py): the arrival
 * prior xbar, per stage i the input U_i (applied since the previous sample), the
 * measurement Y_i, the mask m_i (1: stage i holds a sample) and the per-output weights G_i
 * (1: output j of sample i enters the cost; 0: it was missing, rejected by the gate, or
 * folded into a restart prior). Y holds a measurement only where G is 1 (0 elsewhere), so a
 * missing output's value is never read. The blocks are laid out as ParamLayout's first ones.
 */
#ifndef LEARNEST_WINDOW_H
#define LEARNEST_WINDOW_H

#include "learnest_kit.h"

#if !defined(LEARNEST_NX) || !defined(LEARNEST_NU) || !defined(LEARNEST_NY) || !defined(LEARNEST_N)
#error "learnest_window.h: define LEARNEST_NX, LEARNEST_NU, LEARNEST_NY and LEARNEST_N"
#endif

#define LEARNEST_NW ((LEARNEST_N + 1) * LEARNEST_NX)

struct learnest_window {
  learnest_real xbar[LEARNEST_NX];
  learnest_real U[(LEARNEST_N + 1) * LEARNEST_NU];
  learnest_real Y[(LEARNEST_N + 1) * LEARNEST_NY];
  learnest_real mask[LEARNEST_N + 1];
  learnest_real G[(LEARNEST_N + 1) * LEARNEST_NY];
};

/* An empty window with prior x0. */
LEARNEST_KIT void learnest_window_reset(struct learnest_window* w, const learnest_real* x0) {
  memset(w, 0, sizeof *w);
  memcpy(w->xbar, x0, sizeof w->xbar);
}

/* Drop the first of `count` blocks of `width` values; the last block keeps its value. */
LEARNEST_KIT void learnest_shift(learnest_real* block, int width, int count) {
  memmove(block, block + width, (size_t)((count - 1) * width) * sizeof(learnest_real));
}

/* The window of the next sample from w (solved with states X, N+1 stages): one stage older;
 * once the window was full the arrival prior moves on to X's second stage. The last stage
 * keeps the old values until learnest_window_open writes the new sample's. */
LEARNEST_KIT void learnest_window_shift(struct learnest_window* w, const learnest_real* X) {
  if (w->mask[0] == 1) memcpy(w->xbar, X + LEARNEST_NX, sizeof w->xbar);
  learnest_shift(w->U, LEARNEST_NU, LEARNEST_N + 1);
  learnest_shift(w->Y, LEARNEST_NY, LEARNEST_N + 1);
  learnest_shift(w->mask, 1, LEARNEST_N + 1);
  learnest_shift(w->G, LEARNEST_NY, LEARNEST_N + 1);
}

/* The new sample's stage: input u, mask 1, no measurement yet (learnest_window_weigh). */
LEARNEST_KIT void learnest_window_open(struct learnest_window* w, const learnest_real* u) {
  memcpy(w->U + LEARNEST_N * LEARNEST_NU, u, LEARNEST_NU * sizeof(learnest_real));
  memset(w->Y + LEARNEST_N * LEARNEST_NY, 0, LEARNEST_NY * sizeof(learnest_real));
  memset(w->G + LEARNEST_N * LEARNEST_NY, 0, LEARNEST_NY * sizeof(learnest_real));
  w->mask[LEARNEST_N] = 1;
}

/* The new sample's measurement y: output j enters the cost (G_j = 1, Y_j = y_j) when keep[j],
 * else G_j = Y_j = 0. */
LEARNEST_KIT void learnest_window_weigh(struct learnest_window* w, const learnest_real* y,
                                        const int* keep) {
  int j;
  for (j = 0; j < LEARNEST_NY; ++j) {
    w->G[LEARNEST_N * LEARNEST_NY + j] = keep[j] ? 1 : 0;
    w->Y[LEARNEST_N * LEARNEST_NY + j] = keep[j] ? y[j] : 0;
  }
}

/* Every stage of the states X (N+1 x NX) set to x. */
LEARNEST_KIT void learnest_window_fill(learnest_real* X, const learnest_real* x) {
  int i;
  for (i = 0; i <= LEARNEST_N; ++i) memcpy(X + i * LEARNEST_NX, x, LEARNEST_NX * sizeof(learnest_real));
}

#endif /* LEARNEST_WINDOW_H */
