/* autoconf.h (replay stub): the configuration the app is built with (app-config over the
 * cf2 defaults): the Kalman estimator enabled, the out-of-tree estimator on. */
#ifndef REPLAY_AUTOCONF_H
#define REPLAY_AUTOCONF_H
#define CONFIG_ESTIMATOR_KALMAN_ENABLE 1
#define CONFIG_ESTIMATOR_OOT 1
#endif
