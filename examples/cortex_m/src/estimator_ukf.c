/* estimator_ukf.c: estimator.h over a generated UKF (<prefix>_api.h: workspace_size, init on
 * caller memory, step, get_state). estimator_config.h names the prefix and holds x0, P0, Q, R. */
#include "estimator_common.h"

int estimator_init(void) {
    est_real x0[EST_NX], P0[EST_NX * EST_NX], Q[EST_NX * EST_NX], R[EST_NY * EST_NY];
    if (EST_API(_workspace_size)() > sizeof est_workspace) return LEARNEST_NO_MEMORY;
    est_round(x0, est_x0, EST_NX);
    est_round(P0, est_P0, EST_NX * EST_NX);
    est_round(Q, est_Q, EST_NX * EST_NX);
    est_round(R, est_R, EST_NY * EST_NY);
    return EST_API(_init)(est_workspace, sizeof est_workspace, x0, P0, Q, R, &est_h);
}
