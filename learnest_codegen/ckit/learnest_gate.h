/* learnest_gate.h -- the innovation gate and lost-track recovery of every estimator (the
 * Python twin is learnest_codegen/estimators/gate.py; tests/test_ckit.py compares them).
 *
 * Gate: a valid output j of a sample is rejected when d2_j = (y_j - yhat_j)^2 / S_jj exceeds
 * the threshold (a chi-square(1) quantile) or is NaN; yhat and S are the predicted output and
 * innovation variance (each estimator's header says which). A rejected output is left out of
 * the update and the step returns LEARNEST_MEASUREMENT_REJECTED (1). An output the caller
 * marked missing is neither tested nor rejected.
 * Recovery: the streak is kept per output and counts that output's own samples: a rejection
 * lengthens it, an acceptance ends it, a missing sample does neither (so the accepted samples
 * of a fast output do not end the streak of a slow one that keeps being rejected). A step that
 * rejects an output whose streak has reached recover_after multiplies the inflation rho by
 * inflation_step (up to cap) and the estimator inflates its uncertainty by it; a step that
 * accepts its valid outputs divides rho by inflation_step, down to 1; a step without any valid
 * output leaves the gate as it was. With every output sampled every step this is the
 * single-rate rule of docs/reliability.md.
 *
 * Include after learnest_kit.h with LEARNEST_NY.
 */
#ifndef LEARNEST_GATE_H
#define LEARNEST_GATE_H

#include "learnest_kit.h"

struct learnest_gate {
  learnest_real threshold, inflation_step, rho, cap;  /* threshold < 0: no gate */
  int recover_after, streaks[LEARNEST_NY];  /* per output: its rejected samples in a row */
};

LEARNEST_KIT void learnest_gate_defaults(struct learnest_gate* g, learnest_real threshold,
                                         int recover_after, learnest_real inflation,
                                         learnest_real cap) {
  g->threshold = (threshold == 0 || isinf(threshold)) ? -1 : threshold;
  g->recover_after = recover_after;
  g->inflation_step = inflation;
  g->cap = cap;
  g->rho = 1;
  memset(g->streaks, 0, sizeof g->streaks);
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
  g->threshold = (threshold == 0 || isinf(threshold)) ? -1 : threshold;
  g->recover_after = recover_after;
  g->inflation_step = inflation;
  return LEARNEST_OK;
}

LEARNEST_KIT void learnest_gate_restart(struct learnest_gate* g) {
  g->rho = 1;
  memset(g->streaks, 0, sizeof g->streaks);
}

/* The longest streak of the outputs. */
LEARNEST_KIT int learnest_gate_streak(const struct learnest_gate* g) {
  int j, longest = 0;
  for (j = 0; j < LEARNEST_NY; ++j) longest = g->streaks[j] > longest ? g->streaks[j] : longest;
  return longest;
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

/* 1 when this step (before learnest_gate_record) ends a recovery episode: it rejects nothing
 * and accepts a sample of an output whose streak had reached recover_after (the MHEs then
 * restart their window). */
LEARNEST_KIT int learnest_gate_ends_episode(const struct learnest_gate* g, const int* rejected,
                                            const unsigned char* valid) {
  int j, ends = 0;
  for (j = 0; j < LEARNEST_NY; ++j) {
    if (rejected[j]) return 0;
    ends |= (!valid || valid[j]) && g->streaks[j] >= g->recover_after;
  }
  return ends;
}

/* Book a committed step: rejected (NY) the outputs rejected, valid (NY; NULL: all) those the
 * step had. Returns the factor to inflate the uncertainty by now (1: none). */
LEARNEST_KIT learnest_real learnest_gate_record(struct learnest_gate* g, const int* rejected,
                                                const unsigned char* valid) {
  int j, any = 0, due = 0;
  if (!learnest_any_valid(valid, LEARNEST_NY)) return 1;
  for (j = 0; j < LEARNEST_NY; ++j) {
    if (valid && !valid[j]) continue;  /* a missing sample neither lengthens nor ends it */
    g->streaks[j] = rejected[j] ? g->streaks[j] + 1 : 0;
    any |= rejected[j];
    due |= rejected[j] && g->streaks[j] >= g->recover_after;
  }
  if (!any) {
    g->rho = g->rho / g->inflation_step > 1 ? g->rho / g->inflation_step : 1;
    return 1;
  }
  if (!due || g->rho * g->inflation_step > g->cap) return 1;
  g->rho *= g->inflation_step;
  return g->inflation_step;
}

#endif /* LEARNEST_GATE_H */
