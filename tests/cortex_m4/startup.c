/* Minimal bare-metal start-up for a Cortex-M4 (QEMU's mps2-an386): the vector table, a reset handler
   that sets up C's memory, turns the FPU on and calls main, and the semihosting calls the test
   program reports through (the debugger, here QEMU, carries them out: -semihosting-config enable=on). */
#include <stdint.h>

#include "startup.h"

extern uint32_t __data_start, __data_end, __data_load, __bss_start, __bss_end, __stack_limit, __stack_top;
int main(void);
void Reset_Handler(void);
void Fault_Handler(void);

/* The core loads SP from entry 0 and jumps to entry 1 at reset; the rest are the fault handlers
   (NMI, HardFault, MemManage, BusFault, UsageFault). */
__attribute__((section(".vectors"), used)) static const uintptr_t vectors[] = {
    (uintptr_t)&__stack_top, (uintptr_t)Reset_Handler,  (uintptr_t)Fault_Handler, (uintptr_t)Fault_Handler,
    (uintptr_t)Fault_Handler, (uintptr_t)Fault_Handler, (uintptr_t)Fault_Handler,
};

#define STACK_PAINT 0xC0FFEE11u
#define SYS_WRITE0 0x04
#define SYS_EXIT 0x18
#define ADP_STOPPED_APPLICATION_EXIT 0x20026
#define ADP_STOPPED_RUN_TIME_ERROR 0x20023
#define CPACR (*(volatile uint32_t *)0xE000ED88u)

static int semihost(int op, const void *arg)
{
    register int r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

void semihost_write0(const char *text)
{
    semihost(SYS_WRITE0, text);
}

/* AArch32 SYS_EXIT takes the reason only: QEMU exits with status 0 for ApplicationExit, 1 otherwise. */
void semihost_exit(int ok)
{
    semihost(SYS_EXIT, (const void *)(uintptr_t)(ok ? ADP_STOPPED_APPLICATION_EXIT : ADP_STOPPED_RUN_TIME_ERROR));
    for (;;) {
    }
}

void Fault_Handler(void)
{
    semihost_write0("fault\n");
    semihost_exit(0);
}

/* Fills the free part of the stack with a pattern, so stack_bytes_used can find the deepest use. */
static __attribute__((noinline)) void paint_stack(void)
{
    uint32_t *p = &__stack_limit;
    uint32_t *below_this_frame = (uint32_t *)__builtin_frame_address(0) - 64;
    while (p < below_this_frame) *p++ = STACK_PAINT;
}

uint32_t stack_bytes_used(void)
{
    const uint32_t *p = &__stack_limit;
    while (p < &__stack_top && *p == STACK_PAINT) ++p;
    return (uint32_t)((uintptr_t)&__stack_top - (uintptr_t)p);
}

void Reset_Handler(void)
{
    const uint32_t *src = &__data_load;
    uint32_t *dst;
    /* Full access to the FPU (coprocessors 10 and 11) before any floating-point instruction runs. */
    CPACR |= 0xFu << 20;
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    for (dst = &__data_start; dst < &__data_end;) *dst++ = *src++;
    for (dst = &__bss_start; dst < &__bss_end;) *dst++ = 0;
    paint_stack();
    semihost_exit(main() == 0);
}
