/* kit_core.c -- the C kit's building blocks behind plain functions, for tests/test_ckit.py.
 *
 * Built on its own (no generated code) as a shared library per compiler and precision
 * (-DKIT_REAL=double|float), with the cartpole's sizes so that the Python MHE's window can be
 * driven alongside. Every function is a thin wrapper: the code under test is the kit's.
 */
#ifndef KIT_REAL
#define KIT_REAL double
#endif
#define LEARNEST_REAL KIT_REAL
#define LEARNEST_NX 4
#define LEARNEST_NU 1
#define LEARNEST_NY 2
#define LEARNEST_N 5
#define LEARNEST_MAX_INFLATION 1e4
#include "learnest_kit.h"

struct learnest_model {
  int unused;
};
/* The GN core's hooks, declared for learnest_gn.h (only its linear algebra is used here). */
static void learnest_model_stage(struct learnest_model* m, const learnest_real* x,
                                 const learnest_real* u, learnest_real* F, learnest_real* A);
static void learnest_model_node(struct learnest_model* m, const learnest_real* x,
                                const learnest_real* u, learnest_real* h, learnest_real* C);

#include "learnest_mhe.h"
#include "learnest_gn.h"

typedef learnest_real real;

#ifdef __cplusplus
extern "C" {
#endif

int kt_real_size(void) { return (int)sizeof(real); }

/* -- dense algebra */
int kt_cholesky(real* M, int n) { return learnest_cholesky(M, n); }
void kt_forward(const real* L, int n, real* b) { learnest_forward_subst(L, n, b); }
void kt_backward(const real* L, int n, real* b) { learnest_backward_subst(L, n, b); }
real kt_quad(const real* W, const real* r, int n) { return learnest_quad(W, r, n); }

int kt_spd_inverse(const real* A, int n, real* Ainv) {
  real work[64];
  return n <= 8 ? learnest_spd_inverse(A, n, Ainv, work) : -1;
}

int kt_covariance_ok(const real* A, int n) {
  real work[64];
  return n <= 8 ? learnest_covariance_ok(A, n, work) : -1;
}

/* The block-tridiagonal solve: D ((N+1) NX x NX blocks), E (N blocks), g -> dx. */
int kt_btd_solve(real* D, real* E, const real* g, real* dx) {
  return learnest_btd_solve(D, E, g, dx);
}

/* -- the gate */
size_t kt_gate_size(void) { return sizeof(struct learnest_gate); }

void kt_gate_defaults(void* g, real threshold, int recover_after, real inflation, real cap) {
  learnest_gate_defaults((struct learnest_gate*)g, threshold, recover_after, inflation, cap);
}

int kt_gate_set(void* g, real threshold, int recover_after, real inflation) {
  return learnest_gate_set((struct learnest_gate*)g, threshold, recover_after, inflation);
}

int kt_gate_test(const void* g, const real* d2, const unsigned char* valid, int* rejected) {
  return learnest_gate_test((const struct learnest_gate*)g, d2, valid, LEARNEST_NY, rejected);
}

int kt_gate_ends_episode(const void* g, const int* rejected, const unsigned char* valid) {
  return learnest_gate_ends_episode((const struct learnest_gate*)g, rejected, valid);
}

real kt_gate_record(void* g, const int* rejected, const unsigned char* valid) {
  return learnest_gate_record((struct learnest_gate*)g, rejected, valid);
}

void kt_gate_state(const void* g, real* rho, int* streaks, int* age, int* lost) {
  *rho = ((const struct learnest_gate*)g)->rho;
  memcpy(streaks, ((const struct learnest_gate*)g)->streaks, LEARNEST_NY * sizeof(int));
  *age = ((const struct learnest_gate*)g)->age;
  *lost = learnest_gate_lost((const struct learnest_gate*)g);
}

int kt_gate_reseeds(const void* g, int* rejected) {
  return learnest_gate_reseeds((const struct learnest_gate*)g, rejected);
}

/* -- the MHE window, gate and restart (learnest_mhe.h) */
size_t kt_mhe_size(void) { return sizeof(struct learnest_mhe); }

int kt_mhe_reset(void* m, const real* x0, const real* P0, const real* Q, const real* R) {
  struct learnest_mhe_tuning t;
  int code;
  memset(&t, 0, sizeof t);
  code = learnest_mhe_tune(&t, P0, Q, R);
  if (code == LEARNEST_OK) learnest_mhe_reset((struct learnest_mhe*)m, x0, &t);
  return code;
}

/* learnest_mhe_advance (H, A: the Jacobians at the leaving stage, used when a covariance is
 * carried), then the caller's prediction of the warm start's last stage. */
void kt_mhe_advance(void* m, int has_previous, const real* u, const real* x_pred, const real* H,
                    const real* A) {
  struct learnest_mhe* mhe = (struct learnest_mhe*)m;
  int carries = learnest_mhe_carries(mhe, has_previous);
  learnest_mhe_advance(mhe, has_previous, u, carries ? H : 0, carries ? A : 0);
  if (has_previous) memcpy(mhe->Xn + LEARNEST_N * LEARNEST_NX, x_pred, LEARNEST_NX * sizeof(real));
}

int kt_mhe_gate(void* m, const void* g, int has_previous, const real* u, const real* y,
                const unsigned char* valid, const real* h, const real* C, int* rejected,
                int* restarted) {
  return learnest_mhe_gate((struct learnest_mhe*)m, (const struct learnest_gate*)g, has_previous,
                           u, y, valid, h, C, rejected, restarted);
}

/* The next problem solved with X (the test's stand-in for a solver), committed. */
void kt_mhe_commit(void* m, const real* X) {
  struct learnest_mhe* mhe = (struct learnest_mhe*)m;
  memcpy(mhe->Xn, X, sizeof mhe->Xn);
  learnest_mhe_commit(mhe);
}

void kt_mhe_fail(void* m) { ((struct learnest_mhe*)m)->restart = 1; }

int kt_mhe_carried(const void* m) { return ((const struct learnest_mhe*)m)->carried; }

/* The problem being solved (next) and its warm start. */
void kt_mhe_next(const void* m, real* xbar, real* U, real* Y, real* mask, real* G, real* Xn) {
  const struct learnest_mhe* mhe = (const struct learnest_mhe*)m;
  memcpy(xbar, mhe->next.w.xbar, sizeof mhe->next.w.xbar);
  memcpy(U, mhe->next.w.U, sizeof mhe->next.w.U);
  memcpy(Y, mhe->next.w.Y, sizeof mhe->next.w.Y);
  memcpy(mask, mhe->next.w.mask, sizeof mhe->next.w.mask);
  memcpy(G, mhe->next.w.G, sizeof mhe->next.w.G);
  memcpy(Xn, mhe->Xn, sizeof mhe->Xn);
}

/* The weights of the current problem (column-major). */
void kt_mhe_weights(const void* m, real* Q, real* R, real* P) {
  const struct learnest_mhe* mhe = (const struct learnest_mhe*)m;
  memcpy(Q, mhe->now.Q, sizeof mhe->now.Q);
  memcpy(R, mhe->now.R, sizeof mhe->now.R);
  memcpy(P, mhe->now.P, sizeof mhe->now.P);
}

#ifdef __cplusplus
}
#endif

/* Never called (the GN core's line search and linearisation are tested through kit_gn.c). */
static void learnest_model_stage(struct learnest_model* m, const learnest_real* x,
                                 const learnest_real* u, learnest_real* F, learnest_real* A) {
  (void)m, (void)x, (void)u, (void)F, (void)A;
}
static void learnest_model_node(struct learnest_model* m, const learnest_real* x,
                                const learnest_real* u, learnest_real* h, learnest_real* C) {
  (void)m, (void)x, (void)u, (void)h, (void)C;
}
