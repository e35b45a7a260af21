/* kit_lanes_ukf.c -- the UKF of the C kit with its own sigma points over the nonlinear model of
 * kit_lanes.h: where the build has vectors, F on the sigma points a batch at a time through
 * learnest_casadi.h's batch hook (learnest_ukf.h's batched propagation); with
 * -DLEARNEST_NO_SIMD one scalar call a point. Prefix tlu. */
#include "kit_lanes.h"

#define LEARNEST_PREFIX tlu
#define LEARNEST_UKF_ALPHA 0.5
#define LEARNEST_UKF_BETA 2.0
#define LEARNEST_UKF_KAPPA 1.0

#include "learnest_ukf.h"
