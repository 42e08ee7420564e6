"""The FMI 3.0 co-simulation wrapper (:mod:`torchhys.deploy.fmu`): C over the shared core
(:mod:`torchhys.deploy.fmu._core`), its types and functions written from the signatures of
the FMI 3.0 specification (chapters 2 and 4); every function of the standard is defined
(those for model exchange, scheduled execution, clocks, event mode, configuration mode and
derivatives, which this FMU does not provide, return fmi3Error with a logged message).
With ``FMI3_FUNCTION_PREFIX`` defined (a static link of several FMUs), the names are
prefixed."""

from __future__ import annotations

FMI3 = r"""
/* ---- FMI 3.0 co-simulation (torchhys.deploy.fmu._fmi3) ------------------------------ */
#include <stdbool.h>

typedef void *fmi3Instance;
typedef void *fmi3InstanceEnvironment;
typedef void *fmi3FMUState;
typedef uint32_t fmi3ValueReference;
typedef float fmi3Float32;
typedef double fmi3Float64;
typedef int8_t fmi3Int8;
typedef uint8_t fmi3UInt8;
typedef int16_t fmi3Int16;
typedef uint16_t fmi3UInt16;
typedef int32_t fmi3Int32;
typedef uint32_t fmi3UInt32;
typedef int64_t fmi3Int64;
typedef uint64_t fmi3UInt64;
typedef bool fmi3Boolean;
typedef char fmi3Char;
typedef const fmi3Char *fmi3String;
typedef uint8_t fmi3Byte;
typedef const fmi3Byte *fmi3Binary;
typedef bool fmi3Clock;
typedef enum { fmi3OK, fmi3Warning, fmi3Discard, fmi3Error, fmi3Fatal } fmi3Status;
typedef enum { fmi3IntervalNotYetKnown, fmi3IntervalUnchanged,
               fmi3IntervalChanged } fmi3IntervalQualifier;
typedef enum { fmi3Independent, fmi3Constant, fmi3Fixed, fmi3Tunable, fmi3Discrete,
               fmi3Dependent } fmi3DependencyKind;
typedef void (*fmi3LogMessageCallback)(fmi3InstanceEnvironment, fmi3Status, fmi3String,
                                       fmi3String);
typedef void (*fmi3IntermediateUpdateCallback)(fmi3InstanceEnvironment, fmi3Float64,
                                               fmi3Boolean, fmi3Boolean, fmi3Boolean,
                                               fmi3Boolean, fmi3Boolean *, fmi3Float64 *);
typedef void (*fmi3ClockUpdateCallback)(fmi3InstanceEnvironment);
typedef void (*fmi3LockPreemptionCallback)(void);
typedef void (*fmi3UnlockPreemptionCallback)(void);

#ifdef FMI3_FUNCTION_PREFIX
#define THYS_CAT_(a, b) a##b
#define THYS_CAT(a, b) THYS_CAT_(a, b)
#define FMI3(name) THYS_CAT(FMI3_FUNCTION_PREFIX, name)
#else
#define FMI3(name) name
#endif

typedef struct {
    thys_core core;
    fmi3LogMessageCallback logger;
    fmi3InstanceEnvironment env;
    int mode;
    int logging;
} thys_instance;

static void thys_log(const thys_instance *inst, fmi3Status status, const char *fmt, ...)
{
    char buf[512];
    va_list args;
    if (inst == NULL || inst->logger == NULL || (status == fmi3OK && !inst->logging))
        return;
    va_start(args, fmt);
    thys_format(buf, sizeof buf, fmt, args);
    va_end(args);
    inst->logger(inst->env, status, status == fmi3Error ? "logStatusError" : "logAll", buf);
}

static thys_instance *thys_check(fmi3Instance instance, int mask, const char *function)
{
    thys_instance *inst = (thys_instance *)instance;
    if (inst == NULL)
        return NULL;
    if (!(mask & (1 << inst->mode))) {
        thys_log(inst, fmi3Error, "%s: not allowed in the instance's present state", function);
        return NULL;
    }
    return inst;
}

#define ANY ((1 << THYS_INSTANTIATED) | (1 << THYS_INITIALIZATION) | (1 << THYS_STEPPING) \
             | (1 << THYS_TERMINATED))
#define SETTABLE ((1 << THYS_INSTANTIATED) | (1 << THYS_INITIALIZATION) | (1 << THYS_STEPPING))

/* a function this FMU does not provide: logged, fmi3Error */
static fmi3Status thys_unsupported(fmi3Instance instance, const char *function)
{
    thys_log((thys_instance *)instance, fmi3Error, "%s: not provided by this FMU "
             "(co-simulation without event mode, clocks, configuration mode or derivatives)",
             function);
    return fmi3Error;
}

/* get or set of a type the FMU has no variable of: fine for none, else fmi3Error */
static fmi3Status thys_none(fmi3Instance instance, size_t nvr, const char *function)
{
    thys_instance *inst = thys_check(instance, ANY, function);
    if (inst == NULL)
        return fmi3Error;
    if (nvr == 0)
        return fmi3OK;
    thys_log(inst, fmi3Error, "%s: the FMU has no variable of this type", function);
    return fmi3Error;
}

THYS_EXPORT const char *FMI3(fmi3GetVersion)(void) { return "3.0"; }

THYS_EXPORT fmi3Status FMI3(fmi3SetDebugLogging)(fmi3Instance instance, fmi3Boolean loggingOn,
                                                 size_t nCategories,
                                                 const fmi3String categories[])
{
    thys_instance *inst = thys_check(instance, ANY, "fmi3SetDebugLogging");
    (void)nCategories; (void)categories;
    if (inst == NULL)
        return fmi3Error;
    inst->logging = loggingOn;
    return fmi3OK;
}

THYS_EXPORT fmi3Instance FMI3(fmi3InstantiateCoSimulation)(
    fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath,
    fmi3Boolean visible, fmi3Boolean loggingOn, fmi3Boolean eventModeUsed,
    fmi3Boolean earlyReturnAllowed, const fmi3ValueReference requiredIntermediateVariables[],
    size_t nRequiredIntermediateVariables, fmi3InstanceEnvironment instanceEnvironment,
    fmi3LogMessageCallback logMessage, fmi3IntermediateUpdateCallback intermediateUpdate)
{
    thys_instance probe, *inst;
    (void)instanceName; (void)resourcePath; (void)visible; (void)earlyReturnAllowed;
    (void)requiredIntermediateVariables; (void)intermediateUpdate;
    memset(&probe, 0, sizeof probe);
    probe.logger = logMessage;
    probe.env = instanceEnvironment;
    if (instantiationToken == NULL || strcmp(instantiationToken, thys_token) != 0) {
        thys_log(&probe, fmi3Error, "fmi3InstantiateCoSimulation: the instantiationToken %s "
                 "is not this FMU's %s", instantiationToken ? instantiationToken : "(null)",
                 thys_token);
        return NULL;
    }
    if (eventModeUsed || nRequiredIntermediateVariables > 0) {
        thys_log(&probe, fmi3Error, "fmi3InstantiateCoSimulation: the FMU has no event mode "
                 "and no intermediate variables");
        return NULL;
    }
    inst = (thys_instance *)calloc(1, sizeof *inst);
    if (inst == NULL)
        return NULL;
    *inst = probe;
    inst->logging = loggingOn;
    inst->mode = THYS_INSTANTIATED;
    thys_core_reset(&inst->core);
    return inst;
}

THYS_EXPORT void FMI3(fmi3FreeInstance)(fmi3Instance instance) { free(instance); }

THYS_EXPORT fmi3Status FMI3(fmi3EnterInitializationMode)(
    fmi3Instance instance, fmi3Boolean toleranceDefined, fmi3Float64 tolerance,
    fmi3Float64 startTime, fmi3Boolean stopTimeDefined, fmi3Float64 stopTime)
{
    thys_instance *inst = thys_check(instance, 1 << THYS_INSTANTIATED,
                                     "fmi3EnterInitializationMode");
    (void)toleranceDefined; (void)tolerance; (void)stopTimeDefined; (void)stopTime;
    if (inst == NULL)
        return fmi3Error;
    if (!isfinite(startTime)) {
        thys_log(inst, fmi3Error, "fmi3EnterInitializationMode: startTime must be finite");
        return fmi3Error;
    }
    inst->core.start = startTime;
    inst->mode = THYS_INITIALIZATION;
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3ExitInitializationMode)(fmi3Instance instance)
{
    thys_instance *inst = thys_check(instance, 1 << THYS_INITIALIZATION,
                                     "fmi3ExitInitializationMode");
    if (inst == NULL)
        return fmi3Error;
    inst->mode = THYS_STEPPING;  /* no event mode: step mode */
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3Terminate)(fmi3Instance instance)
{
    thys_instance *inst = thys_check(instance, 1 << THYS_STEPPING, "fmi3Terminate");
    if (inst == NULL)
        return fmi3Error;
    inst->mode = THYS_TERMINATED;
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3Reset)(fmi3Instance instance)
{
    thys_instance *inst = thys_check(instance, ANY, "fmi3Reset");
    if (inst == NULL)
        return fmi3Error;
    thys_core_reset(&inst->core);
    inst->mode = THYS_INSTANTIATED;
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3GetFloat64)(fmi3Instance instance,
                                            const fmi3ValueReference valueReferences[],
                                            size_t nValueReferences, fmi3Float64 values[],
                                            size_t nValues)
{
    size_t i;
    thys_instance *inst = thys_check(instance, ANY, "fmi3GetFloat64");
    if (inst == NULL || nValues != nValueReferences
        || (nValueReferences > 0 && (valueReferences == NULL || values == NULL)))
        return fmi3Error;
    for (i = 0; i < nValueReferences; ++i)
        if (thys_core_get_real(&inst->core, valueReferences[i], &values[i]) != 0) {
            thys_log(inst, fmi3Error, "fmi3GetFloat64: no Float64 variable of value "
                     "reference %u", (unsigned)valueReferences[i]);
            return fmi3Error;
        }
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3SetFloat64)(fmi3Instance instance,
                                            const fmi3ValueReference valueReferences[],
                                            size_t nValueReferences, const fmi3Float64 values[],
                                            size_t nValues)
{
    size_t i;
    thys_instance *inst = thys_check(instance, SETTABLE, "fmi3SetFloat64");
    if (inst == NULL || nValues != nValueReferences
        || (nValueReferences > 0 && (valueReferences == NULL || values == NULL)))
        return fmi3Error;
    for (i = 0; i < nValueReferences; ++i) {
        int done = thys_core_set_real(&inst->core, valueReferences[i], values[i]);
        if (done != 0) {
            thys_log(inst, fmi3Error, done == -2
                     ? "fmi3SetFloat64: the variable of value reference %u is not an input"
                     : "fmi3SetFloat64: no Float64 variable of value reference %u",
                     (unsigned)valueReferences[i]);
            return fmi3Error;
        }
    }
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3GetInt64)(fmi3Instance instance,
                                          const fmi3ValueReference valueReferences[],
                                          size_t nValueReferences, fmi3Int64 values[],
                                          size_t nValues)
{
    size_t i;
    thys_instance *inst = thys_check(instance, ANY, "fmi3GetInt64");
    if (inst == NULL || nValues != nValueReferences
        || (nValueReferences > 0 && (valueReferences == NULL || values == NULL)))
        return fmi3Error;
    for (i = 0; i < nValueReferences; ++i)
        if (thys_core_get_count(&inst->core, valueReferences[i], &values[i]) != 0) {
            thys_log(inst, fmi3Error, "fmi3GetInt64: no Int64 variable of value reference %u",
                     (unsigned)valueReferences[i]);
            return fmi3Error;
        }
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3SetInt64)(fmi3Instance instance,
                                          const fmi3ValueReference valueReferences[],
                                          size_t nValueReferences, const fmi3Int64 values[],
                                          size_t nValues)
{
    (void)valueReferences; (void)values; (void)nValues;
    if (nValueReferences > 0 && instance != NULL) {
        thys_log((thys_instance *)instance, fmi3Error, "fmi3SetInt64: the Int64 variables "
                 "(the counters) are outputs");
        return fmi3Error;
    }
    return thys_none(instance, nValueReferences, "fmi3SetInt64");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetFMUState)(fmi3Instance instance, fmi3FMUState *FMUState)
{
    thys_instance *inst = thys_check(instance, ANY, "fmi3GetFMUState");
    if (inst == NULL || FMUState == NULL)
        return fmi3Error;
    if (*FMUState == NULL) {
        *FMUState = calloc(1, sizeof(thys_core));
        if (*FMUState == NULL) {
            thys_log(inst, fmi3Error, "fmi3GetFMUState: out of memory");
            return fmi3Error;
        }
    }
    memcpy(*FMUState, &inst->core, sizeof(thys_core));
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3SetFMUState)(fmi3Instance instance, fmi3FMUState FMUState)
{
    thys_instance *inst = thys_check(instance, ANY, "fmi3SetFMUState");
    if (inst == NULL || FMUState == NULL)
        return fmi3Error;
    memcpy(&inst->core, FMUState, sizeof(thys_core));
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3FreeFMUState)(fmi3Instance instance, fmi3FMUState *FMUState)
{
    thys_instance *inst = thys_check(instance, ANY, "fmi3FreeFMUState");
    if (inst == NULL || FMUState == NULL)
        return fmi3Error;
    free(*FMUState);
    *FMUState = NULL;
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3SerializedFMUStateSize)(fmi3Instance instance,
                                                        fmi3FMUState FMUState, size_t *size)
{
    thys_instance *inst = thys_check(instance, ANY, "fmi3SerializedFMUStateSize");
    (void)FMUState;
    if (inst == NULL || size == NULL)
        return fmi3Error;
    *size = THYS_SERIALIZED_BYTES;
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3SerializeFMUState)(fmi3Instance instance, fmi3FMUState FMUState,
                                                   fmi3Byte serializedState[], size_t size)
{
    thys_instance *inst = thys_check(instance, ANY, "fmi3SerializeFMUState");
    if (inst == NULL || FMUState == NULL || serializedState == NULL)
        return fmi3Error;
    if (size < THYS_SERIALIZED_BYTES) {
        thys_log(inst, fmi3Error, "fmi3SerializeFMUState: the buffer holds %lu bytes, the "
                 "state needs %lu", (unsigned long)size, (unsigned long)THYS_SERIALIZED_BYTES);
        return fmi3Error;
    }
    thys_core_serialize((const thys_core *)FMUState, serializedState);
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3DeserializeFMUState)(fmi3Instance instance,
                                                     const fmi3Byte serializedState[],
                                                     size_t size, fmi3FMUState *FMUState)
{
    thys_core core;
    thys_instance *inst = thys_check(instance, ANY, "fmi3DeserializeFMUState");
    if (inst == NULL || serializedState == NULL || FMUState == NULL)
        return fmi3Error;
    if (thys_core_deserialize(&core, serializedState, size) != 0) {
        thys_log(inst, fmi3Error, "fmi3DeserializeFMUState: the %lu bytes are not a state "
                 "serialized by this FMU", (unsigned long)size);
        return fmi3Error;
    }
    if (*FMUState == NULL)
        *FMUState = calloc(1, sizeof(thys_core));
    if (*FMUState == NULL)
        return fmi3Error;
    memcpy(*FMUState, &core, sizeof core);
    return fmi3OK;
}

THYS_EXPORT fmi3Status FMI3(fmi3DoStep)(fmi3Instance instance,
                                        fmi3Float64 currentCommunicationPoint,
                                        fmi3Float64 communicationStepSize,
                                        fmi3Boolean noSetFMUStatePriorToCurrentPoint,
                                        fmi3Boolean *eventHandlingNeeded,
                                        fmi3Boolean *terminateSimulation,
                                        fmi3Boolean *earlyReturn,
                                        fmi3Float64 *lastSuccessfulTime)
{
    int64_t n = 0;
    int why;
    thys_instance *inst = thys_check(instance, 1 << THYS_STEPPING, "fmi3DoStep");
    (void)noSetFMUStatePriorToCurrentPoint;
    if (inst == NULL)
        return fmi3Error;
    if (eventHandlingNeeded)
        *eventHandlingNeeded = false;
    if (terminateSimulation)
        *terminateSimulation = false;
    if (earlyReturn)
        *earlyReturn = false;
    why = thys_core_samples(&inst->core, currentCommunicationPoint, communicationStepSize, &n);
    if (why == 0)
        thys_core_run(&inst->core, n);
    if (lastSuccessfulTime)
        *lastSuccessfulTime = inst->core.start + (double)inst->core.k * THYS_SAMPLE_PERIOD;
    if (why == 1) {
        thys_log(inst, fmi3Error, "fmi3DoStep: currentCommunicationPoint %.17g is not the "
                 "instance's time %.17g", currentCommunicationPoint,
                 inst->core.start + (double)inst->core.k * THYS_SAMPLE_PERIOD);
        return fmi3Error;
    }
    if (why == 2) {
        thys_log(inst, fmi3Error, "fmi3DoStep: communicationStepSize %.17g is not a positive "
                 "integer multiple of the sample period %.17g", communicationStepSize,
                 THYS_SAMPLE_PERIOD);
        return fmi3Error;
    }
    return fmi3OK;
}
"""
