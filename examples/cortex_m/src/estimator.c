/* estimator.c: estimator.h over any generated estimator (UKF, EKF, embedded MHE): they share one
 * C API (docs/c_api.md), so only the prefix differs; estimator_config.h names it. The
 * estimator starts from the tuned defaults of its generated header (<prefix>_init_default)
 * in a static workspace of <PREFIX>_WORKSPACE_BYTES bytes: no heap, no hand-copied numbers. */
#include "estimator.h"

#define EST_CONCAT_(a, b) a##b
#define EST_CONCAT(a, b) EST_CONCAT_(a, b)
#define EST_API(name) EST_CONCAT(EST_PREFIX, name)

typedef EST_API(_real) est_real;
typedef EST_API(_t) est_handle;

/* The estimator's memory: a static buffer (init aligns inside), no heap. */
static unsigned char est_workspace[EST_WORKSPACE_BYTES];
static est_handle* est_h;

/* to[i] = (est_real)from[i]: round-to-nearest into float in a float32 build. */
static void est_round(est_real* to, const double* from, int n) {
    int i;
    for (i = 0; i < n; ++i) to[i] = (est_real)from[i];
}

int estimator_init(void) {
    return EST_API(_init_default)(est_workspace, sizeof est_workspace, &est_h);
}

int estimator_step(const double* u, const double* y) {
    est_real ur[EST_NU], yr[EST_NY];
    est_round(ur, u, EST_NU);
    est_round(yr, y, EST_NY);
    return EST_API(_step)(est_h, ur, yr, 0); /* every output present in this run */
}

void estimator_get_state(double* x) {
    est_real xr[EST_NX];
    int i;

    /* Only fails without a handle (init failed): report zeros then. */
    int ok = EST_API(_get_state)(est_h, xr) == LEARNEST_OK;
    for (i = 0; i < EST_NX; ++i) x[i] = ok ? (double)xr[i] : 0.0;
}
