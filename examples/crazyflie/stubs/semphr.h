/* semphr.h (replay stub): binary semaphores and mutexes that check they are used as the
 * replay's single thread can: a take must find the semaphore given. */
#ifndef REPLAY_SEMPHR_H
#define REPLAY_SEMPHR_H
#include "FreeRTOS.h"

typedef struct {
  int given;
} StaticSemaphore_t;
typedef StaticSemaphore_t* SemaphoreHandle_t;

static inline SemaphoreHandle_t xSemaphoreCreateBinaryStatic(StaticSemaphore_t* buffer) {
  buffer->given = 0;
  return buffer;
}
static inline SemaphoreHandle_t xSemaphoreCreateMutexStatic(StaticSemaphore_t* buffer) {
  buffer->given = 1;
  return buffer;
}
static inline BaseType_t xSemaphoreTake(SemaphoreHandle_t s, TickType_t wait) {
  (void)wait;
  if (!s->given) replay_fail("a semaphore taken before it was given would block");
  s->given = 0;
  return pdTRUE;
}
static inline BaseType_t xSemaphoreGive(SemaphoreHandle_t s) {
  s->given = 1;
  return pdTRUE;
}
#endif
