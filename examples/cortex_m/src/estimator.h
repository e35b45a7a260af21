/* estimator.h: the estimator as the loop sees it.
 *
 * estimator_ukf.c implements this with a generated UKF; an estimator with another C API needs
 * only another implementation of these three functions. */
#ifndef ESTIMATOR_H
#define ESTIMATOR_H

#include "estimator_config.h" /* generated: EST_NX, EST_NU, EST_NY, the API and its tuning */

/* Set the estimator to its initial state; 0 on success, else the API's error code. */
int estimator_init(void);

/* One sample: input u (EST_NU) held since the previous sample, measurement y (EST_NY);
 * 0 on success, else the API's error code. */
int estimator_step(const double* u, const double* y);

/* The current state estimate x (EST_NX). */
void estimator_get_state(double* x);

#endif /* ESTIMATOR_H */
