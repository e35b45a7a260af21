/* kit_casadi_gn.c -- the embedded MHE of the C kit over the model in CasADi's calling
 * convention (kit_casadi.h): learnest_casadi.h's stage, node and F hooks as a generated mhe_gn
 * uses them. Prefix tcg, horizon 6. */
#include "kit_casadi.h"

#define LEARNEST_MODEL_STAGE kc_stage
#define LEARNEST_MODEL_NODE kc_node
#define LEARNEST_MODEL_F kc_F
#include "learnest_casadi.h"

#define LEARNEST_PREFIX tcg
#define LEARNEST_N 6
#define LEARNEST_DEFAULT_MODE 0
#define LEARNEST_DEFAULT_MAX_ITER 30
#define LEARNEST_DEFAULT_TOL 1e-10

#include "learnest_mhe_gn.h"
