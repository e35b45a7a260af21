/* learnest_api.h -- the C API every estimator shares: handles on caller memory, argument and
 * finiteness checks at the boundary, init that validates before it touches the workspace,
 * the gate's accessors, the run loop and the build's identity. docs/c_api.md documents it.
 *
 * Included at the end of an estimator's kit file (learnest_ukf.h, learnest_mhe_gn.h,
 * learnest_mhe_ipopt.h), which defines before it:
 *   LEARNEST_HANDLE            its handle type, whose first member is struct learnest_common c
 *   learnest_tuning            what init/reset validate before touching anything (a typedef)
 *   learnest_est_tune(t, P0, Q, R)            check and convert the covariances into t
 *   learnest_est_start(h, x0, t)              start over from x0 with t (cannot fail)
 *   learnest_est_defaults(h)                  the estimator's own options at init
 *   learnest_est_step(h, u, y, valid, rejected)  one sample (y finite where valid)
 *   learnest_est_set_noise(h, Q, R)           run-time tuning (NULL: keep)
 *   learnest_est_state(h)                     the current estimate (NX)
 * and the generated glue defines LEARNEST_PREFIX, LEARNEST_DT, LEARNEST_MAGIC,
 * LEARNEST_FINGERPRINT, LEARNEST_WORKSPACE_BYTES, LEARNEST_DEFAULT_X0/_P0/_Q/_R and the
 * gate's LEARNEST_DEFAULT_THRESHOLD/_RECOVER_AFTER/_INFLATION, LEARNEST_MAX_INFLATION, and,
 * when the system gives input limits, LEARNEST_INPUT_LO/_HI (NU initialisers each).
 *
 * The input check (estimators/inputs.py, line by line): each component u_i must be finite and,
 * with limits, in [LEARNEST_INPUT_LO_i, LEARNEST_INPUT_HI_i]; one that is not is replaced by
 * its last accepted value (zero clipped into the limits before any) and the step returns the
 * status bit LEARNEST_INPUT_REJECTED (2), OR-ed with LEARNEST_MEASUREMENT_REJECTED (1). An input
 * drives the prediction, which the innovation gate sees only once the state is already off.
 */
#ifndef LEARNEST_API_H
#define LEARNEST_API_H

#include <limits.h>

#include "learnest_gate.h"

/* A handle made by init checks its magic number, unique to the build's prefix: a NULL,
 * foreign or stale pointer is LEARNEST_NOT_INITIALISED rather than a crash. */
LEARNEST_KIT int learnest_handle_ok(const LEARNEST_HANDLE* h) {
  return h != 0 && h->c.magic == LEARNEST_MAGIC;
}

LEARNEST_STATIC_ASSERT(sizeof(LEARNEST_HANDLE) + LEARNEST_ALIGN <= LEARNEST_WORKSPACE_BYTES,
                       workspace_bytes_bounds_the_handle);

#ifdef LEARNEST_INPUT_LO
static const learnest_real learnest_input_lo[LEARNEST_NU] = LEARNEST_INPUT_LO;
static const learnest_real learnest_input_hi[LEARNEST_NU] = LEARNEST_INPUT_HI;
#endif

/* used = u with every implausible component replaced by its last accepted value; rejected[i]
 * says which were; 1 when any was. */
LEARNEST_KIT int learnest_input_check(const struct learnest_common* c, const learnest_real* u,
                                      learnest_real* used, int* rejected) {
  int i, any = 0;
  for (i = 0; i < LEARNEST_NU; ++i) {
    int ok = isfinite(u[i]) != 0;
#ifdef LEARNEST_INPUT_LO
    ok = ok && u[i] >= learnest_input_lo[i] && u[i] <= learnest_input_hi[i];
#endif
    used[i] = ok ? u[i] : c->u_held[i];
    rejected[i] = !ok;
    any |= !ok;
  }
  return any;
}

/* Counters, gate and input check of a fresh start (the gate keeps its settings). */
LEARNEST_KIT void learnest_start(LEARNEST_HANDLE* h, const learnest_real* x0,
                                 const learnest_tuning* t) {
  int i;
  h->c.samples = 0;
  h->c.rejections = 0;
  memset(h->c.rejected, 0, sizeof h->c.rejected);
  h->c.input_rejections = 0;
  memset(h->c.input_rejected, 0, sizeof h->c.input_rejected);
  for (i = 0; i < LEARNEST_NU; ++i) {  /* zero clipped into the limits */
    h->c.u_held[i] = 0;
#ifdef LEARNEST_INPUT_LO
    if (h->c.u_held[i] < learnest_input_lo[i]) h->c.u_held[i] = learnest_input_lo[i];
    if (h->c.u_held[i] > learnest_input_hi[i]) h->c.u_held[i] = learnest_input_hi[i];
#endif
  }
  learnest_gate_restart(&h->c.gate);
  learnest_est_start(h, x0, t);
}

/* x0 finite and P0, Q, R valid (the estimator's rule) into t; nothing else is touched. */
LEARNEST_KIT int learnest_tune_all(learnest_tuning* t, const learnest_real* x0,
                                   const learnest_real* P0, const learnest_real* Q,
                                   const learnest_real* R) {
  memset(t, 0, sizeof *t);  /* written whole below; compilers cannot always see it */
  if (!x0 || !P0 || !Q || !R) return LEARNEST_BAD_ARGUMENT;
  if (!learnest_all_finite(x0, LEARNEST_NX)) return LEARNEST_NONFINITE_INPUT;
  return learnest_est_tune(t, P0, Q, R);
}

const char* LEARNEST_API(fingerprint)(void) { return LEARNEST_FINGERPRINT; }

int LEARNEST_API(real_size)(void) { return (int)sizeof(learnest_real); }

double LEARNEST_API(dt)(void) { return LEARNEST_DT; }

void LEARNEST_API(sizes)(int* nx, int* nu, int* ny, int* horizon) {
  if (nx) *nx = LEARNEST_NX;
  if (nu) *nu = LEARNEST_NU;
  if (ny) *ny = LEARNEST_NY;
#ifdef LEARNEST_N
  if (horizon) *horizon = LEARNEST_N;
#else
  if (horizon) *horizon = 0;
#endif
}

size_t LEARNEST_API(workspace_size)(void) { return sizeof(LEARNEST_HANDLE) + LEARNEST_ALIGN; }

int LEARNEST_API(init)(void* mem, size_t size, const learnest_real* x0, const learnest_real* P0,
                       const learnest_real* Q, const learnest_real* R, LEARNEST_HANDLE** handle) {
  learnest_tuning t;
  LEARNEST_HANDLE* h;
  int code;
  if (!handle) return LEARNEST_BAD_ARGUMENT;
  *handle = 0;
  if (!mem) return LEARNEST_BAD_ARGUMENT;
  if (size < LEARNEST_API(workspace_size)()) return LEARNEST_NO_MEMORY;
  code = learnest_tune_all(&t, x0, P0, Q, R);
  if (code != LEARNEST_OK) return code;  /* the workspace is untouched */
  h = (LEARNEST_HANDLE*)learnest_align(mem);
  memset(h, 0, sizeof *h);
  h->c.magic = LEARNEST_MAGIC;
  learnest_gate_defaults(&h->c.gate, (learnest_real)LEARNEST_DEFAULT_THRESHOLD,
                         LEARNEST_DEFAULT_RECOVER_AFTER, (learnest_real)LEARNEST_DEFAULT_INFLATION,
                         (learnest_real)LEARNEST_MAX_INFLATION);
  learnest_est_defaults(h);
  learnest_start(h, x0, &t);
  *handle = h;
  return LEARNEST_OK;
}

int LEARNEST_API(init_default)(void* mem, size_t size, LEARNEST_HANDLE** handle) {
  static const learnest_real x0[LEARNEST_NX] = LEARNEST_DEFAULT_X0;
  static const learnest_real P0[LEARNEST_NX * LEARNEST_NX] = LEARNEST_DEFAULT_P0;
  static const learnest_real Q[LEARNEST_NX * LEARNEST_NX] = LEARNEST_DEFAULT_Q;
  static const learnest_real R[LEARNEST_NY * LEARNEST_NY] = LEARNEST_DEFAULT_R;
  return LEARNEST_API(init)(mem, size, x0, P0, Q, R, handle);
}

int LEARNEST_API(reset)(LEARNEST_HANDLE* h, const learnest_real* x0, const learnest_real* P0,
                        const learnest_real* Q, const learnest_real* R) {
  learnest_tuning t;
  int code;
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  code = learnest_tune_all(&t, x0, P0, Q, R);
  if (code != LEARNEST_OK) return code;
  learnest_start(h, x0, &t);
  return LEARNEST_OK;
}

int LEARNEST_API(set_noise)(LEARNEST_HANDLE* h, const learnest_real* Q, const learnest_real* R) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  return learnest_est_set_noise(h, Q, R);
}

int LEARNEST_API(step)(LEARNEST_HANDLE* h, const learnest_real* u, const learnest_real* y,
                       const unsigned char* valid) {
  learnest_real ys[LEARNEST_NY], us[LEARNEST_NU];
  unsigned char v[LEARNEST_NY];
  int j, code, u_any, rejected[LEARNEST_NY], u_rejected[LEARNEST_NU];
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (!u || learnest_check_flags(valid, LEARNEST_NY) != LEARNEST_OK) return LEARNEST_BAD_ARGUMENT;
  for (j = 0; j < LEARNEST_NY; ++j) v[j] = valid ? valid[j] : 1;
  if (!y && learnest_any_valid(v, LEARNEST_NY)) return LEARNEST_BAD_ARGUMENT;
  for (j = 0; j < LEARNEST_NY; ++j) {  /* a missing output's value is never read */
    if (v[j] && !isfinite(y[j])) return LEARNEST_NONFINITE_INPUT;
    ys[j] = v[j] ? y[j] : 0;
  }
  u_any = learnest_input_check(&h->c, u, us, u_rejected);
  code = learnest_est_step(h, us, ys, v, rejected);
  if (code < 0) return code;
  if (h->c.samples < INT_MAX) ++h->c.samples;  /* saturates: years of samples at 1 kHz */
  memcpy(h->c.rejected, rejected, sizeof h->c.rejected);
  for (j = 0; j < LEARNEST_NY; ++j) {
    if (h->c.rejections < INT_MAX) h->c.rejections += rejected[j];
  }
  memcpy(h->c.u_held, us, sizeof h->c.u_held);
  memcpy(h->c.input_rejected, u_rejected, sizeof h->c.input_rejected);
  for (j = 0; j < LEARNEST_NU; ++j) {
    if (h->c.input_rejections < INT_MAX) h->c.input_rejections += u_rejected[j];
  }
  if (learnest_gate_lost(&h->c.gate)) code |= LEARNEST_UNRELIABLE;
  return code | (u_any ? LEARNEST_INPUT_REJECTED : 0);
}

int LEARNEST_API(predict)(LEARNEST_HANDLE* h, const learnest_real* u) {
  static const unsigned char none[LEARNEST_NY] = {0};
  return LEARNEST_API(step)(h, u, 0, none);
}

int LEARNEST_API(run)(LEARNEST_HANDLE* h, int T, const learnest_real* U, const learnest_real* Y,
                      const unsigned char* valid, learnest_real* Xhat) {
  int k, code, status = LEARNEST_OK;
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (T < 0 || (T > 0 && (!U || !Y || !Xhat))) return LEARNEST_BAD_ARGUMENT;
  for (k = 0; k < T; ++k) {
    code = LEARNEST_API(step)(h, U + (k > 0 ? k - 1 : 0) * LEARNEST_NU, Y + k * LEARNEST_NY,
                              valid ? valid + k * LEARNEST_NY : 0);
    if (code < 0) return code;
    status |= code;  /* success codes are bits: 1 output rejected, 2 input rejected, 4 unreliable */
    memcpy(Xhat + k * LEARNEST_NX, learnest_est_state(h), LEARNEST_NX * sizeof(learnest_real));
  }
  return status;
}

int LEARNEST_API(get_state)(const LEARNEST_HANDLE* h, learnest_real* x) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (!x) return LEARNEST_BAD_ARGUMENT;
  memcpy(x, learnest_est_state(h), LEARNEST_NX * sizeof(learnest_real));
  return LEARNEST_OK;
}

int LEARNEST_API(set_gate)(LEARNEST_HANDLE* h, learnest_real threshold, int recover_after,
                           learnest_real inflation) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  return learnest_gate_set(&h->c.gate, threshold, recover_after, inflation);
}

/* The n flags of src (of the handle h) into the caller's out. */
LEARNEST_KIT int learnest_flags_out(const LEARNEST_HANDLE* h, const int* src, int n, int* out) {
  if (!learnest_handle_ok(h)) return LEARNEST_NOT_INITIALISED;
  if (!out) return LEARNEST_BAD_ARGUMENT;
  memcpy(out, src, (size_t)n * sizeof *src);
  return LEARNEST_OK;
}

int LEARNEST_API(get_rejected)(const LEARNEST_HANDLE* h, int* rejected) {
  return learnest_flags_out(h, h ? h->c.rejected : 0, LEARNEST_NY, rejected);
}

int LEARNEST_API(rejections)(const LEARNEST_HANDLE* h) {
  return learnest_handle_ok(h) ? h->c.rejections : LEARNEST_NOT_INITIALISED;
}

int LEARNEST_API(get_input_rejected)(const LEARNEST_HANDLE* h, int* rejected) {
  return learnest_flags_out(h, h ? h->c.input_rejected : 0, LEARNEST_NU, rejected);
}

int LEARNEST_API(input_rejections)(const LEARNEST_HANDLE* h) {
  return learnest_handle_ok(h) ? h->c.input_rejections : LEARNEST_NOT_INITIALISED;
}

int LEARNEST_API(samples)(const LEARNEST_HANDLE* h) {
  return learnest_handle_ok(h) ? h->c.samples : LEARNEST_NOT_INITIALISED;
}

#endif /* LEARNEST_API_H */
