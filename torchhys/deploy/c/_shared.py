"""One C step shared by many devices: the step of :func:`torchhys.deploy.c.to_c` written
with every constant tensor read from a ``const PREFIX_params *p`` instead of a ``static
const`` array, and the tables of ``PREFIX_params`` one device each.

The step of each device is written by the same generator as :func:`~torchhys.deploy.c.to_c`
(:class:`ParamsWriter` differs from its writer only in where a constant is read). The
devices share one step when these texts are equal: the same statements, loops and literals
(a Python number of the traced step, such as a layer norm's ``eps``, is a literal of the
code), the same state struct and the same fields (name, C type, size). A constant tensor is
a field, whatever it holds: weights and biases, the input normalisation, the command's
saturation, the input clamp's bounds, the direction guard's sign and the tables folded from
them; a field equal in every device (bit for bit) is written once into the shared step as
a ``static const`` array (``PREFIX_c<i>``), the others are the fields of ``PREFIX_params``
(``k<i>``), one initializer a device in ``PREFIX_params.c``. Where the texts differ (other
sizes, other operators, or code the generator chose from a constant's values, such as the
sparse running sum of a Preisach table) :func:`shared_files` raises :class:`NotShared` with
the first difference.

::

    PREFIX.h          PREFIX_real, PREFIX_state, PREFIX_params, PREFIX_N_DEVICES,
                      PREFIX_DEVICE_<device> (its index), the prototypes
    PREFIX.c          PREFIX_init, PREFIX_step(s, p, x), the two counters
    PREFIX_params.c   const PREFIX_params PREFIX_params_table[PREFIX_N_DEVICES],
                      const char *const PREFIX_device_names[PREFIX_N_DEVICES]
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._version import __version__
from torchhys.deploy.adaptive import AdaptiveCompensator
from torchhys.deploy.c._files import _source, _struct, state_members
from torchhys.deploy.c._graph import translate
from torchhys.deploy.c._to_c import _build
from torchhys.deploy.c._writer import CTensor, Writer, _index
from torchhys.deploy.export import _ExplicitStep


class NotShared(ValueError):
    """The devices' steps differ in more than their constants' values (the message says
    where): they cannot share one step."""


class ParamsWriter(Writer):
    """A :class:`~torchhys.deploy.c._writer.Writer` whose constant tensors are the fields
    ``p->k<i>`` of the step's ``const PREFIX_params *p`` (in order of first use), read by
    index even where they hold one value (a literal would bake a device's value into the
    shared code)."""

    def __init__(self, prefix: str) -> None:
        super().__init__(prefix)
        self.fields: list[tuple[str, torch.dtype, Tensor]] = []
        self._field_names: dict[int, str] = {}

    def array(self, t: CTensor) -> str:
        if t.value is None:
            return super().array(t)
        key = id(t.value)
        if key not in self._field_names:
            self._field_names[key] = f"k{len(self.fields)}"
            self._pinned.append(t.value)
            self.fields.append((self._field_names[key], t.dtype, t.value.reshape(-1)))
        return f"p->{self._field_names[key]}"

    def read(self, t: CTensor, idx: Sequence[str]) -> str:
        if t.element is None and t.value is not None:
            return f"{self.array(t)}[{_index(t.offset, idx, t.strides)}]"
        return super().read(t, idx)


@dataclass
class DeviceStep:
    """One device's step written by :class:`ParamsWriter`: the source's text, the state
    struct's fields and size, the constant fields ``(name, dtype, values)``, the command's
    saturation and the number of conditions."""

    source: str
    state_fields: list[str]
    state_bytes: int
    fields: list[tuple[str, torch.dtype, Tensor]]
    low: float
    high: float
    dtype: torch.dtype
    n_conditions: int


def device_step(model: nn.Module, prefix: str, dtype: torch.dtype,
                options: Mapping[str, Any]) -> DeviceStep:
    """The step of ``model``'s compensator (``options``: ``limits``, ``initial_command``,
    ``input_range``, ``input_margin``, ``direction``, as :func:`~torchhys.deploy.c.to_c`)
    with its constants as fields of ``PREFIX_params``."""
    opts = dict(options)
    limits, initial = opts.pop("limits", None), opts.pop("initial_command", 0.0)
    comp = _build(model, dtype, limits, initial, opts)
    if isinstance(comp, AdaptiveCompensator):
        raise ValueError("adapt: a shared fleet step is static (adapt='none')")
    state, inputs = comp.initial_state(1), comp.example_inputs(1)
    with torch.no_grad():
        ep = torch.export.export(_ExplicitStep(comp),
                                 (torch.zeros(1, dtype=dtype), *(t for _, t in inputs),
                                  *state), strict=False)
    w = ParamsWriter(prefix)
    members = state_members(comp, len(state))
    u, outputs = translate(ep, w, members, inputs=[name for name, _ in inputs])
    fields, n_bytes = _struct(w, state, members)
    source = _source(prefix, w, comp, members, u, outputs)
    return DeviceStep(source, fields, n_bytes, w.fields, float(comp.low), float(comp.high),
                      dtype, comp.n_conditions)


def c_identifier(name: str) -> str:
    """``name`` as a C identifier's tail: characters other than letters, digits and ``_``
    as ``_``, a leading digit after a ``d``."""
    text = re.sub(r"[^A-Za-z0-9_]", "_", name) or "_"
    return "d" + text if text[0].isdigit() else text


def _first_difference(a: str, b: str) -> str:
    for k, (x, y) in enumerate(zip(a.splitlines(), b.splitlines(), strict=False)):
        if x != y:
            return f"line {k + 1} of the step: {x.strip()[:60]!r} against {y.strip()[:60]!r}"
    return "the step's length"


def _check_same(steps: Mapping[str, DeviceStep]) -> None:
    names = list(steps)
    first = steps[names[0]]
    for name in names[1:]:
        s = steps[name]
        where = None
        if s.dtype != first.dtype:
            where = f"dtype {s.dtype} against {first.dtype}"
        elif s.state_fields != first.state_fields:
            where = "the state struct"
        elif [(f, d, v.numel()) for f, d, v in s.fields] != [
                (f, d, v.numel()) for f, d, v in first.fields]:
            where = "the constants' number, types or sizes"
        elif s.source != first.source:
            where = _first_difference(s.source, first.source)
        if where is not None:
            raise NotShared(f"device {name!r} differs from {names[0]!r} in {where}")


def _equal(tensors: list[Tensor]) -> bool:
    raw = [t.detach().cpu().contiguous().numpy().tobytes() for t in tensors]
    return all(r == raw[0] for r in raw[1:])


def _values(w: Writer, t: Tensor, dtype: torch.dtype) -> str:
    values = [w.literal(v, dtype) for v in t.tolist()] or [w.literal(0, dtype)]
    rows = [", ".join(values[i:i + 4]) for i in range(0, len(values), 4)]
    return ",\n        ".join(rows)


def _c_string(text: str) -> str:
    out = []
    for b in text.encode():
        ch = chr(b)
        out.append(ch if 32 <= b < 127 and ch not in '"\\?' else f"\\{b:03o}")
    return '"' + "".join(out) + '"'


def shared_files(prefix: str, steps: Mapping[str, DeviceStep]) -> tuple[str, str, str]:
    """The texts of ``PREFIX.h``, ``PREFIX.c`` and ``PREFIX_params.c`` of one step shared
    by the devices of ``steps`` (name -> :func:`device_step`, in the tables' order).

    Raises:
        NotShared: the steps differ in more than their constants' values.
        ValueError: two devices of one C name (:func:`c_identifier`).
    """
    names = list(steps)
    if not names:
        raise ValueError("steps: no device")
    ids = [c_identifier(n) for n in names]
    for k, i in enumerate(ids):
        if i in ids[:k]:
            raise ValueError(f"devices {names[ids.index(i)]!r} and {names[k]!r} have one C "
                             f"name {i!r}: rename one")
    _check_same(steps)
    first = steps[names[0]]
    w = Writer(prefix)
    common, varying, rename = [], [], {}
    for k, (field, dtype, value) in enumerate(first.fields):
        if _equal([steps[n].fields[k][2] for n in names]):
            rename[field] = f"{prefix}_c{len(common)}"
            common.append(f"static const {w.ctype(dtype)} {rename[field]}[{max(value.numel(), 1)}]"
                          f" = {{\n        {_values(w, value, dtype)}\n}};")
        else:
            rename[field] = f"p->k{len(varying)}"
            varying.append(k)
    source = re.sub(r"\bp->(k\d+)\b", lambda m: rename[m.group(1)], first.source)
    real = f"{prefix}_real"
    old = f"{real} {prefix}_step({prefix}_state *s, {real} x"
    new = f"{real} {prefix}_step({prefix}_state *s, const {prefix}_params *p, {real} x"
    if source.count("\n" + old) != 1:
        raise RuntimeError(f"shared_files: the step's signature {old!r} not found once")
    source = source.replace("\n" + old, "\n" + new)
    init = f"\nvoid {prefix}_init({prefix}_state *s)"
    source = source.replace(init, "\n" + "\n".join(common) + ("\n" if common else "") + init)
    if "p->" not in source:  # every constant common: the devices differ in low, high only
        at = source.index("\n{\n", source.index(new)) + 3
        source = source[:at] + "    (void)p;\n" + source[at:]
    header = _header(prefix, names, ids, first, varying)
    source = source.replace(f"see {prefix}.h.", f"see {prefix}.h (a fleet's shared step).", 1)
    return header, source, _params(prefix, names, steps, varying)


def _fleet_fields(prefix: str, first: DeviceStep, varying: list[int]) -> list[str]:
    w = Writer(prefix)
    rows = [f"    {prefix}_real low;   /* the command's saturation */",
            f"    {prefix}_real high;"]
    for j, k in enumerate(varying):
        _, dtype, value = first.fields[k]
        rows.append(f"    {w.ctype(dtype)} k{j}[{max(value.numel(), 1)}];")
    return rows


def _header(prefix: str, names: list[str], ids: list[str], first: DeviceStep,
            varying: list[int]) -> str:
    real, g = Writer.ctype(first.dtype), prefix.upper() + "_H"
    step = (f"{prefix}_real {prefix}_step({prefix}_state *s, const {prefix}_params *p, "
            f"{prefix}_real x" + (f", const {prefix}_real *conditions);"
                                  if first.n_conditions else ");"))
    shown = ", ".join(names[:8]) + (f", ... ({len(names)} in all)" if len(names) > 8 else "")
    return "\n".join([
        f"/* {prefix}.h: one torchhys compensator step shared by a fleet of {len(names)} "
        "devices, as dependency-free C99.",
        f" * Generated by torchhys {__version__} (torchhys.deploy.export_fleet): do not edit.",
        f" * Devices: {shown.replace('*/', '* /')}.",
        f" * Use: {prefix}_state s; {prefix}_init(&s); then u = {prefix}_step(&s, "
        f"&{prefix}_params_table[{prefix}_DEVICE_<device>], x"
        + (", conditions" if first.n_conditions else "") + ") once a sample,",
        f" * one state a device; {prefix}_params.c holds each device's {prefix}_params (its "
        "weights and every",
        " * other constant that differs between the devices). Compile without -ffast-math.",
        " */",
        f"#ifndef {g}", f"#define {g}", "", "#include <stdint.h>", "",
        "#ifdef __cplusplus", 'extern "C" {', "#endif", "",
        f"typedef {real} {prefix}_real;", "",
        f"#define {prefix}_N_DEVICES {len(names)}",
        f"#define {prefix}_STATE_BYTES {first.state_bytes}",
        *(f"#define {prefix}_N_CONDITIONS {first.n_conditions}"
          for _ in range(bool(first.n_conditions))),
        *[f"#define {prefix}_DEVICE_{i} {k}" for k, i in enumerate(ids)], "",
        "typedef struct {", *[f"    {f.replace('REAL', prefix + '_real')}"
                              for f in first.state_fields], f"}} {prefix}_state;", "",
        "typedef struct {", *_fleet_fields(prefix, first, varying), f"}} {prefix}_params;", "",
        f"extern const {prefix}_params {prefix}_params_table[{prefix}_N_DEVICES];",
        f"extern const char *const {prefix}_device_names[{prefix}_N_DEVICES];", "",
        f"void {prefix}_init({prefix}_state *s);", step,
        f"int64_t {prefix}_nonfinite_count(const {prefix}_state *s);",
        f"int64_t {prefix}_out_of_range_count(const {prefix}_state *s);", "",
        "#ifdef __cplusplus", "}", "#endif", "", f"#endif /* {g} */", ""])


def _params(prefix: str, names: list[str], steps: Mapping[str, DeviceStep],
            varying: list[int]) -> str:
    w = Writer(prefix)
    rows = []
    for name in names:
        s = steps[name]
        parts = [w.literal(s.low, s.dtype), w.literal(s.high, s.dtype)] + [
            "{\n        " + _values(w, s.fields[k][2], s.fields[k][1]) + "\n    }"
            for k in varying]
        label = name.replace("*/", "* /")
        rows.append(f"    {{ /* {label} */\n    " + ",\n    ".join(parts) + "\n    }")
    return "\n".join([
        f"/* {prefix}_params.c: the {prefix}_params of each device of the fleet, generated by "
        f"torchhys (torchhys.deploy.export_fleet); see {prefix}.h. */",
        f'#include "{prefix}.h"', "",
        f"const {prefix}_params {prefix}_params_table[{prefix}_N_DEVICES] = {{",
        ",\n".join(rows), "};", "",
        f"const char *const {prefix}_device_names[{prefix}_N_DEVICES] = {{",
        "    " + ",\n    ".join(_c_string(n) for n in names), "};", ""])
