/* kit_ipopt.c -- the Ipopt MHE of the C kit (learnest_mhe_ipopt.h) and learnest_casadi.h's
 * solver glue over a hand-written nlpsol: eq. (2) for the linear model of kit_casadi.h, whose
 * cost is the quadratic 1/2 X'H X + b'X + c, given to Ipopt through its C interface
 * (IpStdCInterface.h; the casadi wheel's libipopt) with the options of estimators/
 * mhe_problem.py's IPOPT_OPTIONS (and BOUNDED_IPOPT_OPTIONS with bounds), and behind CasADi's nlpsol calling convention: inputs x0, p,
 * lbx, ubx, ...; output x; status 0 solved, 1 failed, 2 maximum iterations; memory checked
 * out and released. Prefix tip, horizon 6, double only (Ipopt's precision). */
#include <IpStdCInterface.h>

#include "kit_casadi.h"

#define LEARNEST_PREFIX tip
#define LEARNEST_N 6
/* The nlpsol's parameter vector, ParamLayout(2, 1, 2, 6) (tests/test_ckit.py checks it):
 * xbar, U, Y, mask, G, Q, R, P. */
#define LEARNEST_NP 56
#define LEARNEST_OFF_XBAR 0
#define LEARNEST_OFF_U 2
#define LEARNEST_OFF_Y 9
#define LEARNEST_OFF_MASK 23
#define LEARNEST_OFF_G 30
#define LEARNEST_OFF_Q 44
#define LEARNEST_OFF_R 48
#define LEARNEST_OFF_P 52

#define KC_NW ((LEARNEST_N + 1) * KC_NX)

/* The NLP's data for one solve: the cost 1/2 X'H X + b'X + c. */
struct kc_qp {
  double H[KC_NW * KC_NW], b[KC_NW], c;
};

static int kc_max_iter = 100, kc_refuse_memory = 0, kc_checked_out = 0, kc_solves = 0;

/* Adds f * |J X + r|^2_W (J rows x NW, column-major; W rows x rows) to the quadratic. */
static void kc_add_term(struct kc_qp* q, int rows, const double* J, const double* r,
                        const double* W, double f) {
  double WJ[KC_NX * KC_NW], Wr[KC_NX];
  int i, j, k;
  if (f == 0) return;
  for (i = 0; i < rows; ++i) {
    Wr[i] = 0;
    for (k = 0; k < rows; ++k) Wr[i] += W[i + k * rows] * r[k];
    for (j = 0; j < KC_NW; ++j) {
      WJ[i + j * rows] = 0;
      for (k = 0; k < rows; ++k) WJ[i + j * rows] += W[i + k * rows] * J[k + j * rows];
    }
  }
  for (j = 0; j < KC_NW; ++j) {
    for (i = 0; i < KC_NW; ++i) {
      double v = 0;
      for (k = 0; k < rows; ++k) v += J[k + i * rows] * WJ[k + j * rows];
      q->H[i + j * KC_NW] += 2 * f * v;
    }
    for (k = 0; k < rows; ++k) q->b[j] += 2 * f * J[k + j * rows] * Wr[k];
  }
  for (k = 0; k < rows; ++k) q->c += f * r[k] * Wr[k];
}

/* Eq. (2) (estimators/mhe_problem.py): per node i the measurement term m_i |G_i (Y_i - C x_i)|^2_R
 * and the arrival term (1 - m_{i-1}) |x_i - xbar|^2_P (m_{-1} = 0), per stage i < N the process
 * term m_i |x_{i+1} - A x_i - B U_{i+1}|^2_Q, all scaled by 1 / (the weights' largest diagonal
 * entry). */
static void kc_build(struct kc_qp* q, const double* p) {
  const double *xbar = p + LEARNEST_OFF_XBAR, *U = p + LEARNEST_OFF_U, *Y = p + LEARNEST_OFF_Y;
  const double *mask = p + LEARNEST_OFF_MASK, *G = p + LEARNEST_OFF_G, *Q = p + LEARNEST_OFF_Q;
  const double *R = p + LEARNEST_OFF_R, *P = p + LEARNEST_OFF_P;
  double J[KC_NX * KC_NW], r[KC_NX], big = 0, s;
  int i, k, c;
  for (k = 0; k < KC_NX; ++k) big = Q[k + k * KC_NX] > big ? Q[k + k * KC_NX] : big;
  for (k = 0; k < KC_NY; ++k) big = R[k + k * KC_NY] > big ? R[k + k * KC_NY] : big;
  for (k = 0; k < KC_NX; ++k) big = P[k + k * KC_NX] > big ? P[k + k * KC_NX] : big;
  s = 1 / big;
  memset(q, 0, sizeof *q);
  for (i = 0; i <= LEARNEST_N; ++i) {
    memset(J, 0, sizeof J);  /* G_i (Y_i - C x_i) */
    for (k = 0; k < KC_NY; ++k) {
      for (c = 0; c < KC_NX; ++c) J[k + (i * KC_NX + c) * KC_NY] = -G[i * KC_NY + k] * kc_C[k + c * KC_NY];
      r[k] = G[i * KC_NY + k] * Y[i * KC_NY + k];
    }
    kc_add_term(q, KC_NY, J, r, R, s * mask[i]);
    memset(J, 0, sizeof J);  /* x_i - xbar */
    for (k = 0; k < KC_NX; ++k) {
      J[k + (i * KC_NX + k) * KC_NX] = 1;
      r[k] = -xbar[k];
    }
    kc_add_term(q, KC_NX, J, r, P, s * (1 - (i ? mask[i - 1] : 0)));
    if (i == LEARNEST_N) break;
    memset(J, 0, sizeof J);  /* x_{i+1} - A x_i - B U_{i+1} */
    for (k = 0; k < KC_NX; ++k) {
      for (c = 0; c < KC_NX; ++c) J[k + (i * KC_NX + c) * KC_NX] = -kc_A[k + c * KC_NX];
      J[k + ((i + 1) * KC_NX + k) * KC_NX] = 1;
      r[k] = 0;
      for (c = 0; c < KC_NU; ++c) r[k] -= kc_B[k + c * KC_NX] * U[(i + 1) * KC_NU + c];
    }
    kc_add_term(q, KC_NX, J, r, Q, s * mask[i]);
  }
}

static bool kc_f(ipindex n, ipnumber* x, bool new_x, ipnumber* f, UserDataPtr data) {
  const struct kc_qp* q = (const struct kc_qp*)data;
  int i, j;
  (void)new_x;
  *f = q->c;
  for (j = 0; j < n; ++j) {
    double Hx = 0;
    for (i = 0; i < n; ++i) Hx += q->H[j + i * KC_NW] * x[i];
    *f += x[j] * (0.5 * Hx + q->b[j]);
  }
  return true;
}

static bool kc_grad(ipindex n, ipnumber* x, bool new_x, ipnumber* g, UserDataPtr data) {
  const struct kc_qp* q = (const struct kc_qp*)data;
  int i, j;
  (void)new_x;
  for (j = 0; j < n; ++j) {
    g[j] = q->b[j];
    for (i = 0; i < n; ++i) g[j] += q->H[j + i * KC_NW] * x[i];
  }
  return true;
}

static bool kc_g(ipindex n, ipnumber* x, bool new_x, ipindex m, ipnumber* g, UserDataPtr data) {
  (void)n, (void)x, (void)new_x, (void)m, (void)g, (void)data;
  return true;
}

static bool kc_jac(ipindex n, ipnumber* x, bool new_x, ipindex m, ipindex nele, ipindex* row,
                   ipindex* col, ipnumber* values, UserDataPtr data) {
  (void)n, (void)x, (void)new_x, (void)m, (void)nele, (void)row, (void)col, (void)values, (void)data;
  return true;
}

/* The lower triangle of obj_factor H, row by row. */
static bool kc_hess(ipindex n, ipnumber* x, bool new_x, ipnumber obj_factor, ipindex m,
                    ipnumber* lambda, bool new_lambda, ipindex nele, ipindex* row, ipindex* col,
                    ipnumber* values, UserDataPtr data) {
  const struct kc_qp* q = (const struct kc_qp*)data;
  ipindex i, j, k = 0;
  (void)x, (void)new_x, (void)m, (void)lambda, (void)new_lambda, (void)nele;
  for (i = 0; i < n; ++i) {
    for (j = 0; j <= i; ++j, ++k) {
      if (values) {
        values[k] = obj_factor * q->H[i + j * KC_NW];
      } else {
        row[k] = i;
        col[k] = j;
      }
    }
  }
  return true;
}

/* CasADi's nlpsol memory: one slot (the kit checks it out for each solve and gives it back). */
static int kc_solver_checkout(void) {
  if (kc_refuse_memory || kc_checked_out) return -1;
  kc_checked_out = 1;
  return 0;
}

static void kc_solver_release(int mem) {
  if (mem == 0) kc_checked_out = 0;
}

/* nlpsol(x0, p, lbx, ubx, lbg, ubg, lam_x0, lam_g0) -> x (res[0]); NULL bounds: none. */
static int kc_solver(const casadi_real** arg, casadi_real** res, casadi_int* iw, casadi_real* w,
                     int mem) {
  static struct kc_qp q;
  double lo[KC_NW], hi[KC_NW];
  enum ApplicationReturnStatus status;
  IpoptProblem nlp;
  int i;
  (void)iw, (void)w;
  if (mem != 0 || !kc_checked_out) return 1;
  kc_build(&q, arg[1]);
  for (i = 0; i < KC_NW; ++i) {
    lo[i] = arg[2] ? arg[2][i] : -1e19;  /* Ipopt's infinity */
    hi[i] = arg[3] ? arg[3][i] : 1e19;
  }
  nlp = CreateIpoptProblem(KC_NW, lo, hi, 0, NULL, NULL, 0, KC_NW * (KC_NW + 1) / 2, 0, kc_f, kc_g,
                           kc_grad, kc_jac, kc_hess);
  if (!nlp) return 1;
  AddIpoptNumOption(nlp, (char*)"tol", 1e-12);
  AddIpoptIntOption(nlp, (char*)"max_iter", kc_max_iter);
  AddIpoptStrOption(nlp, (char*)"hessian_approximation", (char*)"exact");
  AddIpoptIntOption(nlp, (char*)"print_level", 0);
  AddIpoptStrOption(nlp, (char*)"sb", (char*)"yes");
  if (arg[2] || arg[3]) {  /* BOUNDED_IPOPT_OPTIONS: the solution inside the box */
    AddIpoptNumOption(nlp, (char*)"bound_relax_factor", 0.0);
    AddIpoptStrOption(nlp, (char*)"honor_original_bounds", (char*)"yes");
    AddIpoptStrOption(nlp, (char*)"mu_strategy", (char*)"adaptive");
    AddIpoptNumOption(nlp, (char*)"mu_target", 0.0);
    AddIpoptNumOption(nlp, (char*)"mu_min", 1e-20);
    AddIpoptNumOption(nlp, (char*)"tol", 1e-14);
  }
  memcpy(res[0], arg[0], KC_NW * sizeof(double));
  status = IpoptSolve(nlp, res[0], NULL, NULL, NULL, NULL, NULL, &q);
  FreeIpoptProblem(nlp);
  ++kc_solves;
  if (status == Solve_Succeeded || status == Solved_To_Acceptable_Level) return 0;
  return status == Maximum_Iterations_Exceeded ? 2 : 1;
}

#define LEARNEST_MODEL_SOLVER kc_solver
#define LEARNEST_MODEL_SOLVER_CHECKOUT kc_solver_checkout
#define LEARNEST_MODEL_SOLVER_RELEASE kc_solver_release
#define LEARNEST_MODEL_F kc_F
#define LEARNEST_MODEL_NODE kc_node
#define LEARNEST_MODEL_STAGE kc_stage
#include "learnest_casadi.h"

#include "learnest_mhe_ipopt.h"

/* The parameter layout above, for the test to compare with ParamLayout. */
KIT_EXTERN void kt_layout(int* out) {
  out[0] = LEARNEST_NP, out[1] = LEARNEST_OFF_XBAR, out[2] = LEARNEST_OFF_U, out[3] = LEARNEST_OFF_Y;
  out[4] = LEARNEST_OFF_MASK, out[5] = LEARNEST_OFF_G, out[6] = LEARNEST_OFF_Q, out[7] = LEARNEST_OFF_R;
  out[8] = LEARNEST_OFF_P;
}

/* Ipopt's iteration limit; whether the solver's memory is refused; solves so far; whether the
 * memory is still checked out. */
KIT_EXTERN void kt_solver_set(int max_iter, int refuse_memory) {
  kc_max_iter = max_iter;
  kc_refuse_memory = refuse_memory;
}

KIT_EXTERN int kt_solves(void) { return kc_solves; }

KIT_EXTERN int kt_checked_out(void) { return kc_checked_out; }
