/* task.h (replay stub). */
#ifndef REPLAY_TASK_H
#define REPLAY_TASK_H
#include "FreeRTOS.h"

static inline void vTaskDelay(TickType_t ticks) { (void)ticks; }
#endif
