/* learnest_mhe_gn.h -- the embedded MHE: eq. (2) solved by the Gauss-Newton core
 * (learnest_gn.h), converged (mhe_gn) or one iteration per sample (mhe_rti), with no Ipopt
 * and no malloc (docs/embedded_mhe.md).
 *
 * Include after learnest_kit.h with LEARNEST_PREFIX, LEARNEST_NX, LEARNEST_NU, LEARNEST_NY,
 * LEARNEST_N, the options' defaults LEARNEST_DEFAULT_MODE (0 converged, 1 RTI),
 * LEARNEST_DEFAULT_MAX_ITER, LEARNEST_DEFAULT_TOL, and the model of learnest_gn.h plus
 * learnest_model_F(md, x, u, F) (the warm start's prediction).
 */
#ifndef LEARNEST_MHE_GN_H
#define LEARNEST_MHE_GN_H

#include "learnest_gn.h"
#include "learnest_handle.h"
#include "learnest_mhe_model.h"

typedef struct learnest_mhe_tuning learnest_tuning;

LEARNEST_HANDLE {
  struct learnest_common c;
  struct learnest_mhe m;
  struct learnest_gn gn;
  struct learnest_model model;
};

LEARNEST_KIT void learnest_est_defaults(LEARNEST_HANDLE* h) {
  h->gn.mode = LEARNEST_DEFAULT_MODE;
  h->gn.max_iter = LEARNEST_DEFAULT_MAX_ITER;
  h->gn.tol = (learnest_real)LEARNEST_DEFAULT_TOL;
}

LEARNEST_KIT void learnest_est_retuned(LEARNEST_HANDLE* h) { learnest_gn_scale(&h->gn, &h->m.now); }

LEARNEST_KIT void learnest_est_start(LEARNEST_HANDLE* h, const learnest_real* x0,
                                     const learnest_tuning* t) {
  learnest_mhe_reset(&h->m, x0, t);
  learnest_gn_scale(&h->gn, &h->m.now);
  h->gn.iterations = 0;
  h->gn.lin_valid = 0;
}

/* One sample: the window moves on, the warm start is predicted and linearised (RTI reuses the
 * shifted stages'), the gate weighs the new outputs (or restarts the window), the
 * Gauss-Newton solve runs; a failure changes nothing but makes the next step restart. */
LEARNEST_KIT int learnest_est_step(LEARNEST_HANDLE* h, const learnest_real* u,
                                   const learnest_real* y, const unsigned char* valid,
                                   int* rejected) {
  struct learnest_mhe* m = &h->m;
  int has_previous = h->c.samples > 0, code, steps, any, restarted;
  learnest_mhe_slide(m, &h->model, has_previous, u);
  learnest_gn_advance(&h->gn, &h->model, &m->next.w, m->Xn, has_previous);
  any = learnest_mhe_gate(m, &h->c.gate, has_previous, u, y, valid,
                          LEARNEST_GN_LIN(&h->gn)->h + LEARNEST_N * LEARNEST_NY,
                          LEARNEST_GN_LIN(&h->gn)->C + LEARNEST_N * LEARNEST_NY * LEARNEST_NX, rejected, &restarted);
  if (restarted) learnest_gn_linearise(&h->model, &m->next.w, m->Xn, LEARNEST_GN_LIN(&h->gn));
  learnest_gn_scale(&h->gn, &m->next);  /* the arrival weight may have changed */
  code = learnest_gn_solve(&h->gn, &h->model, &m->next.w, m->Xn, &steps);
  if (code == LEARNEST_OK && !learnest_all_finite(m->Xn, LEARNEST_NW)) code = LEARNEST_NONFINITE_RESULT;
  if (code != LEARNEST_OK) {
    h->gn.lin_valid = 0;  /* lin belongs to the abandoned problem */
    m->restart = 1;       /* the same window would fail again: restart it from the prediction */
    return code;
  }
  h->gn.iterations = steps;
  learnest_mhe_commit(m);
  h->gn.lin_valid = 1;
  (void)learnest_gate_record(&h->c.gate, rejected, valid);
  return any ? LEARNEST_MEASUREMENT_REJECTED : LEARNEST_OK;
}

#include "learnest_mhe_api.h"

int LEARNEST_API(set_options)(LEARNEST_HANDLE* h, int mode, int max_iter, learnest_real tol) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  /* the bounds in the real type: a float build takes the float nearest to each (and its own
   * lower end: below it a float step cannot be met) */
  const learnest_real tol_min = LEARNEST_IS_FLOAT ? (learnest_real)LEARNEST_TOL_FLOAT32_MIN
                                                  : (learnest_real)LEARNEST_TOL_MIN;
  if ((mode != LEARNEST_GN_CONVERGED && mode != LEARNEST_GN_RTI) || max_iter < 1
      || max_iter > LEARNEST_MAX_ITER_MAX || !(tol >= tol_min
                                               && tol <= (learnest_real)LEARNEST_TOL_MAX)) {
    return LEARNEST_BAD_ARGUMENT;
  }
  h->gn.mode = mode;
  h->gn.max_iter = max_iter;
  h->gn.tol = tol;
  return LEARNEST_OK;
}

int LEARNEST_API(iterations)(const LEARNEST_HANDLE* h) {
  return learnest_handle_ok(h) ? h->gn.iterations : LEARNEST_NOT_INITIALISED;
}

#endif /* LEARNEST_MHE_GN_H */
