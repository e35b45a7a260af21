/* learnest_gate.h -- the innovation gate, lost-track recovery and re-seed of every estimator
 * (the Python twin is learnest_codegen/estimators/gate.py; tests/test_ckit.py compares them).
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
 * output leaves rho and the streaks as they were.
 * Lost track: age counts the steps since one last accepted an output (a step whose outputs are
 * all missing or all rejected lengthens it). lost_after is recover_after plus the widenings rho
 * needs to reach cap. An estimate is lost when an output's streak has reached lost_after (a
 * track the widest gate cannot re-acquire) or age has (a run of that many predictions): each
 * step then reports LEARNEST_UNRELIABLE (4), and the next step whose gate rejects a valid
 * output re-seeds instead (learnest_gate_reseeds): it takes every valid output with the
 * estimator's widest prior (its covariance ceiling, cap times its reference covariance), which
 * ends the streaks and the age.
 *
 * Include after learnest_kit.h with LEARNEST_NY.
 */
#ifndef LEARNEST_GATE_H
#define LEARNEST_GATE_H

#include <limits.h>

#include "learnest_kit.h"

struct learnest_gate {
  learnest_real threshold, inflation_step, rho, cap;  /* threshold < 0: no gate */
  int recover_after, streaks[LEARNEST_NY];  /* per output: its rejected samples in a row */
  int age, lost_after;  /* steps since an output was accepted; lost from lost_after on */
};

/* recover_after plus the number of widenings by inflation that keep rho within cap (counted
 * in double, as estimators/gate.py lost_after). */
LEARNEST_KIT void learnest_gate_horizon(struct learnest_gate* g) {
  double r = 1;
  int n = 0;
  while (r * (double)g->inflation_step <= (double)g->cap && n < 1000) {
    r *= (double)g->inflation_step;
    ++n;
  }
  g->lost_after = g->recover_after + n;
}

LEARNEST_KIT void learnest_gate_defaults(struct learnest_gate* g, learnest_real threshold,
                                         int recover_after, learnest_real inflation,
                                         learnest_real cap) {
  g->threshold = (threshold == 0 || isinf(threshold)) ? -1 : threshold;
  g->recover_after = recover_after;
  g->inflation_step = inflation;
  g->cap = cap;
  g->rho = 1;
  memset(g->streaks, 0, sizeof g->streaks);
  g->age = 0;
  learnest_gate_horizon(g);
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

/* New settings (checked as learnest_gate_check; nothing changes on an error); rho, the streaks
 * and the age are kept. */
LEARNEST_KIT int learnest_gate_set(struct learnest_gate* g, learnest_real threshold,
                                   int recover_after, learnest_real inflation) {
  int code = learnest_gate_check(threshold, recover_after, inflation);
  if (code != LEARNEST_OK) return code;
  g->threshold = (threshold == 0 || isinf(threshold)) ? -1 : threshold;
  g->recover_after = recover_after;
  g->inflation_step = inflation;
  learnest_gate_horizon(g);
  return LEARNEST_OK;
}

LEARNEST_KIT void learnest_gate_restart(struct learnest_gate* g) {
  g->rho = 1;
  memset(g->streaks, 0, sizeof g->streaks);
  g->age = 0;
}

/* The longest streak of the outputs. */
LEARNEST_KIT int learnest_gate_streak(const struct learnest_gate* g) {
  int j, longest = 0;
  for (j = 0; j < LEARNEST_NY; ++j) longest = g->streaks[j] > longest ? g->streaks[j] : longest;
  return longest;
}

/* 1 when the estimate is lost: an output rejected lost_after times in a row, or no output
 * accepted for lost_after steps. */
LEARNEST_KIT int learnest_gate_lost(const struct learnest_gate* g) {
  return g->age >= g->lost_after || learnest_gate_streak(g) >= g->lost_after;
}

/* 1 when this step re-seeds: the estimate is lost and the gate rejected a valid output of the
 * sample; rejected (NY) is then cleared (every valid output is taken). */
LEARNEST_KIT int learnest_gate_reseeds(const struct learnest_gate* g, int* rejected) {
  int j, any = 0;
  for (j = 0; j < LEARNEST_NY; ++j) any |= rejected[j];
  if (!any || !learnest_gate_lost(g)) return 0;
  for (j = 0; j < LEARNEST_NY; ++j) rejected[j] = 0;
  return 1;
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
  int j, any = 0, due = 0, accepted = 0;
  for (j = 0; j < LEARNEST_NY; ++j) accepted |= (!valid || valid[j]) && !rejected[j];
  g->age = accepted ? 0 : (g->age < INT_MAX ? g->age + 1 : g->age);
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
