/* main.c: a firmware-style estimator loop over a recorded run.
 *
 * Every sample period the loop waits for the sample tick, takes that sample's input and
 * measurement (here from the recorded run in run_data.h instead of a driver), steps the
 * estimator and reports the estimate. Each output line is
 *
 *     x <k> <status> <x_0> ... <x_{nx-1}> <busy_ticks>
 *
 * with every x_i as the 16 hex digits of its IEEE-754 binary64 bits (exact, and no printf or
 * heap needed), and busy_ticks the sample clock's ticks spent on the step. One last line,
 *
 *     summary steps=<T> status=<s> overruns=<n> missed_ticks=<m> busy_ticks_max=<t>
 *             busy_ticks_total=<t> tick_hz=<f> stack_peak_bytes=<b>
 *
 * (wrapped here, a single line in the output) closes the run: overruns counts the steps that
 * took longer than the sample period (late steps; a step of 1.3 periods is late though it
 * misses no tick), missed_ticks the sample ticks that passed while a step was still running
 * beyond the next one. The program exits 0 when every
 * step succeeded (status >= 0, learnest_status.h); the loop stops at the first failing step. */
#include <stdint.h>
#include <string.h>

#include "estimator.h"
#include "platform.h"
#include "run_data.h" /* generated: RUN_T, RUN_DT_S, run_u[RUN_T][EST_NU], run_y[RUN_T][EST_NY] */

#if RUN_NU != EST_NU || RUN_NY != EST_NY
#error "run_data.h and the estimator disagree on the number of inputs or outputs"
#endif

static char* put_text(char* p, const char* text) {
    while (*text) *p++ = *text++;
    return p;
}

static char* put_uint(char* p, uint64_t v) {
    char digits[20];
    int n = 0;
    do {
        digits[n++] = (char)('0' + v % 10u);
        v /= 10u;
    } while (v);
    while (n) *p++ = digits[--n];
    return p;
}

static char* put_int(char* p, int v) {
    if (v < 0) *p++ = '-';
    return put_uint(p, v < 0 ? 0u - (uint64_t)v : (uint64_t)v);
}

static char* put_bits(char* p, double v) {
    static const char hex[] = "0123456789abcdef";
    uint64_t bits;
    int shift;
    memcpy(&bits, &v, sizeof bits);
    for (shift = 60; shift >= 0; shift -= 4) *p++ = hex[(bits >> shift) & 0xfu];
    return p;
}

static void write_line(char* start, char* end) {
    *end++ = '\n';
    platform_write(start, (size_t)(end - start));
}

int main(void) {
    char line[32 + 17 * EST_NX + 16];
    double x[EST_NX];
    uint32_t k, busy, busy_max = 0, overruns = 0, missed = 0;
    uint64_t busy_total = 0;
    const double period = RUN_DT_S * (double)platform_tick_hz(); /* ticks per sample */
    int status, i;
    char* p;

    status = estimator_init();
    platform_start(RUN_DT_S);
    for (k = 0; status >= 0 && k < RUN_T; ++k) {
        missed += platform_wait_for_sample();
        /* Sample k: the input held since sample k - 1 (none before sample 0), measurement k. */
        status = estimator_step(run_u[k > 0 ? k - 1 : 0], run_y[k]);
        busy = platform_busy_ticks();
        estimator_get_state(x);
        overruns += (double)busy > period; /* late: the step outlasted its sample period */
        busy_max = busy > busy_max ? busy : busy_max;
        busy_total += busy;
        p = put_text(line, "x ");
        p = put_uint(p, k);
        *p++ = ' ';
        p = put_int(p, status);
        for (i = 0; i < EST_NX; ++i) {
            *p++ = ' ';
            p = put_bits(p, x[i]);
        }
        *p++ = ' ';
        p = put_uint(p, busy);
        write_line(line, p);
    }
    {
        char summary[256];
        p = put_text(summary, "summary steps=");
        p = put_uint(p, k);
        p = put_text(p, " status=");
        p = put_int(p, status);
        p = put_text(p, " overruns=");
        p = put_uint(p, overruns);
        p = put_text(p, " missed_ticks=");
        p = put_uint(p, missed);
        p = put_text(p, " busy_ticks_max=");
        p = put_uint(p, busy_max);
        p = put_text(p, " busy_ticks_total=");
        p = put_uint(p, busy_total);
        p = put_text(p, " tick_hz=");
        p = put_uint(p, platform_tick_hz());
        p = put_text(p, " stack_peak_bytes=");
        p = put_uint(p, platform_stack_peak());
        write_line(summary, p);
    }
    platform_exit(status >= 0 ? 0 : 1);
}
