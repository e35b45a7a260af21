/* kit_gn_groups.c -- the embedded MHE of the C kit over a linear model whose states fall apart
 * in two groups (learnest_gn_groups.h: the normal equations solved group by group): two
 * mass-spring-dampers, states [q1, q2, v1, v2], outputs [q1, q2, v2], so the groups interleave
 * (states 0, 2 and 1, 3) and differ in their outputs (one and two); with KIT_UNIFORM_GROUPS,
 * outputs [q1, q2]: groups of one size (LEARNEST_COMP_SIZE, as the generator declares them).
 * Prefix tgg, horizon 6. */
#define LEARNEST_NX 4
#define LEARNEST_DEFAULT_X0 {1.0, -0.5, 0.0, 0.0}
#define LEARNEST_DEFAULT_P0 {0.25, 0, 0, 0, 0, 0.25, 0, 0, 0, 0, 0.25, 0, 0, 0, 0, 0.25}
#define LEARNEST_DEFAULT_Q {1e-6, 0, 0, 0, 0, 1e-6, 0, 0, 0, 0, 1e-4, 0, 0, 0, 0, 1e-4}
#ifdef KIT_UNIFORM_GROUPS
#define LEARNEST_NY 2
#define LEARNEST_DEFAULT_R {0.0025, 0, 0, 0.0025}
#else
#define LEARNEST_NY 3
#define LEARNEST_DEFAULT_R {0.0025, 0, 0, 0, 0.0025, 0, 0, 0, 0.01}
#endif
#include "kit_linear.h"

#define LEARNEST_PREFIX tgg
#define LEARNEST_N 6
#define LEARNEST_DEFAULT_MODE 0
#define LEARNEST_DEFAULT_MAX_ITER 30
#define LEARNEST_DEFAULT_TOL 1e-10
#define LEARNEST_NCOMP 2
#define LEARNEST_COMP_X {0, 2, 1, 3}
#define LEARNEST_COMP_NX {2, 2}
#define LEARNEST_COMP_OF_X {0, 1, 0, 1}
#ifdef KIT_UNIFORM_GROUPS
#define LEARNEST_COMP_Y {0, 1}
#define LEARNEST_COMP_NY {1, 1}
#define LEARNEST_COMP_OF_Y {0, 1}
#define LEARNEST_COMP_SIZE 2
#define LEARNEST_COMP_YSIZE 1
#else
#define LEARNEST_COMP_Y {0, 1, 2}
#define LEARNEST_COMP_NY {1, 2}
#define LEARNEST_COMP_OF_Y {0, 1, 1}
#endif

#include "learnest_mhe_gn.h"

KIT_LINEAR_SET_MODEL

/* Whether the weights in force keep the groups apart, so the last solve went group by group. */
KIT_EXTERN int kt_split(const LEARNEST_HANDLE* h) { return h->gn.split; }
