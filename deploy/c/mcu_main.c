/* The example main of deploy/c/cortex_m4.sh: steps the reference sequence of ref.h (a const
 * array, compiled in) through the generated compensator and prints one command a line, then
 * the two counters. On the Cortex-M4 the lines go out through semihosting (newlib's rdimon);
 * the same file compiled for the host prints the same lines, which the script compares.
 *
 *   cc -std=c99 -O2 -I GEN mcu_main.c GEN/torchhys_comp.c -lm
 *
 * -DCOMP=NAME -DCOMP_HEADER='"NAME.h"' for files exported with --prefix NAME. */
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

int main(void)
{
    static NAME(_state) s; /* the caller's state: static here, a member or a local elsewhere */
    long i;
    NAME(_init)(&s);
    printf("state_bytes %ld\n", (long)sizeof s);
    for (i = 0; i < REF_N; ++i) {
        NAME(_real) u = NAME(_step)(&s, ref[i]);
        printf("%ld %.9g\n", i, (double)u);
    }
    printf("nonfinite %ld out_of_range %ld\n", (long)NAME(_nonfinite_count)(&s),
           (long)NAME(_out_of_range_count)(&s));
    return 0;
}
