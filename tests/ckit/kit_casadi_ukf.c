/* kit_casadi_ukf.c -- the UKF of the C kit with its own sigma points (learnest_ukf.h with
 * LEARNEST_UKF_ALPHA, as codegen/ukf.py builds it) over the model in CasADi's calling convention
 * (kit_casadi.h): learnest_casadi.h's F and h hooks. Prefix tcu. */
#include "kit_casadi.h"

#define LEARNEST_MODEL_F kc_F
#define LEARNEST_MODEL_H kc_h
#include "learnest_casadi.h"

#define LEARNEST_PREFIX tcu
#define LEARNEST_UKF_ALPHA 0.5
#define LEARNEST_UKF_BETA 2.0
#define LEARNEST_UKF_KAPPA 1.0

#include "learnest_ukf.h"
