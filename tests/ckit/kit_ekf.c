/* kit_ekf.c -- the C kit's extended Kalman filter (learnest_ekf.h, docs/c_kit.md's worked
 * example) over a linear model, where it is the Kalman filter: prefix tekf. */
#include "kit_linear.h"

#define LEARNEST_PREFIX tekf

#include "learnest_ekf.h"

KIT_LINEAR_SET_MODEL
