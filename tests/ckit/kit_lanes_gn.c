/* kit_lanes_gn.c -- the embedded MHE of the C kit over the nonlinear model of kit_lanes.h:
 * where the build has vectors, the window's stages linearised a batch at a time through
 * learnest_casadi.h's batch hook (learnest_gn.h); with -DLEARNEST_NO_SIMD one scalar call a
 * stage. Prefix tlg, horizon 6 (one batch and a part: spare lanes in both precisions). */
#include "kit_lanes.h"

#define LEARNEST_PREFIX tlg
#define LEARNEST_N 6
#define LEARNEST_DEFAULT_MODE 0
#define LEARNEST_DEFAULT_MAX_ITER 30
#define LEARNEST_DEFAULT_TOL 1e-10

#include "learnest_mhe_gn.h"
