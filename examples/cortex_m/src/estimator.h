/* estimator.h: the estimator as the loop sees it.
 *
 * estimator.c implements this over any generated estimator (ukf, ekf, mhe_rti, mhe_gn): they share
 * one C API. The loop speaks double; the adapter rounds to the API's real type (float in a
 * float32 build) on the way in and widens (exactly) on the way out. */
#ifndef ESTIMATOR_H
#define ESTIMATOR_H

#include "estimator_config.h" /* generated: the header, EST_PREFIX, EST_NX/NU/NY, EST_WORKSPACE_BYTES */

/* Place the estimator in its static workspace and start it; learnest_status.h's code. */
int estimator_init(void);

/* One sample: input u (EST_NU) held since the previous sample, measurement y (EST_NY);
 * learnest_status.h's code (negative: an error, the estimator unchanged). */
int estimator_step(const double* u, const double* y);

/* The current state estimate x (EST_NX). */
void estimator_get_state(double* x);

#endif /* ESTIMATOR_H */
