"""The FMI 2.0 functions without a meaning for this FMU (:mod:`torchhys.deploy.fmu._fmi2`'s
second part): the Boolean and String variables (none: fine for no value reference),
derivatives, the asynchronous step's cancel and status calls (``fmi2GetRealStatus``
answers fmi2LastSuccessfulTime, ``fmi2GetBooleanStatus`` fmi2Terminated)."""

FMI2_UNSUPPORTED = r"""
THYS_EXPORT fmi2Status FMI2(fmi2GetBoolean)(fmi2Component c, const fmi2ValueReference vr[],
                                            size_t nvr, fmi2Boolean value[])
{
    (void)vr;
    (void)value;
    return thys_none(c, nvr, "fmi2GetBoolean");
}

THYS_EXPORT fmi2Status FMI2(fmi2GetString)(fmi2Component c, const fmi2ValueReference vr[],
                                           size_t nvr, fmi2String value[])
{
    (void)vr;
    (void)value;
    return thys_none(c, nvr, "fmi2GetString");
}

THYS_EXPORT fmi2Status FMI2(fmi2SetBoolean)(fmi2Component c, const fmi2ValueReference vr[],
                                            size_t nvr, const fmi2Boolean value[])
{
    (void)vr;
    (void)value;
    return thys_none(c, nvr, "fmi2SetBoolean");
}

THYS_EXPORT fmi2Status FMI2(fmi2SetString)(fmi2Component c, const fmi2ValueReference vr[],
                                           size_t nvr, const fmi2String value[])
{
    (void)vr;
    (void)value;
    return thys_none(c, nvr, "fmi2SetString");
}

THYS_EXPORT fmi2Status FMI2(fmi2GetDirectionalDerivative)(
    fmi2Component c, const fmi2ValueReference vUnknown_ref[], size_t nUnknown,
    const fmi2ValueReference vKnown_ref[], size_t nKnown, const fmi2Real dvKnown[],
    fmi2Real dvUnknown[])
{
    (void)vUnknown_ref;
    (void)nUnknown;
    (void)vKnown_ref;
    (void)nKnown;
    (void)dvKnown;
    (void)dvUnknown;
    thys_log((thys_instance *)c, fmi2Error, "fmi2GetDirectionalDerivative: not provided "
             "(providesDirectionalDerivative is false)");
    return fmi2Error;
}

THYS_EXPORT fmi2Status FMI2(fmi2SetRealInputDerivatives)(fmi2Component c,
                                                         const fmi2ValueReference vr[],
                                                         size_t nvr,
                                                         const fmi2Integer order[],
                                                         const fmi2Real value[])
{
    (void)vr;
    (void)order;
    (void)value;
    if (nvr == 0)
        return fmi2OK;
    thys_log((thys_instance *)c, fmi2Error, "fmi2SetRealInputDerivatives: the FMU does not "
             "interpolate its inputs (canInterpolateInputs is false)");
    return fmi2Error;
}

THYS_EXPORT fmi2Status FMI2(fmi2GetRealOutputDerivatives)(fmi2Component c,
                                                          const fmi2ValueReference vr[],
                                                          size_t nvr,
                                                          const fmi2Integer order[],
                                                          fmi2Real value[])
{
    (void)vr;
    (void)order;
    (void)value;
    if (nvr == 0)
        return fmi2OK;
    thys_log((thys_instance *)c, fmi2Error, "fmi2GetRealOutputDerivatives: not provided "
             "(maxOutputDerivativeOrder is 0)");
    return fmi2Error;
}

THYS_EXPORT fmi2Status FMI2(fmi2CancelStep)(fmi2Component c)
{
    thys_log((thys_instance *)c, fmi2Error, "fmi2CancelStep: fmi2DoStep never returns "
             "fmi2Pending");
    return fmi2Error;
}

THYS_EXPORT fmi2Status FMI2(fmi2GetStatus)(fmi2Component c, const fmi2StatusKind s,
                                           fmi2Status *value)
{
    (void)c;
    (void)s;
    (void)value;
    return fmi2Discard;  /* fmi2DoStep never returns fmi2Pending */
}

THYS_EXPORT fmi2Status FMI2(fmi2GetRealStatus)(fmi2Component c, const fmi2StatusKind s,
                                               fmi2Real *value)
{
    thys_instance *inst = thys_check(c, ANY, "fmi2GetRealStatus");
    if (inst == NULL || value == NULL)
        return fmi2Error;
    if (s != fmi2LastSuccessfulTime)
        return fmi2Discard;
    *value = inst->core.start + (double)inst->core.k * THYS_SAMPLE_PERIOD;
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2GetIntegerStatus)(fmi2Component c, const fmi2StatusKind s,
                                                  fmi2Integer *value)
{
    (void)c;
    (void)s;
    (void)value;
    return fmi2Discard;
}

THYS_EXPORT fmi2Status FMI2(fmi2GetBooleanStatus)(fmi2Component c, const fmi2StatusKind s,
                                                  fmi2Boolean *value)
{
    thys_instance *inst = thys_check(c, ANY, "fmi2GetBooleanStatus");
    if (inst == NULL || value == NULL)
        return fmi2Error;
    if (s != fmi2Terminated)
        return fmi2Discard;
    *value = fmi2False;
    return fmi2OK;
}

THYS_EXPORT fmi2Status FMI2(fmi2GetStringStatus)(fmi2Component c, const fmi2StatusKind s,
                                                 fmi2String *value)
{
    (void)c;
    (void)s;
    (void)value;
    return fmi2Discard;
}
"""
