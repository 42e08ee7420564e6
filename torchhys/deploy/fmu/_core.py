"""The C shared by the FMI 2 and FMI 3 wrappers (:mod:`torchhys.deploy.fmu`): the FMU's own
state (the compensator's ``PREFIX_state``, the inputs, the command and the sample count),
the samples of a communication step, the variables' values by value reference and the
serialized state's layout. Written here, from the FMI specifications' description of the
co-simulation calls; no third-party file is copied."""

from __future__ import annotations

import math

from torchhys.deploy.fmu._variables import Variables

CORE = r"""
/* ---- the FMU's state: @P@_fmu_core (torchhys.deploy.fmu._core) ---------------------- */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <stdarg.h>
#include "@P@.h"

#if defined(__GNUC__)
#define THYS_EXPORT __attribute__((visibility("default")))
#else
#define THYS_EXPORT
#endif

#define THYS_N_INPUTS @N_INPUTS@      /* desired, then the conditions (and measured_prev,
                                         applied_prev for the adaptive step) */
#define THYS_N_CONDITIONS @N_CONDITIONS@
#define THYS_VR_DESIRED 0u
#define THYS_VR_COMMAND 1u
#define THYS_VR_FIRST_INPUT 2u         /* inputs[1] */
#define THYS_VR_FIRST_CONSTANT @VR_FIRST_CONSTANT@u
#define THYS_N_CONSTANTS @N_CONSTANTS@
#define THYS_VR_TIME @VR_TIME@u
#define THYS_SAMPLE_PERIOD @SAMPLE_PERIOD@
#define THYS_TIME_TOLERANCE 1e-6     /* of a sample period */

static const char thys_token[] = "@GUID@";
static const double thys_constants[THYS_N_CONSTANTS] = {@CONSTANTS@};
static const double thys_start_inputs[THYS_N_INPUTS] = {@START_INPUTS@};
static const double thys_initial_command = @INITIAL_COMMAND@;

typedef struct {
    @P@_state s;                    /* the compensator's state (@P@.h) */
    double inputs[THYS_N_INPUTS];   /* the inputs' values, held over a communication step */
    double command;                 /* the last sample's command */
    double start;                   /* the experiment's start time */
    int64_t k;                      /* samples run since the start */
} thys_core;

/* the serialized state: the magic, the instantiation token (its 38 characters and two
   zero bytes), the core's size (uint64, native order) and the core's bytes */
#define THYS_MAGIC "THYSFMU1"
#define THYS_HEADER_BYTES (8 + 40 + 8)
#define THYS_SERIALIZED_BYTES (THYS_HEADER_BYTES + sizeof(thys_core))

enum { THYS_INSTANTIATED, THYS_INITIALIZATION, THYS_STEPPING, THYS_TERMINATED };

static void thys_core_reset(thys_core *c)
{
    memset(c, 0, sizeof *c);
    @P@_init(&c->s);
    memcpy(c->inputs, thys_start_inputs, sizeof c->inputs);
    c->command = thys_initial_command;
}

/* the samples of the communication step [t, t + h]: 0 and *n (>= 1) where t is the
   instance's time and t + h a later sample instant, 1 where t is not the instance's time,
   2 where h is not a positive integer multiple of the sample period */
static int thys_core_samples(const thys_core *c, double t, double h, int64_t *n)
{
    double at = (t - c->start) / THYS_SAMPLE_PERIOD;
    double end = (t + h - c->start) / THYS_SAMPLE_PERIOD;
    double k_end = floor(end + 0.5);
    if (!(fabs(at - (double)c->k) <= THYS_TIME_TOLERANCE))
        return 1;
    if (!(h > 0.0) || !(fabs(end - k_end) <= THYS_TIME_TOLERANCE) || !(k_end > (double)c->k)
        || !(k_end < 9.0e15))
        return 2;
    *n = (int64_t)k_end - c->k;
    return 0;
}

/* n samples of the compensator, the inputs held */
static void thys_core_run(thys_core *c, int64_t n)
{
    int64_t i;
@CONDITIONS_COPY@
    for (i = 0; i < n; ++i)
        c->command = (double)@STEP_CALL@;
    (void)i;
    c->k += n;
}

/* a Real (Float64) variable's value: 0, or -1 for an unknown value reference */
static int thys_core_get_real(const thys_core *c, unsigned vr, double *value)
{
    if (vr == THYS_VR_DESIRED)
        *value = c->inputs[0];
    else if (vr == THYS_VR_COMMAND)
        *value = c->command;
    else if (vr >= THYS_VR_FIRST_INPUT && vr < THYS_VR_FIRST_INPUT + THYS_N_INPUTS - 1)
        *value = c->inputs[1 + (vr - THYS_VR_FIRST_INPUT)];
    else if (vr >= THYS_VR_FIRST_CONSTANT && vr < THYS_VR_FIRST_CONSTANT + THYS_N_CONSTANTS)
        *value = thys_constants[vr - THYS_VR_FIRST_CONSTANT];
    else if (vr == THYS_VR_TIME)
        *value = c->start + (double)c->k * THYS_SAMPLE_PERIOD;
    else
        return -1;
    return 0;
}

/* set an input: 0, -1 for an unknown value reference, -2 for a variable that is not an
   input (the command, a constant) */
static int thys_core_set_real(thys_core *c, unsigned vr, double value)
{
    if (vr == THYS_VR_DESIRED)
        c->inputs[0] = value;
    else if (vr >= THYS_VR_FIRST_INPUT && vr < THYS_VR_FIRST_INPUT + THYS_N_INPUTS - 1)
        c->inputs[1 + (vr - THYS_VR_FIRST_INPUT)] = value;
    else if (vr == THYS_VR_COMMAND || vr == THYS_VR_TIME
             || (vr >= THYS_VR_FIRST_CONSTANT && vr < THYS_VR_FIRST_CONSTANT + THYS_N_CONSTANTS))
        return -2;
    else
        return -1;
    return 0;
}

/* a counter (the held non-finite samples, the clamped samples; the adaptive step's
   updates, skipped pairs and refused updates): 0, or -1 */
static int thys_core_get_count(const thys_core *c, unsigned vr, int64_t *value)
{
    switch (vr) {
@COUNTS@
    default:
        return -1;
    }
    return 0;
}

static void thys_core_header(unsigned char *out)
{
    uint64_t n = (uint64_t)sizeof(thys_core);
    memset(out, 0, THYS_HEADER_BYTES);
    memcpy(out, THYS_MAGIC, 8);
    memcpy(out + 8, thys_token, sizeof thys_token - 1);
    memcpy(out + 48, &n, 8);
}

static void thys_core_serialize(const thys_core *c, unsigned char *out)
{
    thys_core_header(out);
    memcpy(out + THYS_HEADER_BYTES, c, sizeof *c);
}

/* 0, or -1 where the bytes are not a serialized state of this FMU */
static int thys_core_deserialize(thys_core *c, const unsigned char *in, size_t size)
{
    unsigned char header[THYS_HEADER_BYTES];
    thys_core_header(header);
    if (size != THYS_SERIALIZED_BYTES || memcmp(in, header, THYS_HEADER_BYTES) != 0)
        return -1;
    memcpy(c, in + THYS_HEADER_BYTES, sizeof *c);
    return 0;
}

/* a message, formatted into buf (never a '%' left in it: the message is passed on as a
   format string where the logger is FMI 2's) */
static void thys_format(char *buf, size_t size, const char *fmt, va_list args)
{
    char *p;
    vsnprintf(buf, size, fmt, args);
    for (p = buf; *p; ++p)
        if (*p == '%')
            *p = '?';
}
"""


def core_source(prefix: str, variables: Variables, token: str) -> str:
    """The shared C of an FMU of the C step ``prefix`` and the ``variables``; an adaptive
    step gets the measured pair at the first sample of a communication step and NaN (no
    pair, counted as skipped) at the others."""
    n_cond = variables.n_conditions
    real = f"{prefix}_real"
    args = [f"({real})c->inputs[0]"]
    copy = ""
    if n_cond:
        copy = (f"    {real} cond[THYS_N_CONDITIONS];\n"
                "    for (i = 0; i < THYS_N_CONDITIONS; ++i)\n"
                f"        cond[i] = ({real})c->inputs[1 + i];")
        args.append("cond")
    step = f"{prefix}_step"
    if variables.adaptive:
        step += "_adapt"
        args += [f"i == 0 ? ({real})c->inputs[{1 + n_cond + k}] : ({real})NAN" for k in (0, 1)]
    call = f"{step}(&c->s, {', '.join(args)})"
    counts = []
    for v in variables.counters:
        counts += [f"    case {v.vr}u:", f"        *value = {prefix}_{v.name}(&c->s);",
                   "        break;"]
    consts = variables.constants
    values = {
        "N_INPUTS": str(len(variables.inputs)), "N_CONDITIONS": str(n_cond),
        "VR_FIRST_CONSTANT": str(consts[0].vr), "N_CONSTANTS": str(len(consts)),
        "VR_TIME": str(variables.time.vr), "GUID": token,
        "SAMPLE_PERIOD": _literal(variables.sample_period),
        "CONSTANTS": ", ".join(_literal(v.start) for v in consts),
        "START_INPUTS": ", ".join(_literal(v.start) for v in variables.inputs),
        "INITIAL_COMMAND": _literal(variables.command.start),
        "CONDITIONS_COPY": copy, "STEP_CALL": call, "COUNTS": "\n".join(counts), "P": prefix,
    }
    text = CORE
    for key, value in values.items():
        text = text.replace(f"@{key}@", value)
    return text


def _literal(value: float) -> str:
    """A C double literal of ``value`` (NaN: the NAN of <math.h>; the constants are finite)."""
    if math.isnan(value):
        return "NAN"
    text = repr(float(value))
    return text if any(ch in text for ch in ".en") else text + ".0"
