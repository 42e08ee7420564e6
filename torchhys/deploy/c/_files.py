"""The two files of :func:`torchhys.deploy.c.to_c`: ``PREFIX.h`` (the contract, the state
struct, a comment with the model and the options) and ``PREFIX.c`` (helpers, constants, the
step written by :mod:`torchhys.deploy.c._templates`, init and the counters)."""

from __future__ import annotations

import math
import textwrap
from typing import Any

import torch
from torch import nn

import torchhys.deploy.c._adaptive as _adaptive
from torchhys._version import __version__
from torchhys.deploy.adaptive import AdaptiveCompensator
from torchhys.deploy.c._views import copy as copy_to_local
from torchhys.deploy.c._writer import CTensor, Writer
from torchhys.deploy.export import metadata
from torchhys.deploy.ranges import default_condition_ranges
from torchhys.deploy.streaming import (
    STATE_F,
    STATE_F64,
    STATE_I,
    STATE_STARTED,
    StreamingCompensator,
)

#: why the source refuses to compile under -ffast-math / -Ofast (its #error)
FAST_MATH_ERROR = ("compile without -ffast-math or -Ofast: the generated step relies on IEEE "
                   "arithmetic (NaN, signed zeros and the rounding of each operation, as the "
                   "exported model computes them)")
#: the source's check (GCC and Clang define __FAST_MATH__ under -ffast-math and -Ofast)
FAST_MATH_CHECK = ["#if defined(__FAST_MATH__)", f'#error "{FAST_MATH_ERROR}"', "#endif"]

#: the state tensors' struct members (torchhys.deploy.streaming's F, I, started, F64; not I: a macro
#: of <complex.h>)
MEMBERS = {STATE_F: "F", STATE_I: "I64", STATE_STARTED: "started", STATE_F64: "F64"}


def state_members(comp: StreamingCompensator, n: int) -> list[str]:
    """The C struct's member names of the ``n`` state tensors."""
    if isinstance(comp, AdaptiveCompensator):
        return _adaptive.members(comp)
    return [MEMBERS.get(k, f"s{k}") for k in range(n)]


def files(prefix: str, w: Writer, model: nn.Module, comp: StreamingCompensator,
          state: list[torch.Tensor], u: CTensor, outputs: list[CTensor], options: dict[str, Any]
          ) -> tuple[str, str]:
    """The header's and the source's text, from the step written into ``w`` (``u``: the
    command, ``outputs``: the new state); an adaptive compensator's step is
    ``PREFIX_step_adapt`` (:mod:`torchhys.deploy.c._adaptive`)."""
    members = state_members(comp, len(state))
    fields, n_bytes = _struct(w, state, members)
    header = _header(prefix, model, comp, options, fields, n_bytes)
    return header, _source(prefix, w, comp, members, u, outputs)


def _condition_macros(prefix: str, model: nn.Module, comp: StreamingCompensator) -> list[str]:
    """``PREFIX_N_CONDITIONS`` and the conditions' ranges, for a conditioned model: the
    training ranges (``PREFIX_CONDITION_RANGES``, as the model recorded them) and the clamp's
    bounds (``PREFIX_CONDITION_CLAMP``: widened by the margin), each an initializer of
    ``PREFIX_real [PREFIX_N_CONDITIONS][2]``."""
    n = comp.n_conditions
    if n == 0:
        return []
    real, lit = Writer.ctype(comp.low.dtype), Writer(prefix).literal

    def pairs(lo: list[float], hi: list[float]) -> str:
        return "{" + ", ".join(f"{{{lit(a, comp.low.dtype)}, {lit(b, comp.low.dtype)}}}"
                               for a, b in zip(lo, hi, strict=True)) + "}"

    ranges = default_condition_ranges(model, n)
    lines = ["", f"/* the {n} condition(s) of {prefix}_step, in the order of its conditions "
             f"array: ({real} [{prefix}_N_CONDITIONS][2] initializers) */",
             f"#define {prefix}_N_CONDITIONS {n}"]
    if ranges is not None:
        lines.append(f"#define {prefix}_CONDITION_RANGES "
                     + pairs([a for a, _ in ranges], [b for _, b in ranges]))
    if comp.clamp_conditions:
        lines.append(f"#define {prefix}_CONDITION_CLAMP "
                     + pairs(comp.cond_low.tolist(), comp.cond_high.tolist()))
    return lines


def _struct(w: Writer, state: list[torch.Tensor], members: list[str]
            ) -> tuple[list[str], int]:
    """The state struct's fields (widest first: no padding inside) and its size in bytes
    (a multiple of 8)."""
    rows = [(t.element_size(), m, w.ctype(t.dtype), max(t.numel(), 1))
            for t, m in zip(state, members, strict=True)]
    rows.sort(key=lambda r: -r[0])
    fields = [f"{'REAL' if m in _adaptive.REAL_MEMBERS else c} {m}[{n}];"
              for _, m, c, n in rows]
    n_bytes = sum(size * n for size, _, _, n in rows)
    if n_bytes % 8:
        fields.append(f"uint8_t pad_[{8 - n_bytes % 8}];")
        n_bytes += 8 - n_bytes % 8
    return fields, n_bytes


def _describe(model: nn.Module) -> list[str]:
    """``model: ...`` and, where recorded, ``training range: ...``."""
    if isinstance(model, StreamingCompensator):
        steps = ", ".join(type(s.step).__name__ for s in model.slots)
        return [f"model: a StreamingCompensator of the steps [{steps}]"]
    text = "model: " + type(model).__name__
    ops = getattr(model, "operators", None)
    if isinstance(ops, nn.ModuleList):
        text += ", operators [" + ", ".join(type(op).__name__ for op in ops) + "]"
    hidden, act = getattr(model, "hidden", None), getattr(model, "activation", None)
    if isinstance(hidden, nn.Linear):
        text += f", hidden {hidden.out_features}, {type(act).__name__.lower()}"
    lines = [text]
    rng = [getattr(model, k, None) for k in ("in_min", "in_max", "out_min", "out_max")]
    if all(isinstance(v, torch.Tensor) and math.isfinite(float(v)) for v in rng):
        a, b, c, d = (float(v) for v in rng)
        lines.append(f"training range: input [{a:.9g}, {b:.9g}], target (command) "
                     f"[{c:.9g}, {d:.9g}]")
    return lines


def _comment(paragraphs: list[str]) -> list[str]:
    """Paragraphs as the lines of a C comment (an empty one: a blank comment line)."""
    out = []
    for text in paragraphs:
        out += [" * " + line for line in textwrap.wrap(text, 92, break_on_hyphens=False)] or [
            " *"]
    return out


def _header(prefix: str, model: nn.Module, comp: StreamingCompensator, options: dict,
            fields: list[str], n_bytes: int) -> str:
    real = Writer.ctype(comp.low.dtype)
    guard = {1: "increasing", -1: "decreasing", 0: "none"}[int(comp.direction)]
    clamp = (f"[{float(comp.in_low)!r}, {float(comp.in_high)!r}]" if comp.clamp_input
             else "none")
    opts = ", ".join(f"{k}={v!r}" for k, v in options.items())
    adaptive = isinstance(comp, AdaptiveCompensator)
    layout = [f" *   {m}[{col}:{col + n}]  {name}" for k, _, name, col, n in comp.layout()
              for m in [MEMBERS.get(k, f"s{k}")]]
    if adaptive:
        layout += _adaptive.layout(comp)
    use = [_adaptive.use_text(prefix, comp), ""] if adaptive else []
    step = (_adaptive.signature(prefix, comp) + ";" if adaptive else
            f"{prefix}_real {prefix}_step({prefix}_state *s, {prefix}_real x"
            + (f", const {prefix}_real *conditions);" if comp.n_conditions else ");"))
    g = prefix.upper() + "_H"
    lines = [
        f"/* {prefix}.h: a torchhys compensator as dependency-free C99.",
        *_comment([
            f"Generated by torchhys {__version__} (torchhys.deploy.c.to_c): do not "
            "edit.", "", *_describe(model), f"export options: {opts}",
            f"command limits [{float(comp.low)!r}, {float(comp.high)!r}], input clamp "
            f"{clamp}, direction guard {guard}", "",
            f"Use: {prefix}_state s; {prefix}_init(&s); then u = {prefix}_step"
            + ("_adapt" if adaptive else "") + "(&s, x"
            + (", conditions" if comp.n_conditions else "")
            + (", measured_prev, applied_prev" if adaptive else "") + ") once a "
            "sample. x is the desired output in physical units, u the saturated command"
            + (f" (conditions: the {comp.n_conditions} measured operating condition(s) of "
               "the sample, clamped to their training ranges widened by the margin and "
               "counted as the input is)" if comp.n_conditions else "") + ". A "
            "NaN or inf sample holds the last command (the initial command before the first "
            "finite sample) and is counted; a finite sample outside the training input range "
            "(widened by the margin) is clamped and counted. Compile without -ffast-math or "
            "-Ofast (the source stops with an #error under them).",
            "", *use, "State layout (torchhys.deploy.streaming; batch 1):"]),
        *layout,
        " */",
        f"#ifndef {g}",
        f"#define {g}",
        "",
        "#include <stdint.h>",
        "",
        "#ifdef __cplusplus",
        'extern "C" {',
        "#endif",
        "",
        f"typedef {real} {prefix}_real;",
        "",
        f"#define {prefix}_LOW (({prefix}_real){float(comp.low)!r})",
        f"#define {prefix}_HIGH (({prefix}_real){float(comp.high)!r})",
        f"#define {prefix}_STATE_BYTES {n_bytes}",
        *_condition_macros(prefix, model, comp),
        *(_adaptive.macros(prefix, comp) if adaptive else []),
        "",
        "typedef struct {",
        *[f"    {f.replace('REAL', prefix + '_real')}" for f in fields],
        f"}} {prefix}_state;",
        "",
        f"void {prefix}_init({prefix}_state *s);",
        step,
        f"int64_t {prefix}_nonfinite_count(const {prefix}_state *s);",
        f"int64_t {prefix}_out_of_range_count(const {prefix}_state *s);",
        *(_adaptive.prototypes(prefix) if adaptive else []),
        "",
        "#ifdef __cplusplus",
        "}",
        "#endif",
        "",
        f"#endif /* {g} */",
        "",
    ]
    return "\n".join(lines)


def _whole(t: CTensor, member: str, numel: int) -> bool:
    return (t.base == member and t.offset == 0 and t.is_contiguous() and t.numel == numel)


def _source(prefix: str, w: Writer, comp: StreamingCompensator, members: list[str],
            u: CTensor, outputs: list[CTensor]) -> str:
    # the new state: copied into the struct after every statement has read the old one
    local_sizes = {name: n for name, _, n in w.locals}
    stores = []
    for k, t in enumerate(outputs):
        member = f"s->{members[k]}"
        if _whole(t, member, t.numel):
            continue  # unchanged
        if t.base in w.pointers and _whole(t, t.base, t.numel):  # the old state or a new one
            held = member in w.pointers[t.base]
            stores.append((f"if ({t.base} != {member}) " if held else "")
                          + f"memcpy({member}, {t.base}, sizeof {member});")
            continue
        if not (t.base in local_sizes and _whole(t, t.base, local_sizes[t.base])):
            w.node += 1
            t = copy_to_local(w, t)
        w.keep(t.base)
        stores.append(f"memcpy({member}, {t.base}, sizeof {member});")
    if u.base in local_sizes:
        w.keep(u.base)
    w.emit(f"u = {w.read(u, ['0'] * len(u.shape))};")
    for line in stores:
        w.emit(line)
    meta = metadata(comp)
    counter = int(meta["counter"].split(":")[1])
    oor = meta["out_of_range"]
    decls, body = w.shared_locals()
    real = f"{prefix}_real"
    adaptive = isinstance(comp, AdaptiveCompensator)
    check = "    assert(s != NULL);" if adaptive else None
    if adaptive:
        step = [_adaptive.signature(prefix, comp), "{",
                "    assert(s != NULL" + (" && conditions != NULL);" if comp.n_conditions
                                          else ");"),
                f"    const {real} x = desired;"]
    else:
        step = [f"{real} {prefix}_step({prefix}_state *s, {real} x"
                + (f", const {real} *conditions)" if comp.n_conditions else ")"), "{"]
    lines = [
        f"/* {prefix}.c: generated by torchhys (torchhys.deploy.c.to_c); see {prefix}.h. */",
        f'#include "{prefix}.h"',
        "",
        *(["#include <assert.h>"] if adaptive else []),
        "#include <math.h>",
        "#include <stdint.h>",
        "#include <string.h>",
        "",
        *FAST_MATH_CHECK,
        "",
        f"typedef char {prefix}_state_bytes_check[(sizeof({prefix}_state) == "
        f"{prefix}_STATE_BYTES) ? 1 : -1];",
        "",
        *[h + "\n" for h in w.helpers.values()],
        *w.constants,
        "",
        f"void {prefix}_init({prefix}_state *s)",
        "{",
        *([check] if check else []),
        "    memset(s, 0, sizeof *s);",
        "}",
        "",
        *step,
        *[f"    {d}" for d in decls],
        f"    {real} u;",
        *body,
        "    return u;",
        "}",
        "",
        f"int64_t {prefix}_nonfinite_count(const {prefix}_state *s)",
        "{",
        *([check] if check else []),
        f"    return s->{members[STATE_I]}[{counter}];",
        "}",
        "",
        f"int64_t {prefix}_out_of_range_count(const {prefix}_state *s)",
        "{",
        *([check] if check else []),
        f"    return s->{members[STATE_I]}[{oor.split(':')[1]}];" if oor else
        "    (void)s;\n    return 0;",
        "}",
        "",
        *(_adaptive.functions(prefix, w, comp) if adaptive else []),
    ]
    return "\n".join(lines)
