/* A fixed-rate feedforward controller over a generated C compensator (torchhys export
 * --format c): the C counterpart of deploy/cpp/controller.cpp, with no library but libc/libm.
 *
 *   controller REF.csv OUT.csv [--rate HZ] [--spin] [--cpu N]
 *
 * REF.csv: one desired output a line, in its first column (a line that does not start with a
 * number, e.g. a header, is skipped; "nan" and "inf" are samples, held and counted by the
 * step); "-" reads standard input. OUT.csv: "y_ref,u" a sample ("-": standard output; the
 * report then goes to standard error). The commands are written after the loop, so no I/O
 * runs inside it.
 *
 * --rate HZ  paces the loop: sample k starts at t0 + k / HZ on CLOCK_MONOTONIC (default 0:
 *            unpaced, as fast as it goes). The wait is clock_nanosleep(TIMER_ABSTIME), or
 * --spin     a busy wait on clock_gettime (no sleep: the core and its caches stay hot).
 * --cpu N    pins the thread to CPU N (default: the CPU it starts on; -1: no pinning).
 *            Linux only (sched_setaffinity); elsewhere the option is accepted and ignored.
 *            On Linux the timer slack is set to 1 ns (prctl), so that a sleep ends at its
 *            deadline rather than up to 50 us after it.
 *
 * Prints the step latency (clock_gettime(CLOCK_MONOTONIC) around each step: median, p99,
 * max, in microseconds), the loop's jitter when paced (each step's start minus its scheduled
 * time: median, p99, max) and the compensator's two counters.
 *
 * Build (deploy/c/build.sh GEN_DIR [OUT_DIR] [PREFIX]):
 *   cc -std=c99 -O2 -D_GNU_SOURCE -I GEN_DIR controller.c GEN_DIR/torchhys_comp.c -lm
 * -DCOMP=NAME -DCOMP_HEADER='"NAME.h"' for files exported with --prefix NAME. The generated
 * files stay pure C99; _GNU_SOURCE is for this file's POSIX and Linux calls.
 *
 * Adaptive mode (-DCOMP_ADAPT, e.g. CFLAGS=-DCOMP_ADAPT build.sh ..., over files exported
 * with adapt="rls" or "nlms"): REF.csv's second column is the response measured at each
 * sample (after its command was applied; missing or "nan": none), and each sample calls
 * NAME_step_adapt with the last sample's measured response and applied command. Every
 * --log-every N samples (default 1000; 0: never) the readout's weights (NAME_weights) are
 * copied out after the step, outside its timing, and printed after the loop ("weights K
 * w0 w1 ..."), with the adaptive counters. */
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#ifdef __linux__
#include <sched.h>
#include <sys/prctl.h>
#endif

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

static int64_t now_ns(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static void sleep_until_ns(int64_t t)
{
    struct timespec ts;
    ts.tv_sec = (time_t)(t / 1000000000);
    ts.tv_nsec = (long)(t % 1000000000);
    while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, NULL) == EINTR) {
    }
}

static int compare_ns(const void *a, const void *b)
{
    int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return (x > y) - (x < y);
}

/* The q-quantile of n sorted values (the sample at floor(q n), as controller.cpp). */
static double quantile_us(const int64_t *sorted, size_t n, double q)
{
    size_t i = (size_t)(q * (double)n);
    if (n == 0)
        return 0.0;
    return (double)sorted[i < n ? i : n - 1] / 1000.0;
}

/* Reads the first column of every line that starts with a number, and the second (a number
 * after a comma or blanks; NAN where there is none) into *second when it is not NULL. */
static double *read_reference(FILE *in, size_t *n, double **second)
{
    char line[4096];
    size_t cap = 1024, k = 0;
    double *ref = malloc(cap * sizeof *ref);
    double *col = second ? malloc(cap * sizeof *col) : NULL;
    while (ref && (col || !second) && fgets(line, sizeof line, in)) {
        char *end, *next;
        double v = strtod(line, &end), y;
        if (end == line)
            continue; /* a header or an empty line */
        while (*end == ' ' || *end == '\t')
            ++end;
        if (*end == ',')
            ++end;
        y = strtod(end, &next);
        if (next == end)
            y = NAN;
        if (k == cap) {
            double *more = realloc(ref, 2 * cap * sizeof *ref);
            if (!more)
                break;
            ref = more;
            if (second) {
                more = realloc(col, 2 * cap * sizeof *col);
                if (!more)
                    break;
                col = more;
            }
            cap *= 2;
        }
        if (second)
            col[k] = y;
        ref[k++] = v;
    }
    if (!ref || (second && !col) || !feof(in)) {
        free(ref);
        free(col);
        return NULL;
    }
    *n = k;
    if (second)
        *second = col;
    return ref;
}

static int pin(long cpu)
{
#ifdef __linux__
    cpu_set_t set;
    if (cpu < 0)
        return -1;
    CPU_ZERO(&set);
    CPU_SET((int)cpu, &set);
    if (sched_setaffinity(0, sizeof set, &set) != 0) {
        fprintf(stderr, "controller: cannot pin to cpu %ld: %s (running unpinned)\n", cpu,
                strerror(errno));
        return -1;
    }
    return (int)cpu;
#else
    (void)cpu;
    return -1;
#endif
}

static int usage(const char *argv0)
{
#ifdef COMP_ADAPT
    fprintf(stderr, "usage: %s REF.csv OUT.csv [--rate HZ] [--spin] [--cpu N] "
            "[--log-every N]\n", argv0);
#else
    fprintf(stderr, "usage: %s REF.csv OUT.csv [--rate HZ] [--spin] [--cpu N]\n", argv0);
#endif
    return 2;
}

int main(int argc, char **argv)
{
    double rate = 0.0, *ref, *cmd;
    int spin = 0, pinned, i;
    long cpu = -2; /* -2: the CPU this starts on */
    size_t n = 0, k;
    int64_t *latency, *late, period = 0, start, next, t0, t1;
    FILE *in, *out, *report = stdout;
    NAME(_state) state, scratch;
#ifdef COMP_ADAPT
    double *measured = NULL;
    NAME(_real) *logged = NULL;
    long log_every = 1000;
    size_t n_logged = 0, slots = 0;
#endif

    if (argc < 3)
        return usage(argv[0]);
    for (i = 3; i < argc; ++i) {
        char *end;
        if (strcmp(argv[i], "--spin") == 0) {
            spin = 1;
        } else if (strcmp(argv[i], "--rate") == 0 && i + 1 < argc) {
            rate = strtod(argv[++i], &end);
            if (*end || !(rate >= 0.0) || rate > 1e9) {
                fprintf(stderr, "controller: --rate: not a rate in Hz: %s\n", argv[i]);
                return 2;
            }
        } else if (strcmp(argv[i], "--cpu") == 0 && i + 1 < argc) {
            cpu = strtol(argv[++i], &end, 10);
            if (*end || cpu < -1) {
                fprintf(stderr, "controller: --cpu: not a CPU number: %s\n", argv[i]);
                return 2;
            }
#ifdef COMP_ADAPT
        } else if (strcmp(argv[i], "--log-every") == 0 && i + 1 < argc) {
            log_every = strtol(argv[++i], &end, 10);
            if (*end || log_every < 0) {
                fprintf(stderr, "controller: --log-every: not a count: %s\n", argv[i]);
                return 2;
            }
#endif
        } else {
            fprintf(stderr, "controller: unknown option %s\n", argv[i]);
            return usage(argv[0]);
        }
    }
    in = strcmp(argv[1], "-") == 0 ? stdin : fopen(argv[1], "r");
    if (!in) {
        fprintf(stderr, "controller: REF.csv: cannot open %s: %s\n", argv[1], strerror(errno));
        return 1;
    }
#ifdef COMP_ADAPT
    ref = read_reference(in, &n, &measured);
    slots = log_every > 0 ? n / (size_t)log_every + 1 : 0;
    logged = malloc((slots ? slots : 1) * NAME(_N_WEIGHTS) * sizeof *logged);
    if (!logged) {
        fprintf(stderr, "controller: out of memory\n");
        return 1;
    }
#else
    ref = read_reference(in, &n, NULL);
#endif
    if (in != stdin)
        fclose(in);
    cmd = malloc((n ? n : 1) * sizeof *cmd);
    latency = malloc((n ? n : 1) * sizeof *latency);
    late = malloc((n ? n : 1) * sizeof *late);
    if (!ref || !cmd || !latency || !late) {
        fprintf(stderr, "controller: out of memory\n");
        return 1;
    }
#ifdef __linux__
    if (cpu == -2)
        cpu = sched_getcpu();
    prctl(PR_SET_TIMERSLACK, 1UL, 0UL, 0UL, 0UL); /* wake at the deadline, not 50 us after */
#endif
    pinned = pin(cpu);

    /* one step on a scratch state: the code and the weights are loaded before the loop */
    NAME(_init)(&scratch);
#ifdef COMP_ADAPT
    (void)NAME(_step_adapt)(&scratch, (NAME(_real))(n ? ref[0] : 0.0), (NAME(_real))NAN,
                            (NAME(_real))NAN);
#else
    (void)NAME(_step)(&scratch, (NAME(_real))(n ? ref[0] : 0.0));
#endif
    NAME(_init)(&state);

    if (rate > 0)
        period = (int64_t)(1e9 / rate + 0.5);
    start = now_ns() + period; /* the first sample one period from now */
    next = start;
    for (k = 0; k < n; ++k) {
        if (period > 0) {
            if (spin)
                while (now_ns() < next) {
                }
            else
                sleep_until_ns(next);
        }
        t0 = now_ns();
#ifdef COMP_ADAPT
        cmd[k] = (double)NAME(_step_adapt)(&state, (NAME(_real))ref[k],
                                           (NAME(_real))(k ? measured[k - 1] : NAN),
                                           (NAME(_real))(k ? cmd[k - 1] : NAN));
        t1 = now_ns();
        if (log_every > 0 && k % (size_t)log_every == 0 && n_logged < slots)
            NAME(_weights)(&state, logged + NAME(_N_WEIGHTS) * n_logged++);
#else
        cmd[k] = (double)NAME(_step)(&state, (NAME(_real))ref[k]);
        t1 = now_ns();
#endif
        latency[k] = t1 - t0;
        late[k] = period > 0 ? t0 - next : 0;
        next += period;
    }

    out = strcmp(argv[2], "-") == 0 ? stdout : fopen(argv[2], "w");
    if (!out) {
        fprintf(stderr, "controller: OUT.csv: cannot write %s: %s\n", argv[2], strerror(errno));
        return 1;
    }
    if (out == stdout)
        report = stderr;
    fprintf(out, "y_ref,u\n");
    for (k = 0; k < n; ++k)
        fprintf(out, "%.17g,%.17g\n", ref[k], cmd[k]);
    if (out != stdout && fclose(out) != 0) {
        fprintf(stderr, "controller: OUT.csv: cannot write %s\n", argv[2]);
        return 1;
    }

    qsort(latency, n, sizeof *latency, compare_ns);
    fprintf(report, "samples %lu rate_hz %g wait %s cpu %d real %s\n", (unsigned long)n, rate,
            period > 0 ? (spin ? "spin" : "sleep") : "none", pinned,
            sizeof(NAME(_real)) == sizeof(float) ? "float32" : "float64");
    fprintf(report, "latency median_us %.3f p99_us %.3f max_us %.3f\n",
            quantile_us(latency, n, 0.5), quantile_us(latency, n, 0.99),
            n ? (double)latency[n - 1] / 1000.0 : 0.0);
    if (period > 0) {
        qsort(late, n, sizeof *late, compare_ns);
        fprintf(report, "jitter median_us %.3f p99_us %.3f max_us %.3f\n",
                quantile_us(late, n, 0.5), quantile_us(late, n, 0.99),
                n ? (double)late[n - 1] / 1000.0 : 0.0);
    }
    fprintf(report, "nonfinite %ld out_of_range %ld\n", (long)NAME(_nonfinite_count)(&state),
            (long)NAME(_out_of_range_count)(&state));
#ifdef COMP_ADAPT
    fprintf(report, "updates %ld skipped %ld refused %ld\n",
            (long)NAME(_updates_count)(&state), (long)NAME(_skipped_count)(&state),
            (long)NAME(_refused_count)(&state));
    for (k = 0; k < n_logged; ++k) {
        int j;
        fprintf(report, "weights %lu", (unsigned long)(k * (size_t)log_every));
        for (j = 0; j < NAME(_N_WEIGHTS); ++j)
            fprintf(report, " %.17g", (double)logged[k * NAME(_N_WEIGHTS) + j]);
        fprintf(report, "\n");
    }
    free(measured);
    free(logged);
#endif
    free(ref);
    free(cmd);
    free(latency);
    free(late);
    return 0;
}
