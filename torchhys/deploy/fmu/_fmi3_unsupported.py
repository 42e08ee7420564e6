"""The FMI 3.0 functions that this FMU does not provide (:mod:`torchhys.deploy.fmu._fmi3`'s
second part): model exchange and scheduled execution, the types without variables
(Float32, the other integers, Boolean, String, Binary, Clock: fine for no value
reference), clocks, event and configuration modes, dependencies and derivatives. Each is
defined, as the standard asks, and returns fmi3Error with a logged message."""

FMI3_UNSUPPORTED = r"""
THYS_EXPORT fmi3Instance FMI3(fmi3InstantiateModelExchange)(
    fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath,
    fmi3Boolean visible, fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment,
    fmi3LogMessageCallback logMessage)
{
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible;
    (void)loggingOn;
    if (logMessage)
        logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                   "fmi3InstantiateModelExchange: the FMU is for co-simulation only");
    return NULL;
}

THYS_EXPORT fmi3Instance FMI3(fmi3InstantiateScheduledExecution)(
    fmi3String instanceName, fmi3String instantiationToken, fmi3String resourcePath,
    fmi3Boolean visible, fmi3Boolean loggingOn, fmi3InstanceEnvironment instanceEnvironment,
    fmi3LogMessageCallback logMessage, fmi3ClockUpdateCallback clockUpdate,
    fmi3LockPreemptionCallback lockPreemption, fmi3UnlockPreemptionCallback unlockPreemption)
{
    (void)instanceName; (void)instantiationToken; (void)resourcePath; (void)visible;
    (void)loggingOn; (void)clockUpdate; (void)lockPreemption; (void)unlockPreemption;
    if (logMessage)
        logMessage(instanceEnvironment, fmi3Error, "logStatusError",
                   "fmi3InstantiateScheduledExecution: the FMU is for co-simulation only");
    return NULL;
}

THYS_EXPORT fmi3Status FMI3(fmi3EnterEventMode)(fmi3Instance instance)
{
    return thys_unsupported(instance, "fmi3EnterEventMode");
}

#define THYS_NO_GET(TYPE, NAME)                                                           \
    THYS_EXPORT fmi3Status FMI3(fmi3Get##NAME)(fmi3Instance instance,                     \
                                               const fmi3ValueReference valueReferences[], \
                                               size_t nValueReferences, TYPE values[],     \
                                               size_t nValues)                             \
    {                                                                                      \
        (void)valueReferences; (void)values; (void)nValues;                                \
        return thys_none(instance, nValueReferences, "fmi3Get" #NAME);                     \
    }
#define THYS_NO_SET(TYPE, NAME)                                                           \
    THYS_EXPORT fmi3Status FMI3(fmi3Set##NAME)(fmi3Instance instance,                     \
                                               const fmi3ValueReference valueReferences[], \
                                               size_t nValueReferences,                    \
                                               const TYPE values[], size_t nValues)        \
    {                                                                                      \
        (void)valueReferences; (void)values; (void)nValues;                                \
        return thys_none(instance, nValueReferences, "fmi3Set" #NAME);                     \
    }
#define THYS_NONE(TYPE, NAME) THYS_NO_GET(TYPE, NAME) THYS_NO_SET(TYPE, NAME)

THYS_NONE(fmi3Float32, Float32)
THYS_NONE(fmi3Int8, Int8)
THYS_NONE(fmi3UInt8, UInt8)
THYS_NONE(fmi3Int16, Int16)
THYS_NONE(fmi3UInt16, UInt16)
THYS_NONE(fmi3Int32, Int32)
THYS_NONE(fmi3UInt32, UInt32)
THYS_NONE(fmi3UInt64, UInt64)
THYS_NONE(fmi3Boolean, Boolean)
THYS_NONE(fmi3String, String)

THYS_EXPORT fmi3Status FMI3(fmi3GetBinary)(fmi3Instance instance,
                                           const fmi3ValueReference valueReferences[],
                                           size_t nValueReferences, size_t valueSizes[],
                                           fmi3Binary values[], size_t nValues)
{
    (void)valueReferences; (void)valueSizes; (void)values; (void)nValues;
    return thys_none(instance, nValueReferences, "fmi3GetBinary");
}

THYS_EXPORT fmi3Status FMI3(fmi3SetBinary)(fmi3Instance instance,
                                           const fmi3ValueReference valueReferences[],
                                           size_t nValueReferences, const size_t valueSizes[],
                                           const fmi3Binary values[], size_t nValues)
{
    (void)valueReferences; (void)valueSizes; (void)values; (void)nValues;
    return thys_none(instance, nValueReferences, "fmi3SetBinary");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetClock)(fmi3Instance instance,
                                          const fmi3ValueReference valueReferences[],
                                          size_t nValueReferences, fmi3Clock values[])
{
    (void)valueReferences; (void)values;
    return thys_none(instance, nValueReferences, "fmi3GetClock");
}

THYS_EXPORT fmi3Status FMI3(fmi3SetClock)(fmi3Instance instance,
                                          const fmi3ValueReference valueReferences[],
                                          size_t nValueReferences, const fmi3Clock values[])
{
    (void)valueReferences; (void)values;
    return thys_none(instance, nValueReferences, "fmi3SetClock");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetNumberOfVariableDependencies)(
    fmi3Instance instance, fmi3ValueReference valueReference, size_t *nDependencies)
{
    (void)valueReference; (void)nDependencies;
    return thys_unsupported(instance, "fmi3GetNumberOfVariableDependencies");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetVariableDependencies)(
    fmi3Instance instance, fmi3ValueReference dependent, size_t elementIndicesOfDependent[],
    fmi3ValueReference independents[], size_t elementIndicesOfIndependents[],
    fmi3DependencyKind dependencyKinds[], size_t nDependencies)
{
    (void)dependent; (void)elementIndicesOfDependent; (void)independents;
    (void)elementIndicesOfIndependents; (void)dependencyKinds; (void)nDependencies;
    return thys_unsupported(instance, "fmi3GetVariableDependencies");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetDirectionalDerivative)(
    fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
    const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed,
    fmi3Float64 sensitivity[], size_t nSensitivity)
{
    (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed;
    (void)sensitivity; (void)nSensitivity;
    return thys_unsupported(instance, "fmi3GetDirectionalDerivative");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetAdjointDerivative)(
    fmi3Instance instance, const fmi3ValueReference unknowns[], size_t nUnknowns,
    const fmi3ValueReference knowns[], size_t nKnowns, const fmi3Float64 seed[], size_t nSeed,
    fmi3Float64 sensitivity[], size_t nSensitivity)
{
    (void)unknowns; (void)nUnknowns; (void)knowns; (void)nKnowns; (void)seed; (void)nSeed;
    (void)sensitivity; (void)nSensitivity;
    return thys_unsupported(instance, "fmi3GetAdjointDerivative");
}

THYS_EXPORT fmi3Status FMI3(fmi3EnterConfigurationMode)(fmi3Instance instance)
{
    return thys_unsupported(instance, "fmi3EnterConfigurationMode");
}

THYS_EXPORT fmi3Status FMI3(fmi3ExitConfigurationMode)(fmi3Instance instance)
{
    return thys_unsupported(instance, "fmi3ExitConfigurationMode");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetIntervalDecimal)(
    fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
    fmi3Float64 intervals[], fmi3IntervalQualifier qualifiers[])
{
    (void)valueReferences; (void)nValueReferences; (void)intervals; (void)qualifiers;
    return thys_unsupported(instance, "fmi3GetIntervalDecimal");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetIntervalFraction)(
    fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
    fmi3UInt64 counters[], fmi3UInt64 resolutions[], fmi3IntervalQualifier qualifiers[])
{
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    (void)qualifiers;
    return thys_unsupported(instance, "fmi3GetIntervalFraction");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetShiftDecimal)(
    fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
    fmi3Float64 shifts[])
{
    (void)valueReferences; (void)nValueReferences; (void)shifts;
    return thys_unsupported(instance, "fmi3GetShiftDecimal");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetShiftFraction)(
    fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
    fmi3UInt64 counters[], fmi3UInt64 resolutions[])
{
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    return thys_unsupported(instance, "fmi3GetShiftFraction");
}

THYS_EXPORT fmi3Status FMI3(fmi3SetIntervalDecimal)(
    fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
    const fmi3Float64 intervals[])
{
    (void)valueReferences; (void)nValueReferences; (void)intervals;
    return thys_unsupported(instance, "fmi3SetIntervalDecimal");
}

THYS_EXPORT fmi3Status FMI3(fmi3SetIntervalFraction)(
    fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
    const fmi3UInt64 counters[], const fmi3UInt64 resolutions[])
{
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    return thys_unsupported(instance, "fmi3SetIntervalFraction");
}

THYS_EXPORT fmi3Status FMI3(fmi3SetShiftDecimal)(
    fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
    const fmi3Float64 shifts[])
{
    (void)valueReferences; (void)nValueReferences; (void)shifts;
    return thys_unsupported(instance, "fmi3SetShiftDecimal");
}

THYS_EXPORT fmi3Status FMI3(fmi3SetShiftFraction)(
    fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
    const fmi3UInt64 counters[], const fmi3UInt64 resolutions[])
{
    (void)valueReferences; (void)nValueReferences; (void)counters; (void)resolutions;
    return thys_unsupported(instance, "fmi3SetShiftFraction");
}

THYS_EXPORT fmi3Status FMI3(fmi3EvaluateDiscreteStates)(fmi3Instance instance)
{
    return thys_unsupported(instance, "fmi3EvaluateDiscreteStates");
}

THYS_EXPORT fmi3Status FMI3(fmi3UpdateDiscreteStates)(
    fmi3Instance instance, fmi3Boolean *discreteStatesNeedUpdate,
    fmi3Boolean *terminateSimulation, fmi3Boolean *nominalsOfContinuousStatesChanged,
    fmi3Boolean *valuesOfContinuousStatesChanged, fmi3Boolean *nextEventTimeDefined,
    fmi3Float64 *nextEventTime)
{
    (void)discreteStatesNeedUpdate; (void)terminateSimulation;
    (void)nominalsOfContinuousStatesChanged; (void)valuesOfContinuousStatesChanged;
    (void)nextEventTimeDefined; (void)nextEventTime;
    return thys_unsupported(instance, "fmi3UpdateDiscreteStates");
}

THYS_EXPORT fmi3Status FMI3(fmi3EnterContinuousTimeMode)(fmi3Instance instance)
{
    return thys_unsupported(instance, "fmi3EnterContinuousTimeMode");
}

THYS_EXPORT fmi3Status FMI3(fmi3CompletedIntegratorStep)(
    fmi3Instance instance, fmi3Boolean noSetFMUStatePriorToCurrentPoint,
    fmi3Boolean *enterEventMode, fmi3Boolean *terminateSimulation)
{
    (void)noSetFMUStatePriorToCurrentPoint; (void)enterEventMode; (void)terminateSimulation;
    return thys_unsupported(instance, "fmi3CompletedIntegratorStep");
}

THYS_EXPORT fmi3Status FMI3(fmi3SetTime)(fmi3Instance instance, fmi3Float64 time)
{
    (void)time;
    return thys_unsupported(instance, "fmi3SetTime");
}

THYS_EXPORT fmi3Status FMI3(fmi3SetContinuousStates)(fmi3Instance instance,
                                                     const fmi3Float64 continuousStates[],
                                                     size_t nContinuousStates)
{
    (void)continuousStates; (void)nContinuousStates;
    return thys_unsupported(instance, "fmi3SetContinuousStates");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetContinuousStateDerivatives)(fmi3Instance instance,
                                                               fmi3Float64 derivatives[],
                                                               size_t nContinuousStates)
{
    (void)derivatives; (void)nContinuousStates;
    return thys_unsupported(instance, "fmi3GetContinuousStateDerivatives");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetEventIndicators)(fmi3Instance instance,
                                                    fmi3Float64 eventIndicators[],
                                                    size_t nEventIndicators)
{
    (void)eventIndicators; (void)nEventIndicators;
    return thys_unsupported(instance, "fmi3GetEventIndicators");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetContinuousStates)(fmi3Instance instance,
                                                     fmi3Float64 continuousStates[],
                                                     size_t nContinuousStates)
{
    (void)continuousStates; (void)nContinuousStates;
    return thys_unsupported(instance, "fmi3GetContinuousStates");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetNominalsOfContinuousStates)(fmi3Instance instance,
                                                               fmi3Float64 nominals[],
                                                               size_t nContinuousStates)
{
    (void)nominals; (void)nContinuousStates;
    return thys_unsupported(instance, "fmi3GetNominalsOfContinuousStates");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetNumberOfEventIndicators)(fmi3Instance instance,
                                                            size_t *nEventIndicators)
{
    (void)nEventIndicators;
    return thys_unsupported(instance, "fmi3GetNumberOfEventIndicators");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetNumberOfContinuousStates)(fmi3Instance instance,
                                                             size_t *nContinuousStates)
{
    (void)nContinuousStates;
    return thys_unsupported(instance, "fmi3GetNumberOfContinuousStates");
}

THYS_EXPORT fmi3Status FMI3(fmi3EnterStepMode)(fmi3Instance instance)
{
    return thys_unsupported(instance, "fmi3EnterStepMode");
}

THYS_EXPORT fmi3Status FMI3(fmi3GetOutputDerivatives)(
    fmi3Instance instance, const fmi3ValueReference valueReferences[], size_t nValueReferences,
    const fmi3Int32 orders[], fmi3Float64 values[], size_t nValues)
{
    (void)valueReferences; (void)orders; (void)values; (void)nValues;
    if (nValueReferences == 0)
        return fmi3OK;
    return thys_unsupported(instance, "fmi3GetOutputDerivatives");
}

THYS_EXPORT fmi3Status FMI3(fmi3ActivateModelPartition)(fmi3Instance instance,
                                                        fmi3ValueReference clockReference,
                                                        fmi3Float64 activationTime)
{
    (void)clockReference; (void)activationTime;
    return thys_unsupported(instance, "fmi3ActivateModelPartition");
}
"""
