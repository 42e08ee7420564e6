/* Start-up for the Cortex-M4 example under QEMU (mps2-an386) and on a bare board: a 16-entry
 * vector table, the FPU enabled, .data copied from flash, .bss zeroed, then newlib's _start
 * (rdimon-crt0: semihosting set-up, constructors, main, exit). Symbols from cortex_m4.ld. */
#include <stdint.h>

extern uint32_t __data_load__[], __data_start__[], __data_end__[];
extern uint32_t __bss_start__[], __bss_end__[];
extern uint32_t __stack[];
extern void _start(void);

void Reset_Handler(void);
void Default_Handler(void);

/* A fault stops the program through semihosting (SYS_EXIT, ADP_Stopped_RunTimeErrorUnknown):
 * QEMU then exits with a non-zero status instead of spinning. */
void Default_Handler(void)
{
    static const char message[] = "fault: default handler\n";
    register uint32_t r0 __asm__("r0") = 0x04; /* SYS_WRITE0 */
    register const void *r1 __asm__("r1") = message;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    r0 = 0x18; /* SYS_EXIT */
    r1 = (const void *)0x20023;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    for (;;) {
    }
}

__attribute__((section(".vectors"), used)) static void (*const vectors[16])(void) = {
    (void (*)(void))__stack, /* initial stack pointer */
    Reset_Handler,
    Default_Handler, /* NMI */
    Default_Handler, /* HardFault */
    Default_Handler, /* MemManage */
    Default_Handler, /* BusFault */
    Default_Handler, /* UsageFault */
    0, 0, 0, 0,
    Default_Handler, /* SVCall */
    Default_Handler, /* DebugMonitor */
    0,
    Default_Handler, /* PendSV */
    Default_Handler, /* SysTick */
};

void Reset_Handler(void)
{
    volatile uint32_t *cpacr = (volatile uint32_t *)0xE000ED88;
    uint32_t *src = __data_load__, *dst = __data_start__;
    *cpacr |= 0xFu << 20; /* CP10, CP11: full access to the FPU */
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    while (dst < __data_end__)
        *dst++ = *src++;
    for (dst = __bss_start__; dst < __bss_end__;)
        *dst++ = 0;
    _start();
    for (;;) {
    }
}
