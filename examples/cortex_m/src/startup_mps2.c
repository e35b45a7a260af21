/* startup_mps2.c: vector table and reset handler for QEMU's mps2-an386 (Cortex-M4F) and
 * mps2-an500 (Cortex-M7).
 *
 * Reset_Handler enables the FPU, copies .data from flash to RAM, zeroes .bss, paints the unused
 * stack with a pattern (platform_stack_peak() later finds the high-water mark) and calls main.
 * Any fault ends the program through semihosting with a non-zero exit code, so a crashed run
 * never hangs the emulator. */
#include <stdint.h>

#include "platform.h"

extern uint32_t __data_start[], __data_end[], __data_load[], __bss_start[], __bss_end[];
extern uint32_t __stack_bottom[], __stack_top[];
extern int main(void);

void Reset_Handler(void) __attribute__((noreturn));
void Fault_Handler(void) __attribute__((noreturn));
void SysTick_Handler(void); /* platform_mps2.c */

#define STACK_PAINT 0xa5a5a5a5u
#define SCB_CPACR (*(volatile uint32_t*)0xe000ed88u)

/* Initial stack pointer, then the 15 system exceptions; the loop uses no peripheral interrupt.
 * A struct keeps the data pointer and the function pointers apart, as ISO C wants. */
typedef void (*handler_t)(void);
struct vector_table {
    uint32_t* initial_sp;
    handler_t exceptions[15];
};

__attribute__((section(".vectors"), used)) static const struct vector_table vectors = {
    __stack_top,
    {
        Reset_Handler, Fault_Handler /* NMI */, Fault_Handler /* HardFault */,
        Fault_Handler /* MemManage */, Fault_Handler /* BusFault */, Fault_Handler /* UsageFault */,
        0, 0, 0, 0, Fault_Handler /* SVCall */, Fault_Handler /* DebugMonitor */, 0,
        Fault_Handler /* PendSV */, SysTick_Handler,
    },
};

void Reset_Handler(void) {
    uint32_t *src, *dst, *sp;
    /* Full access to CP10/CP11 (the FPU) before any floating-point instruction runs. */
    SCB_CPACR |= 0xfu << 20;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    for (src = __data_load, dst = __data_start; dst < __data_end;) *dst++ = *src++;
    for (dst = __bss_start; dst < __bss_end;) *dst++ = 0;
    /* Paint up to 64 bytes below the current stack pointer; above that this frame lives. */
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    for (dst = __stack_bottom; dst < sp - 16;) *dst++ = STACK_PAINT;
    platform_exit(main());
}

void Fault_Handler(void) {
    static const char message[] = "fault: the program took an exception\n";
    platform_write(message, sizeof message - 1);
    platform_exit(2);
}

size_t platform_stack_peak(void) {
    const uint32_t* p = __stack_bottom;
    while (p < __stack_top && *p == STACK_PAINT) ++p;
    return (size_t)((const char*)__stack_top - (const char*)p);
}
