/* estimator_ukf.c: estimator.h over a generated UKF's C API (<prefix>_init/_step/_get_state,
 * one filter in static memory). estimator_config.h names the prefix and holds x0, P0, Q, R. */
#include "estimator.h"

#define EST_CONCAT_(a, b) a##b
#define EST_CONCAT(a, b) EST_CONCAT_(a, b)
#define EST_API(name) EST_CONCAT(EST_PREFIX, name)

int estimator_init(void) { return EST_API(_init)(est_x0, est_P0, est_Q, est_R); }

int estimator_step(const double* u, const double* y) { return EST_API(_step)(u, y); }

void estimator_get_state(double* x) { EST_API(_get_state)(x); }
