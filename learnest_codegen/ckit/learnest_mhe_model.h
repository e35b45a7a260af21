/* learnest_mhe_model.h -- the window moves of learnest_mhe.h that need the model, shared by
 * every MHE (the Ipopt reference and the embedded one).
 *
 * Include after learnest_mhe.h with the model hooks declared before (learnest_casadi.h):
 *   learnest_model_node(md, x, u, h, C), learnest_model_stage(md, x, u, F, A),
 *   learnest_model_F(md, x, u, F).
 */
#ifndef LEARNEST_MHE_MODEL_H
#define LEARNEST_MHE_MODEL_H

#include "learnest_mhe.h"

/* The window moves on by one sample with input u (learnest_mhe_advance), the arrival's
 * covariance carried along the model's linearisation at the old first node when the window
 * is full, and the warm start's new last node predicted by the model from the old last one
 * (the warm start then clamped into the state bounds, learnest_bounds.h). */
LEARNEST_KIT_INLINE void learnest_mhe_slide(struct learnest_mhe* m, struct learnest_model* md,
                                            int has_previous, const learnest_real* u) {
  learnest_real H0[LEARNEST_NY * LEARNEST_NX], A0[LEARNEST_NXX], v0[LEARNEST_NX];
  const int carries = learnest_mhe_carries(m, has_previous);
  if (carries) {
    learnest_model_node(md, m->X, m->now.w.U, v0, H0);
    learnest_model_stage(md, m->X, m->now.w.U + LEARNEST_NU, v0, A0);
  }
  learnest_mhe_advance(m, has_previous, u, carries ? H0 : 0, carries ? A0 : 0);
  if (has_previous) {
    learnest_model_F(md, m->X + LEARNEST_N * LEARNEST_NX, u, m->Xn + LEARNEST_N * LEARNEST_NX);
  }
  learnest_box_clamp(m->Xn, LEARNEST_N + 1);  /* the warm start inside the state bounds */
}

#endif /* LEARNEST_MHE_MODEL_H */
