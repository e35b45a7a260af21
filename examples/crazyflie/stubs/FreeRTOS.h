/* FreeRTOS.h (replay stub): the types and macros estimator_out_of_tree.c uses, for a build
 * without the kernel. The replay is one thread: it calls the stabilizer's side and then the
 * task's round, in the order the scheduler would (the stabilizer task has the higher priority). */
#ifndef REPLAY_FREERTOS_H
#define REPLAY_FREERTOS_H
#include <stdint.h>

typedef long BaseType_t;
typedef uint32_t TickType_t;
#define pdTRUE 1
#define pdFALSE 0
#define portMAX_DELAY ((TickType_t)0xffffffffu)
#define M2T(X) ((TickType_t)(X))
#define T2M(X) ((uint32_t)(X))

/* A call the firmware would block in: the replay's order of calls is wrong. */
void replay_fail(const char* why) __attribute__((noreturn));
#endif
