"""The FMI 2.0 co-simulation wrapper (:mod:`torchhys.deploy.fmu`): C over the shared core
(:mod:`torchhys.deploy.fmu._core`), its types and functions written from the signatures of
the FMI 2.0 specification (section 2.1 and 4.2); every function of the standard's common
and co-simulation interfaces is defined (those without a meaning here return fmi2Error with
a logged message). With ``FMI2_FUNCTION_PREFIX`` defined (a static link of several FMUs),
the names are prefixed."""

from __future__ import annotations

FMI2 = r"""
/* ---- FMI 2.0 co-simulation (torchhys.deploy.fmu._fmi2) ------------------------------ */
typedef void *fmi2Component;
typedef void *fmi2ComponentEnvironment;
typedef void *fmi2FMUstate;
typedef unsigned int fmi2ValueReference;
typedef double fmi2Real;
typedef int fmi2Integer;
typedef int fmi2Boolean;
typedef char fmi2Char;
typedef const fmi2Char *fmi2String;
typedef char fmi2Byte;
#define fmi2True 1
#define fmi2False 0
typedef enum { fmi2OK, fmi2Warning, fmi2Discard, fmi2Error, fmi2Fatal, fmi2Pending } fmi2Status;
typedef enum { fmi2ModelExchange, fmi2CoSimulation } fmi2Type;
typedef enum { fmi2DoStepStatus, fmi2PendingStatus, fmi2LastSuccessfulTime,
               fmi2Terminated } fmi2StatusKind;
typedef void (*fmi2CallbackLogger)(fmi2ComponentEnvironment, fmi2String, fmi2Status,
                                   fmi2String, fmi2String, ...);
typedef void *(*fmi2CallbackAllocateMemory)(size_t, size_t);
typedef void (*fmi2CallbackFreeMemory)(void *);
typedef void (*fmi2StepFinished)(fmi2ComponentEnvironment, fmi2Status);
typedef struct {
    const fmi2CallbackLogger logger;
    const fmi2CallbackAllocateMemory allocateMemory;
    const fmi2CallbackFreeMemory freeMemory;
    const fmi2StepFinished stepFinished;
    const fmi2ComponentEnvironment componentEnvironment;
} fmi2CallbackFunctions;

#ifdef FMI2_FUNCTION_PREFIX
#define THYS_CAT_(a, b) a##b
#define THYS_CAT(a, b) THYS_CAT_(a, b)
#define FMI2(name) THYS_CAT(FMI2_FUNCTION_PREFIX, name)
#else
#define FMI2(name) name
#endif

typedef struct {
    thys_core core;
    fmi2CallbackLogger logger;
    fmi2CallbackAllocateMemory allocate;
    fmi2CallbackFreeMemory release;
    fmi2ComponentEnvironment env;
    char *name;
    int mode;
    int logging;
} thys_instance;

static void thys_log(const thys_instance *inst, fmi2Status status, const char *fmt, ...)
{
    char buf[512];
    va_list args;
    if (inst == NULL || inst->logger == NULL || (status == fmi2OK && !inst->logging))
        return;
    va_start(args, fmt);
    thys_format(buf, sizeof buf, fmt, args);
    va_end(args);
    inst->logger(inst->env, inst->name, status,
                 status == fmi2Error ? "logStatusError" : "logAll", buf);
}

static void *thys_alloc(const thys_instance *inst, size_t n)
{
    return inst->allocate ? inst->allocate(1, n) : calloc(1, n);
}

static void thys_free(const thys_instance *inst, void *p)
{
    if (inst->release)
        inst->release(p);
    else
        free(p);
}

/* the instance, or NULL (logged) where it is NULL or in none of the modes of mask */
static thys_instance *thys_check(fmi2Component c, int mask, const char *function)
{
    thys_instance *inst = (thys_instance *)c;
    if (inst == NULL)
        return NULL;
    if (!(mask & (1 << inst->mode))) {
        thys_log(inst, fmi2Error, "%s: not allowed in the instance's present state", function);
        return NULL;
    }
    return inst;
}

#define ANY ((1 << THYS_INSTANTIATED) | (1 << THYS_INITIALIZATION) | (1 << THYS_STEPPING) \
             | (1 << THYS_TERMINATED))
#define SETTABLE ((1 << THYS_INSTANTIATED) | (1 << THYS_INITIALIZATION) | (1 << THYS_STEPPING))

THYS_EXPORT const char *FMI2(fmi2GetTypesPlatform)(void) { return "default"; }
THYS_EXPORT const char *FMI2(fmi2GetVersion)(void) { return "2.0"; }

THYS_EXPORT fmi2Status FMI2(fmi2SetDebugLogging)(fmi2Component c, fmi2Boolean loggingOn,
                                                 size_t nCategories,
                                                 const fmi2String categories[])
{
    thys_instance *inst = thys_check(c, ANY, "fmi2SetDebugLogging");
    (void)nCategories;
    (void)categories;
    if (inst == NULL)
        return fmi2Error;
    inst->logging = loggingOn != fmi2False;
    return fmi2OK;
}

THYS_EXPORT fmi2Component FMI2(fmi2Instantiate)(fmi2String instanceName, fmi2Type fmuType,
                                                fmi2String fmuGUID,
                                                fmi2String fmuResourceLocation,
                                                const fmi2CallbackFunctions *functions,
                                                fmi2Boolean visible, fmi2Boolean loggingOn)
{
    thys_instance probe, *inst;
    const char *name = instanceName ? instanceName : "";
    (void)fmuResourceLocation;
    (void)visible;
    memset(&probe, 0, sizeof probe);
    if (functions != NULL) {
        probe.logger = functions->logger;
        probe.allocate = functions->allocateMemory;
        probe.release = functions->freeMemory;
        probe.env = functions->componentEnvironment;
    }
    probe.name = (char *)name;
    if (fmuType != fmi2CoSimulation) {
        thys_log(&probe, fmi2Error, "fmi2Instantiate: the FMU is for co-simulation only");
        return NULL;
    }
    if (fmuGUID == NULL || strcmp(fmuGUID, thys_token) != 0) {
        thys_log(&probe, fmi2Error, "fmi2Instantiate: the GUID %s is not this FMU's %s",
                 fmuGUID ? fmuGUID : "(null)", thys_token);
        return NULL;
    }
    inst = (thys_instance *)thys_alloc(&probe, sizeof *inst);
    if (inst == NULL)
        return NULL;
    *inst = probe;
    inst->name = (char *)thys_alloc(&probe, strlen(name) + 1);
    if (inst->name == NULL) {
        thys_free(&probe, inst);
        return NULL;
    }
    memcpy(inst->name, name, strlen(name) + 1);
    inst->logging = loggingOn != fmi2False;
    inst->mode = THYS_INSTANTIATED;
    thys_core_reset(&inst->core);
    return inst;
}

THYS_EXPORT void FMI2(fmi2FreeInstance)(fmi2Component c)
{
    thys_instance *inst = (thys_instance *)c;
    if (inst == NULL)
        return;
    thys_free(inst, inst->name);
    thys_free(inst, inst);
}

THYS_EXPORT fmi2Status FMI2(fmi2SetupExperiment)(fmi2Component c, fmi2Boolean toleranceDefined,
                                                 fmi2Real tolerance, fmi2Real startTime,
                                                 fmi2Boolean stopTimeDefined,
                                                 fmi2Real stopTime)
{
    thys_instance *inst = thys_check(c, 1 << THYS_INSTANTIATED, "fmi2SetupExperiment");
    (void)toleranceDefined;
    (void)tolerance;
    (void)stopTimeDefined;
    (void)stopTime;
    if (inst == NULL)
        return fmi2Error;
    if (!isfinite(startTime)) {
        thys_log(inst, fmi2Error, "fmi2SetupExperiment: startTime must be finite");
        return fmi2Error;
    }
    inst->core.start = startTime;
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2EnterInitializationMode)(fmi2Component c)
{
    thys_instance *inst = thys_check(c, 1 << THYS_INSTANTIATED, "fmi2EnterInitializationMode");
    if (inst == NULL)
        return fmi2Error;
    inst->mode = THYS_INITIALIZATION;
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2ExitInitializationMode)(fmi2Component c)
{
    thys_instance *inst = thys_check(c, 1 << THYS_INITIALIZATION, "fmi2ExitInitializationMode");
    if (inst == NULL)
        return fmi2Error;
    inst->mode = THYS_STEPPING;
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2Terminate)(fmi2Component c)
{
    thys_instance *inst = thys_check(c, 1 << THYS_STEPPING, "fmi2Terminate");
    if (inst == NULL)
        return fmi2Error;
    inst->mode = THYS_TERMINATED;
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2Reset)(fmi2Component c)
{
    thys_instance *inst = thys_check(c, ANY, "fmi2Reset");
    if (inst == NULL)
        return fmi2Error;
    thys_core_reset(&inst->core);
    inst->mode = THYS_INSTANTIATED;
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2GetReal)(fmi2Component c, const fmi2ValueReference vr[],
                                         size_t nvr, fmi2Real value[])
{
    size_t i;
    thys_instance *inst = thys_check(c, ANY, "fmi2GetReal");
    if (inst == NULL || (nvr > 0 && (vr == NULL || value == NULL)))
        return fmi2Error;
    for (i = 0; i < nvr; ++i)
        if (thys_core_get_real(&inst->core, vr[i], &value[i]) != 0) {
            thys_log(inst, fmi2Error, "fmi2GetReal: no Real variable of value reference %u",
                     vr[i]);
            return fmi2Error;
        }
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2SetReal)(fmi2Component c, const fmi2ValueReference vr[],
                                         size_t nvr, const fmi2Real value[])
{
    size_t i;
    thys_instance *inst = thys_check(c, SETTABLE, "fmi2SetReal");
    if (inst == NULL || (nvr > 0 && (vr == NULL || value == NULL)))
        return fmi2Error;
    for (i = 0; i < nvr; ++i) {
        int done = thys_core_set_real(&inst->core, vr[i], value[i]);
        if (done != 0) {
            thys_log(inst, fmi2Error, done == -2
                     ? "fmi2SetReal: the variable of value reference %u is not an input"
                     : "fmi2SetReal: no Real variable of value reference %u", vr[i]);
            return fmi2Error;
        }
    }
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2GetInteger)(fmi2Component c, const fmi2ValueReference vr[],
                                            size_t nvr, fmi2Integer value[])
{
    size_t i;
    int64_t n;
    thys_instance *inst = thys_check(c, ANY, "fmi2GetInteger");
    if (inst == NULL || (nvr > 0 && (vr == NULL || value == NULL)))
        return fmi2Error;
    for (i = 0; i < nvr; ++i) {
        if (thys_core_get_count(&inst->core, vr[i], &n) != 0) {
            thys_log(inst, fmi2Error, "fmi2GetInteger: no Integer variable of value "
                     "reference %u", vr[i]);
            return fmi2Error;
        }
        value[i] = n > 2147483647 ? 2147483647 : (fmi2Integer)n;  /* saturated */
    }
    return fmi2OK;
}

static fmi2Status thys_none(fmi2Component c, size_t nvr, const char *function)
{
    thys_instance *inst = thys_check(c, ANY, function);
    if (inst == NULL)
        return fmi2Error;
    if (nvr == 0)
        return fmi2OK;
    thys_log(inst, fmi2Error, "%s: the FMU has no variable of this type", function);
    return fmi2Error;
}

THYS_EXPORT fmi2Status FMI2(fmi2SetInteger)(fmi2Component c, const fmi2ValueReference vr[],
                                            size_t nvr, const fmi2Integer value[])
{
    (void)vr;
    (void)value;
    if (nvr > 0 && c != NULL) {
        thys_log((thys_instance *)c, fmi2Error, "fmi2SetInteger: the Integer variables "
                 "(the counters) are outputs");
        return fmi2Error;
    }
    return thys_none(c, nvr, "fmi2SetInteger");
}

THYS_EXPORT fmi2Status FMI2(fmi2GetFMUstate)(fmi2Component c, fmi2FMUstate *FMUstate)
{
    thys_instance *inst = thys_check(c, ANY, "fmi2GetFMUstate");
    if (inst == NULL || FMUstate == NULL)
        return fmi2Error;
    if (*FMUstate == NULL) {
        *FMUstate = thys_alloc(inst, sizeof(thys_core));
        if (*FMUstate == NULL) {
            thys_log(inst, fmi2Error, "fmi2GetFMUstate: out of memory");
            return fmi2Error;
        }
    }
    memcpy(*FMUstate, &inst->core, sizeof(thys_core));
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2SetFMUstate)(fmi2Component c, fmi2FMUstate FMUstate)
{
    thys_instance *inst = thys_check(c, ANY, "fmi2SetFMUstate");
    if (inst == NULL || FMUstate == NULL)
        return fmi2Error;
    memcpy(&inst->core, FMUstate, sizeof(thys_core));
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2FreeFMUstate)(fmi2Component c, fmi2FMUstate *FMUstate)
{
    thys_instance *inst = thys_check(c, ANY, "fmi2FreeFMUstate");
    if (inst == NULL || FMUstate == NULL)
        return fmi2Error;
    if (*FMUstate != NULL)
        thys_free(inst, *FMUstate);
    *FMUstate = NULL;
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2SerializedFMUstateSize)(fmi2Component c, fmi2FMUstate FMUstate,
                                                        size_t *size)
{
    thys_instance *inst = thys_check(c, ANY, "fmi2SerializedFMUstateSize");
    (void)FMUstate;
    if (inst == NULL || size == NULL)
        return fmi2Error;
    *size = THYS_SERIALIZED_BYTES;
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2SerializeFMUstate)(fmi2Component c, fmi2FMUstate FMUstate,
                                                   fmi2Byte serializedState[], size_t size)
{
    thys_instance *inst = thys_check(c, ANY, "fmi2SerializeFMUstate");
    if (inst == NULL || FMUstate == NULL || serializedState == NULL)
        return fmi2Error;
    if (size < THYS_SERIALIZED_BYTES) {
        thys_log(inst, fmi2Error, "fmi2SerializeFMUstate: the buffer holds %lu bytes, the "
                 "state needs %lu", (unsigned long)size, (unsigned long)THYS_SERIALIZED_BYTES);
        return fmi2Error;
    }
    thys_core_serialize((const thys_core *)FMUstate, (unsigned char *)serializedState);
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2DeSerializeFMUstate)(fmi2Component c,
                                                     const fmi2Byte serializedState[],
                                                     size_t size, fmi2FMUstate *FMUstate)
{
    thys_core core;
    thys_instance *inst = thys_check(c, ANY, "fmi2DeSerializeFMUstate");
    if (inst == NULL || serializedState == NULL || FMUstate == NULL)
        return fmi2Error;
    if (thys_core_deserialize(&core, (const unsigned char *)serializedState, size) != 0) {
        thys_log(inst, fmi2Error, "fmi2DeSerializeFMUstate: the %lu bytes are not a state "
                 "serialized by this FMU", (unsigned long)size);
        return fmi2Error;
    }
    if (*FMUstate == NULL)
        *FMUstate = thys_alloc(inst, sizeof(thys_core));
    if (*FMUstate == NULL)
        return fmi2Error;
    memcpy(*FMUstate, &core, sizeof core);
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2DoStep)(fmi2Component c, fmi2Real currentCommunicationPoint,
                                        fmi2Real communicationStepSize,
                                        fmi2Boolean noSetFMUStatePriorToCurrentPoint)
{
    int64_t n = 0;
    int why;
    thys_instance *inst = thys_check(c, 1 << THYS_STEPPING, "fmi2DoStep");
    (void)noSetFMUStatePriorToCurrentPoint;
    if (inst == NULL)
        return fmi2Error;
    why = thys_core_samples(&inst->core, currentCommunicationPoint, communicationStepSize, &n);
    if (why == 1) {
        thys_log(inst, fmi2Error, "fmi2DoStep: currentCommunicationPoint %.17g is not the "
                 "instance's time %.17g", currentCommunicationPoint,
                 inst->core.start + (double)inst->core.k * THYS_SAMPLE_PERIOD);
        return fmi2Error;
    }
    if (why == 2) {
        thys_log(inst, fmi2Error, "fmi2DoStep: communicationStepSize %.17g is not a positive "
                 "integer multiple of the sample period %.17g", communicationStepSize,
                 THYS_SAMPLE_PERIOD);
        return fmi2Error;
    }
    thys_core_run(&inst->core, n);
    return fmi2OK;
}
"""
