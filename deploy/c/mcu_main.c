/* The example main of deploy/c/cortex_m4.sh: steps the reference sequence of ref.h (a const
 * array, compiled in) through the generated compensator and prints one command a line, then
 * the two counters. On the Cortex-M4 the lines go out through semihosting (newlib's rdimon);
 * the same file compiled for the host prints the same lines, which the script compares.
 *
 *   cc -std=c99 -O2 -I GEN mcu_main.c GEN/torchhys_comp.c -lm
 *
 * -DCOMP=NAME -DCOMP_HEADER='"NAME.h"' for files exported with --prefix NAME. -DCOMP_ADAPT
 * for files exported with adapt="rls" or "nlms": each sample calls NAME_step_adapt with the
 * pair of the last sample (the command it gave and a measured response 1.02 times the last
 * reference plus 0.01: the same on both machines) and the last line adds the adaptive
 * counters. On the Cortex-M4 (__ARM_ARCH) SysTick times each step: the line "ticks" gives
 * their sum; under QEMU with -icount shift=0 (one instruction a virtual ns, SysTick at the
 * mps2 boards' 25 MHz) a tick is 40 instructions. */
#include <stdio.h>

#ifndef COMP
#define COMP torchhys_comp
#endif
#ifndef COMP_HEADER
#define COMP_HEADER "torchhys_comp.h"
#endif
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define NAME(x) CAT(COMP, x)

#include COMP_HEADER
#include "ref.h" /* REF_N, static const NAME(_real) ref[REF_N] */

#ifdef __ARM_ARCH
#include <stdint.h>
#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
static void ticks_start(void)
{
    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0u;
    SYST_CSR = 5u; /* enabled, the processor clock, no interrupt */
}
static uint32_t ticks_now(void)
{
    return SYST_CVR; /* counts down, 24 bits */
}
#define TICKS(a, b) (((a) - (b)) & 0xFFFFFFu)
#endif

int main(void)
{
    static NAME(_state) s; /* the caller's state: static here, a member or a local elsewhere */
    long i;
#ifdef __ARM_ARCH
    unsigned long ticks = 0;
    uint32_t t0;
    ticks_start();
#endif
#ifdef COMP_ADAPT
    NAME(_real) u_prev = (NAME(_real))0, y_prev = (NAME(_real))0;
#endif
    NAME(_init)(&s);
    printf("state_bytes %ld\n", (long)sizeof s);
    for (i = 0; i < REF_N; ++i) {
        NAME(_real) u;
#ifdef __ARM_ARCH
        t0 = ticks_now();
#endif
#ifdef COMP_ADAPT
        u = NAME(_step_adapt)(&s, ref[i], i ? y_prev : (NAME(_real))NAN, u_prev);
        u_prev = u;
        y_prev = (NAME(_real))(1.02 * (double)ref[i] + 0.01);
#else
        u = NAME(_step)(&s, ref[i]);
#endif
#ifdef __ARM_ARCH
        ticks += TICKS(t0, ticks_now());
#endif
        printf("%ld %.9g\n", i, (double)u);
    }
#ifdef __ARM_ARCH
    fprintf(stderr, "ticks %lu steps %ld\n", ticks, (long)REF_N);
#endif
#ifdef COMP_ADAPT
    printf("nonfinite %ld out_of_range %ld updates %ld skipped %ld refused %ld\n",
           (long)NAME(_nonfinite_count)(&s), (long)NAME(_out_of_range_count)(&s),
           (long)NAME(_updates_count)(&s), (long)NAME(_skipped_count)(&s),
           (long)NAME(_refused_count)(&s));
#else
    printf("nonfinite %ld out_of_range %ld\n", (long)NAME(_nonfinite_count)(&s),
           (long)NAME(_out_of_range_count)(&s));
#endif
    return 0;
}
