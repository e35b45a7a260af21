/* learnest_mhe_ipopt.h -- the reference MHE: eq. (2) solved by the Ipopt nlpsol that CasADi
 * generated, with the window, gate and restart of learnest_mhe.h. Ipopt allocates and frees
 * its problem on every solve: this estimator is the reference, not allocation-free, and one
 * library must be used from one thread at a time (CasADi's memory pool).
 *
 * Include after learnest_kit.h with LEARNEST_PREFIX, LEARNEST_NX, LEARNEST_NU, LEARNEST_NY,
 * LEARNEST_N, the parameter layout of the nlpsol (LEARNEST_NP and LEARNEST_OFF_XBAR, _U, _Y,
 * _MASK, _G, _Q, _R, _P from ParamLayout, checked against the kit's at compile time) and the
 * model hooks learnest_model_solve, learnest_model_node, learnest_model_F (learnest_casadi.h).
 */
#ifndef LEARNEST_MHE_IPOPT_H
#define LEARNEST_MHE_IPOPT_H

#include "learnest_handle.h"
#include "learnest_mhe.h"
#include "learnest_mhe_model.h"

/* The problem struct is the nlpsol's parameter vector: same size, same offsets. */
#define LEARNEST_OFFSET_IS(member, off) (offsetof(struct learnest_mhe_problem, member) == (off) * sizeof(learnest_real))
LEARNEST_STATIC_ASSERT(sizeof(struct learnest_mhe_problem) == LEARNEST_NP * sizeof(learnest_real), p_size);
LEARNEST_STATIC_ASSERT(LEARNEST_OFFSET_IS(w.xbar, LEARNEST_OFF_XBAR) && LEARNEST_OFFSET_IS(w.U, LEARNEST_OFF_U)
                       && LEARNEST_OFFSET_IS(w.Y, LEARNEST_OFF_Y) && LEARNEST_OFFSET_IS(w.mask, LEARNEST_OFF_MASK)
                       && LEARNEST_OFFSET_IS(w.G, LEARNEST_OFF_G) && LEARNEST_OFFSET_IS(Q, LEARNEST_OFF_Q)
                       && LEARNEST_OFFSET_IS(R, LEARNEST_OFF_R) && LEARNEST_OFFSET_IS(P, LEARNEST_OFF_P),
                       p_layout);

typedef struct learnest_mhe_tuning learnest_tuning;

LEARNEST_HANDLE {
  struct learnest_common c;
  struct learnest_mhe m;
  learnest_real solution[LEARNEST_NW];
  struct learnest_model model;
};

LEARNEST_KIT void learnest_est_defaults(LEARNEST_HANDLE* h) { (void)h; }

LEARNEST_KIT void learnest_est_retuned(LEARNEST_HANDLE* h) { (void)h; }

LEARNEST_KIT void learnest_est_start(LEARNEST_HANDLE* h, const learnest_real* x0,
                                     const learnest_tuning* t) {
  learnest_mhe_reset(&h->m, x0, t);
}

LEARNEST_KIT int learnest_est_step(LEARNEST_HANDLE* h, const learnest_real* u,
                                   const learnest_real* y, const unsigned char* valid,
                                   int* rejected) {
  struct learnest_mhe* m = &h->m;
  learnest_real yhat[LEARNEST_NY], C[LEARNEST_NY * LEARNEST_NX], lo[LEARNEST_NW], hi[LEARNEST_NW];
  int has_previous = h->c.samples > 0, code, any, restarted;
  const int bounded = learnest_box_tile(lo, hi, LEARNEST_N + 1);
  learnest_mhe_slide(m, &h->model, has_previous, u);
  learnest_model_node(&h->model, m->Xn + LEARNEST_N * LEARNEST_NX, u, yhat, C);
  any = learnest_mhe_gate(m, &h->c.gate, has_previous, u, y, valid, yhat, C, rejected, &restarted);
  code = learnest_model_solve(&h->model, (const learnest_real*)(const void*)&m->next, m->Xn,
                              bounded ? lo : 0, bounded ? hi : 0, h->solution);
  if (code == LEARNEST_OK && !learnest_all_finite(h->solution, LEARNEST_NW)) {
    code = LEARNEST_NONFINITE_RESULT;
  }
  if (code != LEARNEST_OK) {
    m->restart = 1;  /* as the embedded MHE: the next step restarts the window (no lock) */
    return code;
  }
  memcpy(m->Xn, h->solution, sizeof h->solution);
  learnest_box_clamp(m->Xn, LEARNEST_N + 1);  /* an interior point's last 1e-12 into the box */
  learnest_mhe_commit(m);
  (void)learnest_gate_record(&h->c.gate, rejected, valid);
  return any ? LEARNEST_MEASUREMENT_REJECTED : LEARNEST_OK;
}

#include "learnest_mhe_api.h"

#endif /* LEARNEST_MHE_IPOPT_H */
