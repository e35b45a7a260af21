/* learnest_mhe.h -- what the Ipopt MHE and the embedded Gauss-Newton MHE share: the problem of
 * a sample (window and weights, laid out as ParamLayout in estimators/mhe_problem.py), their
 * tuning from covariances, the arrival weight (the running one, or a first prior's covariance
 * carried forward, estimators/arrival.py), the innovation gate of a new sample and the
 * recovery's restart and re-seed (estimators/mhe.py is the Python reference, line by line).
 *
 * Ceilings: a restart's prior variances are at most LEARNEST_MAX_INFLATION times the running
 * arrival covariance's, and the covariances that become arrival weights (the restart prior's
 * posterior, a carried one) at most LEARNEST_ARRIVAL_CEILING (100) times: the arrival weight
 * then stays within that factor of the running one, which the Gauss-Newton normal equations
 * resolve in float32 (with 1e3 the float32 mhe_gn failed with MAX_ITERATIONS after a gap of
 * 10,000 samples, with 1e5 at every step after a restart; docs/reports/reliability.md).
 *
 * Include after learnest_kit.h with LEARNEST_NX, LEARNEST_NU, LEARNEST_NY, LEARNEST_N and
 * LEARNEST_MAX_INFLATION.
 */
#ifndef LEARNEST_MHE_H
#define LEARNEST_MHE_H

#include "learnest_bounds.h"
#include "learnest_dense.h"
#include "learnest_gate.h"
#include "learnest_update.h"
#include "learnest_window.h"

/* 1: the arrival covariance is carried by the EKF recursion (learnest_mhe_carry) from reset on
 * and never settles back to the running weight (MHESettings.arrival_update). */
#ifndef LEARNEST_ARRIVAL_UPDATE
#define LEARNEST_ARRIVAL_UPDATE 0
#endif

#define LEARNEST_NXX (LEARNEST_NX * LEARNEST_NX)
#define LEARNEST_NYY (LEARNEST_NY * LEARNEST_NY)
#define LEARNEST_NMAX (LEARNEST_NX > LEARNEST_NY ? LEARNEST_NX : LEARNEST_NY)

/* The structural nonzeros of A = dF/dx and C = dh/dx (column-major, 1 a nonzero) when the
 * generated glue gives them (LEARNEST_A_PATTERN, LEARNEST_C_PATTERN: codegen/mhe_gn.py): the
 * normal equations' assembly, the carried covariance and the gate skip their zero terms
 * (LEARNEST_NZ); without them, A and C are taken as dense. */
#ifdef LEARNEST_A_PATTERN
static const unsigned char learnest_a_nz[LEARNEST_NXX] = LEARNEST_A_PATTERN;
#define LEARNEST_A_NZ learnest_a_nz
#else
#define LEARNEST_A_NZ ((const unsigned char*)0)
#endif
#ifdef LEARNEST_C_PATTERN
static const unsigned char learnest_c_nz[LEARNEST_NY * LEARNEST_NX] = LEARNEST_C_PATTERN;
#define LEARNEST_C_NZ learnest_c_nz
#else
#define LEARNEST_C_NZ ((const unsigned char*)0)
#endif

/* The parameters of one sample's problem: the window, then the weights Q, R, P (inverse
 * covariances, symmetric, column-major), exactly the parameter vector of the Ipopt MHE. */
struct learnest_mhe_problem {
  struct learnest_window w;
  learnest_real Q[LEARNEST_NXX], R[LEARNEST_NYY], P[LEARNEST_NXX];
};

/* Tuning as init/reset take it (covariances, row-major, symmetrised) and the weights: P_cov
 * the first prior's covariance, W_cov the running arrival covariance (learnest_mhe_tune sets
 * it to P_cov; the API's init/reset to the build's default). */
struct learnest_mhe_tuning {
  learnest_real P_cov[LEARNEST_NXX], Q_cov[LEARNEST_NXX], R_cov[LEARNEST_NYY];
  learnest_real P[LEARNEST_NXX], Q[LEARNEST_NXX], R[LEARNEST_NYY];
  learnest_real W_cov[LEARNEST_NXX], W[LEARNEST_NXX];
};

/* The arrival weight P of a problem is the running weight W (the inverse of the running
 * arrival covariance P_cov: the build's default, or set_arrival's) unless a first prior's
 * covariance is being carried: after init/reset with a P0 larger than P_cov, and after a
 * recovery restart (the restart prior's covariance). While the window fills, P is the first
 * prior's weight; once it is full and slides, the carried covariance C goes forward by the EKF
 * recursion (learnest_mhe_carry) until it is no larger than P_cov, and P = inv(C) meanwhile. */
struct learnest_mhe {
  struct learnest_mhe_problem now;   /* the last solved problem */
  struct learnest_mhe_problem next;  /* the problem being solved */
  learnest_real X[LEARNEST_NW];      /* the solution of now, oldest stage first */
  learnest_real Xn[LEARNEST_NW];     /* the warm start of next, then its solution */
  learnest_real P_cov[LEARNEST_NXX], W[LEARNEST_NXX];  /* the running arrival covariance, weight */
  learnest_real Q_cov[LEARNEST_NXX], R_cov[LEARNEST_NYY];  /* row-major (symmetric) */
  learnest_real C[LEARNEST_NXX], Cn[LEARNEST_NXX];  /* carried covariance of now's, next's prior */
  int carried, carried_next;         /* whether C, Cn are in force */
  int restart;                       /* the next step empties the window */
};

/* One covariance A (n x n, row-major) checked and inverted: finite (else
 * LEARNEST_NONFINITE_INPUT), its variances in the precision's range (else
 * LEARNEST_BAD_ARGUMENT), symmetric and positive definite (else
 * LEARNEST_NOT_POSITIVE_DEFINITE); cov = A symmetrised, weight = its inverse (symmetrised). */
LEARNEST_KIT int learnest_mhe_covariance(const learnest_real* A, int n, learnest_real* cov,
                                         learnest_real* weight) {
  learnest_real work[LEARNEST_NMAX * LEARNEST_NMAX];
  if (!learnest_all_finite(A, n * n)) return LEARNEST_NONFINITE_INPUT;
  if (!learnest_variances_ok(A, n, 1)) return LEARNEST_BAD_ARGUMENT;
  if (!learnest_covariance_ok(A, n, work)) return LEARNEST_NOT_POSITIVE_DEFINITE;
  memcpy(cov, A, (size_t)(n * n) * sizeof(learnest_real));
  learnest_symmetrise(cov, n);
  if (!learnest_spd_inverse(cov, n, weight, work)) return LEARNEST_NOT_POSITIVE_DEFINITE;
  learnest_symmetrise(weight, n);
  return LEARNEST_OK;
}

/* t from the covariances P0 (arrival), Q (process), R (measurement); any may be NULL (its
 * part of t is left alone). Nothing is written to t unless every given one is valid. */
LEARNEST_KIT int learnest_mhe_tune(struct learnest_mhe_tuning* t, const learnest_real* P0,
                                   const learnest_real* Q, const learnest_real* R) {
  struct learnest_mhe_tuning c;
  int code = LEARNEST_OK;
  if (P0) code = learnest_mhe_covariance(P0, LEARNEST_NX, c.P_cov, c.P);
  if (code == LEARNEST_OK && Q) code = learnest_mhe_covariance(Q, LEARNEST_NX, c.Q_cov, c.Q);
  if (code == LEARNEST_OK && R) code = learnest_mhe_covariance(R, LEARNEST_NY, c.R_cov, c.R);
  if (code != LEARNEST_OK) return code;
  if (P0) {
    memcpy(t->P_cov, c.P_cov, sizeof c.P_cov);
    memcpy(t->P, c.P, sizeof c.P);
    memcpy(t->W_cov, c.P_cov, sizeof c.P_cov);
    memcpy(t->W, c.P, sizeof c.P);
  }
  if (Q) {
    memcpy(t->Q_cov, c.Q_cov, sizeof c.Q_cov);
    memcpy(t->Q, c.Q, sizeof c.Q);
  }
  if (R) {
    memcpy(t->R_cov, c.R_cov, sizeof c.R_cov);
    memcpy(t->R, c.R, sizeof c.R);
  }
  return LEARNEST_OK;
}

/* The largest variance of a covariance that becomes an arrival weight, relative to the running
 * arrival covariance's (estimators/arrival.py ARRIVAL_CEILING). */
#define LEARNEST_ARRIVAL_CEILING 100

/* factor times the running arrival covariance's variances (NX). */
LEARNEST_KIT void learnest_mhe_ceiling(const struct learnest_mhe* m, learnest_real factor,
                                       learnest_real* ceiling) {
  int i;
  for (i = 0; i < LEARNEST_NX; ++i) ceiling[i] = factor * m->P_cov[i * LEARNEST_NX + i];
}

/* 1 when the covariance A (NX x NX, symmetric) is no larger than the running arrival
 * covariance P_cov: (1 + eps) P_cov - A is positive definite (estimators/arrival.py settled:
 * the largest eigenvalue of W A is at most 1 + eps; eps 1e-9, float 1e-4 for rounding). */
LEARNEST_KIT int learnest_mhe_settled(const struct learnest_mhe* m, const learnest_real* A) {
  const learnest_real eps = LEARNEST_IS_FLOAT ? (learnest_real)1e-4 : (learnest_real)1e-9;
  learnest_real D[LEARNEST_NXX];
  int i;
  for (i = 0; i < LEARNEST_NXX; ++i) D[i] = (1 + eps) * m->P_cov[i] - A[i];
  return learnest_cholesky(D, LEARNEST_NX);
}

/* The arrival weight in force once the carried covariance of a problem is cov (carried) or
 * none: P = inv(cov), or W when cov is not carried or has no finite inverse (then it stops
 * being carried). */
LEARNEST_KIT void learnest_mhe_weigh_arrival(const struct learnest_mhe* m, const learnest_real* cov,
                                             int* carried, learnest_real* P) {
  learnest_real L[LEARNEST_NXX];
  if (*carried && learnest_spd_inverse(cov, LEARNEST_NX, P, L)) {
    learnest_symmetrise(P, LEARNEST_NX);
    return;
  }
  *carried = 0;
  memcpy(P, m->W, sizeof m->W);
}

/* Start over from the prior x0 with tuning t: the first prior's weight t->P, carried forward
 * when its covariance is larger than the running one. */
LEARNEST_KIT void learnest_mhe_reset(struct learnest_mhe* m, const learnest_real* x0,
                                     const struct learnest_mhe_tuning* t) {
  memset(m, 0, sizeof *m);
  learnest_window_reset(&m->now.w, x0);
  memcpy(m->now.Q, t->Q, sizeof m->now.Q);  /* symmetric: row- and column-major alike */
  memcpy(m->now.R, t->R, sizeof m->now.R);
  memcpy(m->now.P, t->P, sizeof m->now.P);
  memcpy(m->P_cov, t->W_cov, sizeof m->P_cov);
  memcpy(m->W, t->W, sizeof m->W);
  memcpy(m->Q_cov, t->Q_cov, sizeof m->Q_cov);
  memcpy(m->R_cov, t->R_cov, sizeof m->R_cov);
  m->carried = LEARNEST_ARRIVAL_UPDATE || !learnest_mhe_settled(m, t->P_cov);
  if (m->carried) memcpy(m->C, t->P_cov, sizeof m->C);
  learnest_window_fill(m->X, x0);
}

/* Run-time tuning from t's given parts (Q, R: every stage from the next step on; P: the
 * running arrival covariance, in force now unless a first prior's is being carried). */
LEARNEST_KIT void learnest_mhe_set_tuning(struct learnest_mhe* m, const struct learnest_mhe_tuning* t,
                                          int P, int Q, int R) {
  if (Q) {
    memcpy(m->now.Q, t->Q, sizeof m->now.Q);
    memcpy(m->Q_cov, t->Q_cov, sizeof m->Q_cov);
  }
  if (R) {
    memcpy(m->now.R, t->R, sizeof m->now.R);
    memcpy(m->R_cov, t->R_cov, sizeof m->R_cov);
  }
  if (P) {
    memcpy(m->P_cov, t->P_cov, sizeof m->P_cov);
    memcpy(m->W, t->P, sizeof m->W);
    if (!m->carried) memcpy(m->now.P, m->W, sizeof m->W);
  }
}

/* The carried covariance of the window's second stage from that of its first (the one
 * leaving, solved state X[0]): cov <- A (cov - K H cov) A^T + Q_cov, K the Kalman gain of the
 * outputs that stage kept (G[0]), H = dh/dx(X[0], U[0]) (NY x NX) and A = dF/dx(X[0], U[1])
 * (NX x NX), both column-major; cov row-major (symmetric). */
LEARNEST_KIT void learnest_mhe_carry(const struct learnest_mhe* m, const learnest_real* H,
                                     const learnest_real* A, learnest_real* cov) {
  learnest_real AP[LEARNEST_NXX];
  int i, j, l, keep[LEARNEST_NY];
  for (j = 0; j < LEARNEST_NY; ++j) keep[j] = m->now.w.G[j] == 1;
  (void)learnest_masked_update(cov, H, LEARNEST_C_NZ, m->R_cov, keep, 0, 0);  /* S not PD: the prediction */
  LEARNEST_UNROLL_BLOCK for (i = 0; i < LEARNEST_NX; ++i) {  /* AP = A cov */
    for (l = 0; l < LEARNEST_NX; ++l) {
      learnest_real v = 0;
      LEARNEST_UNROLL_BLOCK for (j = 0; j < LEARNEST_NX; ++j) {
        if (LEARNEST_NZ(LEARNEST_A_NZ, i + j * LEARNEST_NX)) v += A[i + j * LEARNEST_NX] * cov[j * LEARNEST_NX + l];
      }
      AP[i * LEARNEST_NX + l] = v;
    }
  }
  for (i = 0; i < LEARNEST_NX; ++i) {  /* cov = AP A^T + Q_cov */
    LEARNEST_UNROLL_BLOCK for (l = 0; l < LEARNEST_NX; ++l) {
      learnest_real v = m->Q_cov[i * LEARNEST_NX + l];
      LEARNEST_UNROLL_BLOCK for (j = 0; j < LEARNEST_NX; ++j) {
        if (LEARNEST_NZ(LEARNEST_A_NZ, l + j * LEARNEST_NX)) v += AP[i * LEARNEST_NX + j] * A[l + j * LEARNEST_NX];
      }
      cov[i * LEARNEST_NX + l] = v;
    }
  }
  learnest_symmetrise(cov, LEARNEST_NX);
}

/* 1 when the next step's window slides while a first prior's covariance is carried: the
 * caller then gives learnest_mhe_advance H = dh/dx(X[0], U[0]) and A = dF/dx(X[0], U[1]) of
 * the current window. */
LEARNEST_KIT int learnest_mhe_carries(const struct learnest_mhe* m, int has_previous) {
  return has_previous && m->now.w.mask[0] == 1 && m->carried;
}

/* next and its warm start Xn from now and X: the window moves on one stage when a sample was
 * taken before (has_previous) and opens the new sample's stage with input u. When the window
 * was full the arrival moves on: its weight becomes W, or, while a covariance is carried
 * (learnest_mhe_carries: H and A given, else NULL), the inverse of the carried one (its
 * variances capped at the arrival ceiling) until it has settled. The caller then predicts the
 * last stage of the warm start, Xn[N] = F(X[N], u) (when has_previous). */
LEARNEST_KIT void learnest_mhe_advance(struct learnest_mhe* m, int has_previous,
                                       const learnest_real* u, const learnest_real* H,
                                       const learnest_real* A) {
  memcpy(&m->next, &m->now, sizeof m->next);
  memcpy(m->Xn, m->X, sizeof m->Xn);
  memcpy(m->Cn, m->C, sizeof m->Cn);
  m->carried_next = m->carried;
  if (has_previous) {
    if (m->now.w.mask[0] == 1) {  /* the arrival moves on */
      if (m->carried_next && H && A) {
        learnest_real ceiling[LEARNEST_NX], work[LEARNEST_NX];
        learnest_mhe_carry(m, H, A, m->Cn);
        learnest_mhe_ceiling(m, LEARNEST_ARRIVAL_CEILING, ceiling);
        (void)learnest_cap_variances(m->Cn, LEARNEST_NX, ceiling, work);
        if (!LEARNEST_ARRIVAL_UPDATE && learnest_mhe_settled(m, m->Cn)) m->carried_next = 0;
      } else {
        m->carried_next = 0;
      }
      learnest_mhe_weigh_arrival(m, m->Cn, &m->carried_next, m->next.P);
    }
    learnest_window_shift(&m->next.w, m->X);
    learnest_shift(m->Xn, LEARNEST_NX, LEARNEST_N + 1);
  }
  learnest_window_open(&m->next.w, u);
}

/* The recovery's new prior (estimators/mhe.py restart_prior): the Kalman update of x_pred
 * with the diagonal covariance diag(pd) by the outputs kept (keep[j]), C = dh/dx (NY x NX,
 * column-major), R_cov (row-major) and innovation nu: xbar and its covariance
 * cov = Pd - K C Pd (row-major). xbar = x_pred and cov = diag(pd) when no output is kept or S
 * is not positive definite. */
LEARNEST_KIT void learnest_restart_prior(const learnest_real* x_pred, const learnest_real* C,
                                         const learnest_real* pd, const learnest_real* R_cov,
                                         const learnest_real* nu, const int* keep,
                                         learnest_real* xbar, learnest_real* cov) {
  int i;
  for (i = 0; i < LEARNEST_NX; ++i) xbar[i] = x_pred[i];
  for (i = 0; i < LEARNEST_NXX; ++i) cov[i] = 0;
  for (i = 0; i < LEARNEST_NX; ++i) cov[i * LEARNEST_NX + i] = pd[i];
  (void)learnest_masked_update(cov, C, LEARNEST_C_NZ, R_cov, keep, nu, xbar);  /* S not PD: the prediction */
  learnest_symmetrise(cov, LEARNEST_NX);
}

/* The innovation gate of the new sample (u, y, valid) and the recovery's restart and re-seed,
 * after learnest_mhe_advance and the prediction of Xn[N]: h and C = dh/dx (column-major) at
 * x_pred = Xn[N]; a valid output's d2 = (y - h)^2 / S_jj with
 * S_jj = rho (C P_arr C^T)_jj + R_cov_jj, P_arr the carried covariance of next's prior if
 * any, else the running P_cov. A restart (after a failed step, on the step that ends a
 * recovery episode, learnest_gate_ends_episode, or on a re-seed, learnest_gate_reseeds, which
 * takes every valid output) empties the window around learnest_restart_prior from the variances
 * min(rho P_arr_ii, cap P_cov_ii) (a re-seed: cap P_cov_ii), folds the sample into it and
 * carries the prior's covariance, capped at the arrival ceiling (its inverse is the arrival
 * weight). Weighs the sample's
 * outputs (G); sets rejected (NY) and *restarted; returns 1 when an output was rejected. */
LEARNEST_KIT int learnest_mhe_gate(struct learnest_mhe* m, const struct learnest_gate* g,
                                   int has_previous, const learnest_real* u,
                                   const learnest_real* y, const unsigned char* valid,
                                   const learnest_real* h, const learnest_real* C, int* rejected,
                                   int* restarted) {
  learnest_real d2[LEARNEST_NY], nu[LEARNEST_NY], xbar[LEARNEST_NX], cov[LEARNEST_NXX];
  learnest_real pd[LEARNEST_NX], ceiling[LEARNEST_NX];
  const learnest_real* P_arr = m->carried_next ? m->Cn : m->P_cov;
  int i, j, k, any, reseed, keep[LEARNEST_NY];
  LEARNEST_UNROLL_BLOCK for (i = 0; i < LEARNEST_NY; ++i) {
    learnest_real s = 0;
    LEARNEST_UNROLL_BLOCK for (j = 0; j < LEARNEST_NX; ++j) {
      LEARNEST_UNROLL_BLOCK for (k = 0; k < LEARNEST_NX; ++k) {
        if (LEARNEST_NZ(LEARNEST_C_NZ, i + j * LEARNEST_NY) && LEARNEST_NZ(LEARNEST_C_NZ, i + k * LEARNEST_NY)) {
          s += C[i + j * LEARNEST_NY] * P_arr[j * LEARNEST_NX + k] * C[i + k * LEARNEST_NY];
        }
      }
    }
    s = g->rho * s + m->R_cov[i * LEARNEST_NY + i];
    nu[i] = valid[i] ? y[i] - h[i] : 0;
    d2[i] = nu[i] * nu[i] / s;
  }
  any = learnest_gate_test(g, d2, valid, LEARNEST_NY, rejected);
  reseed = any && has_previous && learnest_gate_reseeds(g, rejected);
  for (j = 0; j < LEARNEST_NY; ++j) keep[j] = valid[j] && !rejected[j];
  *restarted = has_previous && (m->restart || reseed || learnest_gate_ends_episode(g, rejected, valid));
  if (*restarted) {
    learnest_mhe_ceiling(m, (learnest_real)LEARNEST_MAX_INFLATION, pd);
    for (i = 0; i < LEARNEST_NX && !reseed; ++i) {
      learnest_real v = g->rho * P_arr[i * LEARNEST_NX + i];
      pd[i] = v < pd[i] ? v : pd[i];
    }
    learnest_restart_prior(m->Xn + LEARNEST_N * LEARNEST_NX, C, pd, m->R_cov, nu, keep, xbar, cov);
    learnest_mhe_ceiling(m, LEARNEST_ARRIVAL_CEILING, ceiling);
    (void)learnest_cap_variances(cov, LEARNEST_NX, ceiling, pd);
    learnest_window_reset(&m->next.w, xbar);
    learnest_window_open(&m->next.w, u);
    learnest_window_fill(m->Xn, xbar);
    learnest_box_clamp(m->Xn, LEARNEST_N + 1);
    memcpy(m->Cn, cov, sizeof m->Cn);
    m->carried_next = 1;
    learnest_mhe_weigh_arrival(m, m->Cn, &m->carried_next, m->next.P);
    for (j = 0; j < LEARNEST_NY; ++j) keep[j] = 0;  /* the sample is in the prior */
  }
  learnest_window_weigh(&m->next.w, y, keep);
  return any && !reseed;
}

/* The solved next problem becomes the current one. */
LEARNEST_KIT void learnest_mhe_commit(struct learnest_mhe* m) {
  memcpy(&m->now, &m->next, sizeof m->now);
  memcpy(m->X, m->Xn, sizeof m->X);
  memcpy(m->C, m->Cn, sizeof m->C);
  m->carried = m->carried_next;
  m->restart = 0;
}

#endif /* LEARNEST_MHE_H */
