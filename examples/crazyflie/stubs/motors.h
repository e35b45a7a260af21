/* motors.h (replay stub): the one driver call the app makes (the firmware's header pulls in
 * the STM32 headers). The replay returns the logged PWM ratio of the sample. */
#ifndef REPLAY_MOTORS_H
#define REPLAY_MOTORS_H
#include <stdint.h>
uint16_t motorsGetRatio(uint32_t id);
#endif
