/* estimator_common.h: what both adapters share: the API's names from EST_PREFIX, the
 * static workspace, and the double <-> real conversions. Included by one adapter only. */
#ifndef ESTIMATOR_COMMON_H
#define ESTIMATOR_COMMON_H

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

int estimator_step(const double* u, const double* y) {
    est_real ur[EST_NU], yr[EST_NY];
    est_round(ur, u, EST_NU);
    est_round(yr, y, EST_NY);
    return EST_API(_step)(est_h, ur, yr);
}

void estimator_get_state(double* x) {
    est_real xr[EST_NX];
    int i;

    /* Only fails without a handle (init failed): report zeros then. */
    int ok = EST_API(_get_state)(est_h, xr) == LEARNEST_OK;
    for (i = 0; i < EST_NX; ++i) x[i] = ok ? (double)xr[i] : 0.0;
}

#endif /* ESTIMATOR_COMMON_H */
