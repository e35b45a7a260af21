/* estimator_mhe.c: estimator.h over a generated embedded MHE (<prefix>.h: workspace_size, init
 * on caller memory, step, get_state), in the mode it was generated with (mhe_rti: one
 * Gauss-Newton iteration per sample; mhe_gn: iterated to convergence). estimator_config.h names
 * the prefix and holds x0 and the weights Q, R, P (inverse covariances). */
#include "estimator_common.h"

int estimator_init(void) {
    est_real x0[EST_NX], Q[EST_NX * EST_NX], R[EST_NY * EST_NY], P[EST_NX * EST_NX];
    if (EST_API(_workspace_size)() > sizeof est_workspace) return LEARNEST_NO_MEMORY;
    est_round(x0, est_x0, EST_NX);
    est_round(Q, est_Q, EST_NX * EST_NX);
    est_round(R, est_R, EST_NY * EST_NY);
    est_round(P, est_P, EST_NX * EST_NX);
    return EST_API(_init)(est_workspace, sizeof est_workspace, x0, Q, R, P, &est_h);
}
