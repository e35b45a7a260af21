/* learnest_gate.h -- the innovation gate and lost-track recovery of every estimator (the
 * Python twin is learnest_codegen/estimators/gate.py; tests/test_ckit.py compares them).
 *
 * Gate: a valid output j of a sample is rejected when d2_j = (y_j - yhat_j)^2 / S_jj exceeds
 * the threshold (a chi-square(1) quantile) or is NaN; yhat and S are the predicted output and
 * innovation variance (each estimator's header says which). A rejected output is left out of
 * the update and the step returns LEARNEST_MEASUREMENT_REJECTED (1). An output the caller
 * marked missing is neither tested nor rejected.
 * Recovery: from the recover_after-th consecutive step with a rejection on, each such step
 * multiplies the inflation rho by inflation_step (up to cap) and the estimator inflates its
 * uncertainty by it; a step that accepts its valid outputs resets the streak and divides rho
 * by inflation_step, down to 1. A step without any valid output leaves the gate as it was.
 */
#ifndef LEARNEST_GATE_H
#define LEARNEST_GATE_H

#include "learnest_kit.h"

struct learnest_gate {
  learnest_real threshold, inflation_step, rho, cap;  /* threshold < 0: no gate */
  int recover_after, streak;
};

LEARNEST_KIT void learnest_gate_defaults(struct learnest_gate* g, learnest_real threshold,
                                         int recover_after, learnest_real inflation,
                                         learnest_real cap) {
  g->threshold = (threshold == 0 || isinf(threshold)) ? -1 : threshold;
  g->recover_after = recover_after;
  g->inflation_step = inflation;
  g->cap = cap;
  g->rho = 1;
  g->streak = 0;
}

/* LEARNEST_OK when the settings are in their documented ranges (learnest_status.h):
 * threshold 0 or +inf (no gate) or in [LEARNEST_THRESHOLD_MIN, LEARNEST_THRESHOLD_MAX],
 * recover_after in [1, LEARNEST_RECOVER_AFTER_MAX], inflation in (1, LEARNEST_INFLATION_MAX];
 * LEARNEST_BAD_ARGUMENT otherwise. */
LEARNEST_KIT int learnest_gate_check(learnest_real threshold, int recover_after,
                                     learnest_real inflation) {
  /* The bounds in the real type: a float build takes the float nearest to each. */
  const learnest_real t_min = (learnest_real)LEARNEST_THRESHOLD_MIN;
  const learnest_real t_max = (learnest_real)LEARNEST_THRESHOLD_MAX;
  const learnest_real i_max = (learnest_real)LEARNEST_INFLATION_MAX;
  int off = threshold == 0 || (isinf(threshold) && threshold > 0);
  if (!off && !(threshold >= t_min && threshold <= t_max)) return LEARNEST_BAD_ARGUMENT;
  if (recover_after < 1 || recover_after > LEARNEST_RECOVER_AFTER_MAX) return LEARNEST_BAD_ARGUMENT;
  if (!(inflation > 1 && inflation <= i_max)) return LEARNEST_BAD_ARGUMENT;
  return LEARNEST_OK;
}

/* New settings (checked as learnest_gate_check; nothing changes on an error); rho and the
 * streak are kept. */
LEARNEST_KIT int learnest_gate_set(struct learnest_gate* g, learnest_real threshold,
                                   int recover_after, learnest_real inflation) {
  int code = learnest_gate_check(threshold, recover_after, inflation);
  if (code != LEARNEST_OK) return code;
  learnest_gate_defaults(g, threshold, recover_after, inflation, g->cap);
  return LEARNEST_OK;
}

LEARNEST_KIT void learnest_gate_restart(struct learnest_gate* g) {
  g->rho = 1;
  g->streak = 0;
}

/* rejected[j] = output j is valid (valid NULL: all are) and the gate rejects d2[j]; returns 1
 * when any output is rejected. */
LEARNEST_KIT int learnest_gate_test(const struct learnest_gate* g, const learnest_real* d2,
                                    const unsigned char* valid, int ny, int* rejected) {
  int j, any = 0;
  for (j = 0; j < ny; ++j) {
    rejected[j] = (!valid || valid[j]) && g->threshold >= 0 && !(d2[j] <= g->threshold);
    any |= rejected[j];
  }
  return any;
}

/* 1 when some output of the sample is valid (valid NULL: all are, ny > 0). */
LEARNEST_KIT int learnest_any_valid(const unsigned char* valid, int ny) {
  int j;
  for (j = 0; j < ny; ++j) {
    if (!valid || valid[j]) return 1;
  }
  return 0;
}

/* Book a committed step: any = an output was rejected, any_valid = some output was valid.
 * Returns the factor to inflate the uncertainty by now (1: none). */
LEARNEST_KIT learnest_real learnest_gate_record(struct learnest_gate* g, int any, int any_valid) {
  if (!any_valid) return 1;
  if (!any) {
    g->streak = 0;
    g->rho = g->rho / g->inflation_step > 1 ? g->rho / g->inflation_step : 1;
    return 1;
  }
  ++g->streak;
  if (g->streak < g->recover_after || g->rho * g->inflation_step > g->cap) return 1;
  g->rho *= g->inflation_step;
  return g->inflation_step;
}

#endif /* LEARNEST_GATE_H */
