/* platform_host.c: platform.h in a hosted C program, for comparing with the firmware build.
 *
 * The loop runs unpaced (every sample is "due" at once); busy ticks are nanoseconds of
 * CLOCK_MONOTONIC. */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#include "platform.h"

static struct timespec g_sample_start;

void platform_start(double period_s) { (void)period_s; }

uint32_t platform_wait_for_sample(void) {
    clock_gettime(CLOCK_MONOTONIC, &g_sample_start);
    return 0;
}

uint32_t platform_busy_ticks(void) {
    struct timespec now;
    clock_gettime(CLOCK_MONOTONIC, &now);
    return (uint32_t)((now.tv_sec - g_sample_start.tv_sec) * 1000000000L
                      + (now.tv_nsec - g_sample_start.tv_nsec));
}

uint32_t platform_tick_hz(void) { return 1000000000u; }

size_t platform_stack_peak(void) { return 0; }

void platform_write(const char* text, size_t length) { fwrite(text, 1, length, stdout); }

void platform_exit(int code) {
    fflush(stdout);
    exit(code);
}
