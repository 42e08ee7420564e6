"""The FMU's XML (:mod:`torchhys.deploy.fmu`): ``modelDescription.xml`` for FMI 2.0 and 3.0
and FMI 3's ``sources/buildDescription.xml``, from the table of
:mod:`torchhys.deploy.fmu._variables`. Deterministic (no date): one model and one set of
options give the same bytes."""

from __future__ import annotations

from xml.sax.saxutils import quoteattr

from torchhys.deploy.fmu._variables import Variable, Variables

#: the log categories of the wrapper's messages
LOG_CATEGORIES = (("logStatusError", "errors: a call in a wrong state, a bad value reference "
                   "or a communication step that is not a multiple of the sample period"),
                  ("logAll", "every other message (with logging on)"))


def _attrs(**items: object) -> str:
    return "".join(f" {k}={quoteattr(str(v))}" for k, v in items.items() if v is not None)


def _number(value: float) -> str:
    """An xs:double (NaN as XML Schema spells it)."""
    return "NaN" if value != value else repr(float(value))


def _units(variables: Variables) -> list[str]:
    units = sorted({v.unit for v in variables.all if v.unit})
    if not units:
        return []
    lines = ["  <UnitDefinitions>"]
    for unit in units:
        lines.append(f'    <Unit name={quoteattr(unit)}><BaseUnit s="1"/></Unit>' if unit == "s"
                     else f"    <Unit name={quoteattr(unit)}/>")
    return [*lines, "  </UnitDefinitions>"]


def _common_head(fmi: int) -> list[str]:
    tag = "Category"
    lines = ["  <LogCategories>"]
    lines += [f"    <{tag}{_attrs(name=n, description=d)}/>" for n, d in LOG_CATEGORIES]
    return [*lines, "  </LogCategories>"]


def _initial(v: Variable) -> str | None:
    if v.causality in ("input", "independent"):
        return None
    return "exact"


def model_description(fmi: int, *, prefix: str, model_name: str, token: str,
                      description: str, tool: str, variables: Variables,
                      step_size: float, sources: list[str]) -> str:
    """The text of ``modelDescription.xml`` (``fmi`` 2 or 3)."""
    head = _attrs(
        fmiVersion="2.0" if fmi == 2 else "3.0", modelName=model_name,
        **({"guid": token} if fmi == 2 else {"instantiationToken": token}),
        description=description, generationTool=tool, variableNamingConvention="flat",
        **({"numberOfEventIndicators": 0} if fmi == 2 else {}))
    if fmi == 2:
        cs = [f"  <CoSimulation{_attrs(modelIdentifier=prefix, canHandleVariableCommunicationStepSize='true', canInterpolateInputs='false', maxOutputDerivativeOrder=0, canRunAsynchronuously='false', canBeInstantiatedOnlyOncePerProcess='false', canNotUseMemoryManagementFunctions='false', canGetAndSetFMUstate='true', canSerializeFMUstate='true', providesDirectionalDerivative='false')}>",  # noqa: E501
              "    <SourceFiles>", *[f"      <File name={quoteattr(s)}/>" for s in sources],
              "    </SourceFiles>", "  </CoSimulation>"]
    else:
        cs = [f"  <CoSimulation{_attrs(modelIdentifier=prefix, canBeInstantiatedOnlyOncePerProcess='false', canGetAndSetFMUState='true', canSerializeFMUState='true', providesDirectionalDerivatives='false', providesAdjointDerivatives='false', canHandleVariableCommunicationStepSize='true', fixedInternalStepSize=_number(variables.sample_period), maxOutputDerivativeOrder=0, providesIntermediateUpdate='false', mightReturnEarlyFromDoStep='false', canReturnEarlyAfterIntermediateUpdate='false', hasEventMode='false', providesEvaluateDiscreteStates='false')}/>"]  # noqa: E501
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', f"<fmiModelDescription{head}>", *cs,
             *_units(variables), *_common_head(fmi),
             f'  <DefaultExperiment startTime="0.0" stepSize="{_number(step_size)}"/>',
             "  <ModelVariables>"]
    index = {}
    for k, v in enumerate(variables.all, start=1):
        index[v.vr] = k
        lines += _variable(fmi, v)
    lines.append("  </ModelVariables>")
    outputs = [variables.command, *variables.counters]
    lines.append("  <ModelStructure>")
    if fmi == 2:
        lines += ["    <Outputs>", *[f'      <Unknown index="{index[v.vr]}" dependencies=""/>'
                                     for v in outputs], "    </Outputs>"]
    else:
        lines += [f'    <Output valueReference="{v.vr}" dependencies=""/>' for v in outputs]
    lines += ["  </ModelStructure>", "</fmiModelDescription>", ""]
    return "\n".join(lines)


def _variable(fmi: int, v: Variable) -> list[str]:
    common = dict(name=v.name, valueReference=v.vr, description=v.description,
                  causality=v.causality, variability=v.variability, initial=_initial(v))
    start = None if v.start is None else (
        str(int(v.start)) if v.kind == "count" else _number(v.start))
    if fmi == 2:
        kind = "Real" if v.kind == "real" else "Integer"
        inner = _attrs(start=start, unit=v.unit if v.kind == "real" else None)
        return [f"    <ScalarVariable{_attrs(**common)}>", f"      <{kind}{inner}/>",
                "    </ScalarVariable>"]
    kind = "Float64" if v.kind == "real" else "Int64"
    return [f"    <{kind}{_attrs(**common, start=start, unit=v.unit if v.kind == 'real' else None)}/>"]  # noqa: E501


def build_description(prefix: str, sources: list[str]) -> str:
    """FMI 3's ``sources/buildDescription.xml``: the sources, C99."""
    return "\n".join([
        '<?xml version="1.0" encoding="UTF-8"?>', '<fmiBuildDescription fmiVersion="3.0">',
        f"  <BuildConfiguration modelIdentifier={quoteattr(prefix)}>",
        '    <SourceFileSet language="C99">',
        *[f"      <SourceFile name={quoteattr(s)}/>" for s in sources],
        "    </SourceFileSet>", "  </BuildConfiguration>", "</fmiBuildDescription>", ""])
