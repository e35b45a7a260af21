/* kit_gn.c -- the embedded MHE of the C kit (learnest_mhe_gn.h) over a linear model, built on
 * its own: prefix tgn, horizon 6 (tests/test_ckit.py compares it with the Python MHE). */
#include "kit_linear.h"

#define LEARNEST_PREFIX tgn
#define LEARNEST_N 6
#define LEARNEST_DEFAULT_MODE 0
#define LEARNEST_DEFAULT_MAX_ITER 30
#define LEARNEST_DEFAULT_TOL 1e-10

static void learnest_model_stage(struct learnest_model* m, const real* x, const real* u, real* F,
                                 real* A) {
  learnest_model_F(m, x, u, F);
  memcpy(A, m->A, sizeof m->A);
}

static void learnest_model_node(struct learnest_model* m, const real* x, const real* u, real* h,
                                real* C) {
  (void)u;
  kt_matvec(m->C, NY, NX, x, h);
  memcpy(C, m->C, sizeof m->C);
}

#include "learnest_mhe_gn.h"

#ifdef __cplusplus
extern "C" {
#endif

int kt_set_model(LEARNEST_HANDLE* h, const real* A, const real* B, const real* C) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  memcpy(h->model.A, A, sizeof h->model.A);
  memcpy(h->model.B, B, sizeof h->model.B);
  memcpy(h->model.C, C, sizeof h->model.C);
  h->gn.lin_valid = 0;
  return LEARNEST_OK;
}

#ifdef __cplusplus
}
#endif
