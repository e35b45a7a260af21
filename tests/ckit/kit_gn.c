/* kit_gn.c -- the embedded MHE of the C kit (learnest_mhe_gn.h) over a linear model, built on
 * its own: prefix tgn, horizon 6 (tests/test_ckit.py compares it with the Python MHE). */
#include "kit_linear.h"

#define LEARNEST_PREFIX tgn
#define LEARNEST_N 6
#define LEARNEST_DEFAULT_MODE 0
#define LEARNEST_DEFAULT_MAX_ITER 30
#define LEARNEST_DEFAULT_TOL 1e-10

#include "learnest_mhe_gn.h"

KIT_LINEAR_SET_MODEL
