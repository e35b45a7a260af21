/* pm.h (replay stub): the battery voltage of the sample (the firmware's header pulls in the
 * power management's driver headers). */
#ifndef REPLAY_PM_H
#define REPLAY_PM_H
float pmGetBatteryVoltage(void);
#endif
