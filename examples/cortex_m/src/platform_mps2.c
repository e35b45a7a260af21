/* platform_mps2.c: platform.h on a bare-metal Cortex-M under QEMU (mps2-an386, mps2-an500).
 *
 * SysTick, clocked by the 25 MHz system clock, interrupts once per sample period; the loop
 * sleeps (WFI) in between. Output and exit go through Arm semihosting (BKPT 0xAB), which QEMU
 * serves with -semihosting-config enable=on,target=native. QEMU does not model timing: its
 * clocks follow the host's wall clock, or with -icount shift=0 advance 1 ns per executed
 * instruction, so busy ticks are then an instruction count (40 instructions per tick). */
#include <stdint.h>

#include "platform.h"

#define SYSCLK_HZ 25000000u
#define SYST_CSR (*(volatile uint32_t*)0xe000e010u)
#define SYST_RVR (*(volatile uint32_t*)0xe000e014u)
#define SYST_CVR (*(volatile uint32_t*)0xe000e018u)
#define SYST_CSR_ENABLE_TICKINT_CPUCLK 7u

#define SYS_OPEN 0x01
#define SYS_WRITE 0x05
#define SYS_EXIT 0x18
#define ADP_STOPPED_APPLICATION_EXIT 0x20026 /* QEMU exits with status 0 */
#define ADP_STOPPED_RUN_TIME_ERROR 0x20023   /* QEMU exits with status 1 */

static volatile uint32_t g_ticks_pending;
static uint32_t g_reload;
static int g_stdout = -1;

void SysTick_Handler(void) { ++g_ticks_pending; }

static int semihost(int operation, void* argument) {
    register int r0 __asm__("r0") = operation;
    register void* r1 __asm__("r1") = argument;
    __asm__ volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

void platform_start(double period_s) {
    g_reload = (uint32_t)(period_s * SYSCLK_HZ + 0.5) - 1u; /* SysTick holds 24 bits */
    SYST_RVR = g_reload;
    SYST_CVR = 0;
    g_ticks_pending = 0;
    SYST_CSR = SYST_CSR_ENABLE_TICKINT_CPUCLK;
}

uint32_t platform_wait_for_sample(void) {
    uint32_t ticks;
    for (;;) {
        __asm__ volatile("cpsid i" ::: "memory");
        ticks = g_ticks_pending;
        if (ticks) break;
        /* WFI wakes on a pending interrupt even while PRIMASK masks it; it runs after cpsie. */
        __asm__ volatile("wfi\n\tcpsie i" ::: "memory");
    }
    g_ticks_pending = 0;
    __asm__ volatile("cpsie i" ::: "memory");
    return ticks - 1;
}

uint32_t platform_busy_ticks(void) {
    /* Ticks since the sample's tick, plus whole periods if the step overran. */
    return g_ticks_pending * (g_reload + 1u) + (g_reload - SYST_CVR);
}

uint32_t platform_tick_hz(void) { return SYSCLK_HZ; }

void platform_write(const char* text, size_t length) {
    uint32_t block[3];
    if (g_stdout < 0) {
        uint32_t open[3] = {(uint32_t)(uintptr_t)":tt", 4 /* mode "w" */, 3 /* strlen(":tt") */};
        g_stdout = semihost(SYS_OPEN, open);
    }
    block[0] = (uint32_t)g_stdout;
    block[1] = (uint32_t)(uintptr_t)text;
    block[2] = (uint32_t)length;
    semihost(SYS_WRITE, block);
}

void platform_exit(int code) {
    semihost(SYS_EXIT, (void*)(code == 0 ? ADP_STOPPED_APPLICATION_EXIT : ADP_STOPPED_RUN_TIME_ERROR));
    for (;;) {
    }
}
