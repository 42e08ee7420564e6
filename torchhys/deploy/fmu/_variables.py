"""The FMU's variables (:mod:`torchhys.deploy.fmu`), one table that the model description and
the C wrapper both read: value references, names, causality, variability, start values,
units and descriptions."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from torchhys.deploy.streaming import StreamingCompensator


@dataclass(frozen=True)
class Variable:
    """One scalar variable: ``kind`` ``"real"`` (FMI 2 Real, FMI 3 Float64) or ``"count"``
    (FMI 2 Integer, FMI 3 Int64)."""
    name: str
    vr: int
    kind: str
    causality: str
    variability: str
    start: float | None
    description: str
    unit: str | None = None


@dataclass
class Variables:
    """The table: the inputs (desired, then the conditions, then for an adaptive step the
    last sample's measured response and applied command), the command, the constants and
    the counters (two; five for an adaptive step); value references unique over all types (0
    the desired output, 1 the command, 2.. the other inputs, then the constants, then the
    counters, then time)."""
    inputs: list[Variable]
    command: Variable
    constants: list[Variable]
    counters: list[Variable]
    time: Variable
    sample_period: float
    n_conditions: int = field(default=0)
    adaptive: bool = field(default=False)

    @property
    def all(self) -> list[Variable]:
        """Every variable, in the model description's order (by value reference)."""
        return sorted([*self.inputs, self.command, *self.constants, *self.counters, self.time],
                      key=lambda v: v.vr)


def condition_names(n: int) -> list[str]:
    """The conditions' variable names, in the order of the C step's conditions array."""
    return [f"condition_{k}" for k in range(n)]


def variables(comp: StreamingCompensator, sample_period: float,
              units: Mapping[str, str] | None, adaptive: bool = False) -> Variables:
    """The table of the compensator ``comp`` (``adaptive``: an
    :class:`~torchhys.deploy.adaptive.AdaptiveCompensator`); ``units`` maps variable names
    to units (a name that is not a variable: ValueError)."""
    n = comp.n_conditions
    cond = condition_names(n)
    units = dict(units or {})
    pair = ["measured_prev", "applied_prev"] if adaptive else []
    real_names = ["desired", "command", *cond, *pair]
    known = [*real_names, "command_low", "command_high", "input_low", "input_high"]
    for name, unit in units.items():
        if name not in known:
            raise ValueError(f"units: {name!r} is not a variable of the FMU (those with units: "
                             f"{', '.join(known)})")
        if not isinstance(unit, str) or not unit or any(c.isspace() for c in unit):
            raise ValueError(f"units[{name!r}] must be a unit name without spaces, got {unit!r}")
    lo_c, hi_c = comp.cond_low.tolist(), comp.cond_high.tolist()

    def mid(k: int) -> float:
        a, b = lo_c[k], hi_c[k]
        return (a + b) / 2 if math.isfinite(a) and math.isfinite(b) else 0.0

    inputs = [Variable("desired", 0, "real", "input", "discrete", 0.0,
                       "the desired output, in the training target's units (sampled at "
                       "each sample instant, held over a communication step)",
                       units.get("desired"))]
    inputs += [Variable(name, 2 + k, "real", "input", "discrete", mid(k),
                        f"operating condition {k} (the C step's conditions[{k}])",
                        units.get(name)) for k, name in enumerate(cond)]
    if adaptive:
        inputs += [
            Variable("measured_prev", 2 + n, "real", "input", "discrete", math.nan,
                     "the response measured at the last sample (NaN: no pair, no update); "
                     "used by the first sample of a communication step only", units.get(
                         "measured_prev", units.get("desired"))),
            Variable("applied_prev", 3 + n, "real", "input", "discrete", math.nan,
                     "the command applied at the last sample (NaN: no pair, no update); used "
                     "by the first sample of a communication step only", units.get(
                         "applied_prev", units.get("command")))]
    command = Variable("command", 1, "real", "output", "discrete", float(comp.u0),
                       "the saturated command of the last sample (the initial command "
                       "before the first finite sample)", units.get("command"))
    consts = [("command_low", float(comp.low), "the command's lower saturation"),
              ("command_high", float(comp.high), "the command's upper saturation")]
    if comp.clamp_input and math.isfinite(float(comp.in_low)):
        consts += [("input_low", float(comp.in_low), "the desired output's clamp, low "
                    "(the training range widened by the input margin)"),
                   ("input_high", float(comp.in_high), "the desired output's clamp, high")]
    consts.append(("sample_period", sample_period, "the compensator's sample period (s)"))
    vr = 2 + n + len(pair)
    constants = []
    for name, value, text in consts:
        unit = "s" if name == "sample_period" else units.get(
            name, units.get("command" if name.startswith("command") else "desired"))
        constants.append(Variable(name, vr, "real", "local", "constant", value,
                                  text + " (compiled into the step: a constant)", unit))
        vr += 1
    counters = [
        Variable("nonfinite_count", vr, "count", "output", "discrete", 0,
                 "NaN or inf samples of the desired output held (the last command kept)"),
        Variable("out_of_range_count", vr + 1, "count", "output", "discrete", 0,
                 "finite samples clamped (the desired output or a condition outside its "
                 "clamp)")]
    if adaptive:
        counters += [
            Variable("updates_count", vr + 2, "count", "output", "discrete", 0,
                     "the readout's weight updates applied"),
            Variable("skipped_count", vr + 3, "count", "output", "discrete", 0,
                     "pairs skipped (not finite: no update)"),
            Variable("refused_count", vr + 4, "count", "output", "discrete", 0,
                     "updates refused (they would reverse the direction)")]
    time = Variable("time", vr + len(counters), "real", "independent", "continuous", None,
                    "the simulation time (s): the start time plus the samples run times the "
                    "sample period", "s")
    return Variables(inputs, command, constants, counters, time, sample_period, n, adaptive)
