/* platform.h: what the estimator loop needs from the machine it runs on.
 *
 * Two implementations: platform_mps2.c (bare-metal Cortex-M under QEMU: SysTick paces the
 * loop, semihosting carries the output and the exit code) and platform_host.c (a hosted C
 * program: no pacing, stdout, exit()). */
#ifndef PLATFORM_H
#define PLATFORM_H

#include <stddef.h>
#include <stdint.h>

/* Start the sample clock: one tick every period_s seconds. */
void platform_start(double period_s);

/* Sleep until the next sample tick. Returns the number of ticks missed since the previous
 * call (0 when the previous step finished within its period). */
uint32_t platform_wait_for_sample(void);

/* Clock ticks since the current sample's tick, and the clock's rate [ticks/s]. */
uint32_t platform_busy_ticks(void);
uint32_t platform_tick_hz(void);

/* Peak stack use so far [bytes] (0 when the platform cannot tell). */
size_t platform_stack_peak(void);

void platform_write(const char* text, size_t length);

/* Stop the program; code 0 means success. */
void platform_exit(int code) __attribute__((noreturn));

#endif /* PLATFORM_H */
