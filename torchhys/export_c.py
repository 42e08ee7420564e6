"""Export a compensator as dependency-free C99, generated from its exported step.

:func:`to_c` builds the :class:`~torchhys.streaming.StreamingCompensator` of a model, exports
its explicit-state step with ``torch.export`` at batch 1 (static shapes) and writes C from the
graph, one small template per aten operation (:mod:`torchhys._c_templates`): every tensor a
fixed-size array, parameters and buffers ``static const`` arrays, the state a struct the
caller owns. No operator has C of its own: a new operator whose step exports with
``torch.export`` gets C without new code, or :func:`to_c` names the operation without a
template and the step it came from.

The generated ``PREFIX.h`` declares (C99; the files include only ``<math.h>``,
``<stdint.h>`` and ``<string.h>``; no dynamic allocation, no global mutable state, no
recursion)::

    typedef double PREFIX_real;                      (float with dtype=torch.float32)
    typedef struct { ... } PREFIX_state;              (the caller's: stack, static, PLC)
    void PREFIX_init(PREFIX_state *s);                 (fresh state, as reset())
    PREFIX_real PREFIX_step(PREFIX_state *s, PREFIX_real x);
    int64_t PREFIX_nonfinite_count(const PREFIX_state *s);
    int64_t PREFIX_out_of_range_count(const PREFIX_state *s);
    PREFIX_LOW, PREFIX_HIGH                            (the command's saturation)
    PREFIX_STATE_BYTES                                 (sizeof(PREFIX_state))

and a comment with the model, its training range, the torchhys version and the export
options. The step is the TorchScript and AOTI files' step: saturation, a NaN or inf sample
held and counted, the input clamp and the direction guard. Compile it without
``-ffast-math`` (the step tests ``x - x`` for non-finite samples); with ``-ffp-contract=off``
(the default of ``-std=c99``) float64 results equal the TorchScript file's to about 1e-15.
"""

from __future__ import annotations

import copy
import math
import os
import re
from pathlib import Path
from typing import Any

import torch
from torch import fx, nn
from torch.export.graph_signature import InputKind

from torchhys._c_templates import SHAPE_ONLY, TEMPLATES
from torchhys._c_templates import copy as copy_to_local
from torchhys._c_writer import CTensor, Writer, constant, contiguous_strides
from torchhys.export import _compensator, _ExplicitStep, metadata
from torchhys.streaming import STATE_F, STATE_F64, STATE_I, STATE_STARTED, StreamingCompensator

__all__ = ["DEFAULT_PREFIX", "check_prefix", "to_c"]

#: the state tensors' struct members (torchhys.streaming's F, I, started, F64; not I: a macro of
#: <complex.h>)
_MEMBERS = {STATE_F: "F", STATE_I: "I64", STATE_STARTED: "started", STATE_F64: "F64"}
_C_KEYWORDS = frozenset(
    "auto break case char const continue default do double else enum extern float for goto "
    "if inline int long register restrict return short signed sizeof static struct switch "
    "typedef union unsigned void volatile while _Bool _Complex _Imaginary".split())


DEFAULT_PREFIX = "torchhys_comp"


def check_prefix(prefix: object) -> str:
    """``prefix`` if it is a C identifier fit for the generated names, else ValueError."""
    if not (isinstance(prefix, str) and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", prefix)
            and prefix not in _C_KEYWORDS and not prefix.startswith("__")):
        raise ValueError(f"prefix must be a C identifier (letters, digits, '_', not starting "
                         f"with a digit or '__', not a keyword), got {prefix!r}")
    return prefix


def _check_out_dir(out_dir: object) -> Path:
    if not isinstance(out_dir, (str, os.PathLike)):
        raise TypeError(f"out_dir must be a str or os.PathLike, got {type(out_dir).__name__}")
    path = Path(out_dir)
    if not path.is_dir():
        raise ValueError(f"out_dir {os.fspath(out_dir)!r} is not an existing folder")
    return path


def _build(model: nn.Module, dtype: torch.dtype, limits: Any, initial_command: float,
           options: dict[str, Any]) -> StreamingCompensator:
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    if isinstance(model, StreamingCompensator):
        if model.low.dtype != dtype:
            raise ValueError(f"dtype {dtype} differs from the StreamingCompensator's "
                             f"{model.low.dtype}: pass the model instead")
    elif any(t.is_floating_point() and t.dtype != dtype
             for t in (*model.parameters(), *model.buffers())):
        model = copy.deepcopy(model).to(dtype)
    return _compensator(model, limits, initial_command, options).eval()


def to_c(
    model: nn.Module, out_dir: str | os.PathLike, *, prefix: str = DEFAULT_PREFIX,
    dtype: torch.dtype = torch.float64, limits: tuple[float, float] | None = None,
    initial_command: float = 0.0, input_range: tuple[float, float] | None = None,
    input_margin: float | None = 0.05, direction: str = "auto",
) -> tuple[Path, Path]:
    """Write the compensator of ``model`` as C99: ``out_dir/PREFIX.h`` and ``PREFIX.c``.

    Args:
        model: an :class:`~torchhys.InverseHysteresisNet` with causal operators, a
            :class:`~torchhys.PrandtlIshlinskiiInverse`, any model with streaming steps, or a
            built :class:`~torchhys.streaming.StreamingCompensator` (then in ``dtype``).
        out_dir: an existing folder.
        prefix: the C prefix of every name (a C identifier).
        dtype: ``torch.float64`` or ``torch.float32``: the C step's real type (a model in
            another dtype is copied and converted, as ``model.to(dtype)``).
        limits, initial_command, input_range, input_margin, direction: as
            :func:`torchhys.export.to_torchscript`.

    Returns:
        ``(header_path, source_path)``.

    Raises:
        ValueError: a bad ``prefix``, ``dtype`` or ``out_dir``; an operation in the step
            without a C template (the message names it and the step it came from); see
            :class:`~torchhys.streaming.StreamingCompensator` for the other options.
        TypeError: see :class:`~torchhys.streaming.StreamingCompensator`.
    """
    prefix, folder = check_prefix(prefix), _check_out_dir(out_dir)
    comp = _build(model, dtype, limits, initial_command,
                  {"input_range": input_range, "input_margin": input_margin,
                   "direction": direction})
    state = comp.initial_state(1)
    with torch.no_grad():
        ep = torch.export.export(_ExplicitStep(comp), (torch.zeros(1, dtype=dtype), *state),
                                 strict=False)
    members = [_MEMBERS.get(k, f"s{k}") for k in range(len(state))]
    w = Writer(prefix)
    u, outputs = _translate(ep, w, members)
    options = {"dtype": str(dtype).replace("torch.", ""), "limits": limits,
               "initial_command": initial_command, "input_range": input_range,
               "input_margin": input_margin, "direction": direction}
    fields, n_bytes = _struct(w, state, members)
    header = _header(prefix, model, comp, options, fields, n_bytes)
    source = _source(prefix, w, comp, members, u, outputs)
    h_path, c_path = folder / f"{prefix}.h", folder / f"{prefix}.c"
    h_path.write_text(header)
    c_path.write_text(source)
    return h_path, c_path


# --- the graph ------------------------------------------------------------------------------


def _spec(val: Any) -> Any:
    if isinstance(val, torch.Tensor):
        return CTensor(val.dtype, tuple(val.shape), contiguous_strides(val.shape))
    if isinstance(val, (list, tuple)):
        return [_spec(v) for v in val]
    return None


def _origin(node: fx.Node) -> str:
    """The module (operator step) and source line a node came from."""
    parts = []
    stack = node.meta.get("nn_module_stack") or {}
    if stack:
        path, cls = list(stack.values())[-1]
        cls = cls if isinstance(cls, str) else getattr(cls, "__qualname__", str(cls))
        parts.append(f"{path} ({cls})" if path else
                     "the compensator's own step (torchhys.streaming.StreamingCompensator)")
    frames = re.findall(r'File "([^"]+)", line (\d+), in (\w+)', node.meta.get("stack_trace")
                        or "")
    if frames:
        file, line, fn = frames[-1]
        parts.append(f"at {Path(file).name}:{line} in {fn}")
    return " ".join(parts) or "an unknown place"


def _fold(node: fx.Node, args: Any, kwargs: Any) -> Any:
    """Compute a node whose tensors are all known (or whose value depends on shapes only)."""
    shape_only = node.target in SHAPE_ONLY

    def real(x: Any) -> Any:
        if isinstance(x, CTensor):
            return torch.zeros(x.shape, dtype=x.dtype) if shape_only else x.value
        return x

    a, k = fx.node.map_aggregate((args, kwargs), real)
    out = node.target(*a, **k)
    if isinstance(out, torch.Tensor):
        return constant(torch.zeros_like(out) if "empty" in str(node.target) else out)
    return [constant(t) for t in out]


def _is_known(value: Any) -> bool:
    known = True

    def visit(x: Any) -> Any:
        nonlocal known
        if isinstance(x, CTensor) and x.value is None:
            known = False
        return x

    fx.node.map_aggregate(value, visit)
    return known


def _live(graph: fx.Graph) -> set[fx.Node]:
    out = next(n for n in graph.nodes if n.op == "output")
    live, todo = set(), [out]
    while todo:
        n = todo.pop()
        if n not in live:
            live.add(n)
            todo.extend(n.all_input_nodes)
    return live


def _translate(ep: torch.export.ExportedProgram, w: Writer, members: list[str]
               ) -> tuple[CTensor, list[CTensor]]:
    """Write the step's statements into ``w``: returns the command's and the new state's
    tensors."""
    sig = ep.graph_signature
    known = {}
    for spec in sig.input_specs:
        if spec.kind in (InputKind.PARAMETER, InputKind.BUFFER, InputKind.CONSTANT_TENSOR):
            src = ep.state_dict if spec.target in ep.state_dict else ep.constants
            known[spec.arg.name] = src[spec.target]
    users = list(sig.user_inputs)
    env: dict[fx.Node, Any] = {}
    missing: dict[str, str] = {}
    live = _live(ep.graph)
    for node in ep.graph.nodes:
        if node not in live:
            continue
        if node.op == "placeholder":
            if node.name in known:
                env[node] = constant(known[node.name])
            else:
                k = users.index(node.name)
                val = node.meta["val"]
                base = "x" if k == 0 else f"s->{members[k - 1]}"
                env[node] = CTensor(val.dtype, tuple(val.shape),
                                    contiguous_strides(val.shape), base)
        elif node.op == "call_function":
            w.node += 1
            env[node] = _emit(w, node, env, missing)
        elif node.op == "output":
            outs = [env[a] for a in node.args[0]]
    if missing:
        raise ValueError("to_c: no C template for " + "; ".join(
            f"{op} (from {where})" for op, where in missing.items())
            + " (templates: torchhys._c_templates.TEMPLATES)")
    return outs[0], outs[1:]


def _emit(w: Writer, node: fx.Node, env: dict, missing: dict[str, str]) -> Any:
    args, kwargs = fx.node.map_arg((node.args, node.kwargs), lambda n: env[n])
    spec = _spec(node.meta.get("val"))
    if node.target in SHAPE_ONLY or (_is_known((args, kwargs))
                                     and isinstance(spec, (CTensor, list))):
        return _fold(node, args, kwargs)
    emit = TEMPLATES.get(node.target)
    if emit is not None:
        start = len(w.lines)
        try:
            out = emit(w, spec, *args, **kwargs)
        except ValueError as e:
            missing.setdefault(f"{node.target} ({e})", _origin(node))
        else:
            if isinstance(spec, CTensor) and tuple(out.shape) != spec.shape:
                raise RuntimeError(f"to_c: the template of {node.target} gave shape "
                                   f"{out.shape}, torch {spec.shape} (node {node.name})")
            if len(w.lines) > start:
                w.lines.insert(start, f"    /* {node.name}: {node.target} */")
            return out
    else:
        missing.setdefault(str(node.target), _origin(node))
    return spec  # a stand-in, so that every missing operation is named at once


# --- the files ------------------------------------------------------------------------------


def _struct(w: Writer, state: list[torch.Tensor], members: list[str]
            ) -> tuple[list[str], int]:
    """The state struct's fields (widest first: no padding inside) and its size in bytes
    (a multiple of 8)."""
    rows = [(t.element_size(), m, w.ctype(t.dtype), max(t.numel(), 1))
            for t, m in zip(state, members, strict=True)]
    rows.sort(key=lambda r: -r[0])
    fields = [f"{'REAL' if m == 'F' else c} {m}[{n}];" for _, m, c, n in rows]
    n_bytes = sum(size * n for size, _, _, n in rows)
    if n_bytes % 8:
        fields.append(f"uint8_t pad_[{8 - n_bytes % 8}];")
        n_bytes += 8 - n_bytes % 8
    return fields, n_bytes


def _describe(model: nn.Module) -> list[str]:
    if isinstance(model, StreamingCompensator):
        steps = ", ".join(type(s.step).__name__ for s in model.slots)
        return [f"a StreamingCompensator of the steps [{steps}]"]
    text = type(model).__name__
    ops = getattr(model, "operators", None)
    if isinstance(ops, nn.ModuleList):
        text += ": operators [" + ", ".join(type(op).__name__ for op in ops) + "]"
    hidden, act = getattr(model, "hidden", None), getattr(model, "activation", None)
    if isinstance(hidden, nn.Linear):
        text += f", hidden {hidden.out_features}, {type(act).__name__.lower()}"
    lines = [text]
    rng = [getattr(model, k, None) for k in ("in_min", "in_max", "out_min", "out_max")]
    if all(isinstance(v, torch.Tensor) and math.isfinite(float(v)) for v in rng):
        a, b, c, d = (float(v) for v in rng)
        lines.append(f"training range: input [{a:.9g}, {b:.9g}], output [{c:.9g}, {d:.9g}]")
    return lines


def _header(prefix: str, model: nn.Module, comp: StreamingCompensator, options: dict,
            fields: list[str], n_bytes: int) -> str:
    import torchhys

    real = Writer.ctype(comp.low.dtype)
    guard = {1: "increasing", -1: "decreasing", 0: "none"}[int(comp.direction)]
    clamp = (f"[{float(comp.in_low)!r}, {float(comp.in_high)!r}]" if comp.clamp_input
             else "none")
    opts = ", ".join(f"{k}={v!r}" for k, v in options.items())
    layout = [f" *   {m}[{col}:{col + n}]  {name}" for k, _, name, col, n in comp.layout()
              for m in [_MEMBERS.get(k, f"s{k}")]]
    g = prefix.upper() + "_H"
    lines = [
        f"/* {prefix}.h: a torchhys compensator as dependency-free C99.",
        f" * Generated by torchhys {torchhys.__version__} (torchhys.export_c.to_c): do not "
        "edit.",
        " *",
        *[f" * model: {t}" for t in _describe(model)],
        f" * export options: {opts}",
        f" * command limits [{float(comp.low)!r}, {float(comp.high)!r}], input clamp {clamp}, "
        f"direction guard {guard}",
        " *",
        f" * Use: {prefix}_state s; {prefix}_init(&s); then u = {prefix}_step(&s, x) once a "
        "sample.",
        " * x is the desired output in physical units, u the saturated command. A NaN or inf "
        "sample",
        " * holds the last command (the initial command before the first finite sample) and is",
        " * counted; a finite sample outside the training input range (widened by the margin) "
        "is",
        " * clamped and counted. Compile without -ffast-math.",
        " *",
        " * State layout (torchhys.streaming; batch 1):",
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
        "",
        "typedef struct {",
        *[f"    {f.replace('REAL', prefix + '_real')}" for f in fields],
        f"}} {prefix}_state;",
        "",
        f"void {prefix}_init({prefix}_state *s);",
        f"{prefix}_real {prefix}_step({prefix}_state *s, {prefix}_real x);",
        f"int64_t {prefix}_nonfinite_count(const {prefix}_state *s);",
        f"int64_t {prefix}_out_of_range_count(const {prefix}_state *s);",
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
    lines = [
        f"/* {prefix}.c: generated by torchhys (torchhys.export_c.to_c); see {prefix}.h. */",
        f'#include "{prefix}.h"',
        "",
        "#include <math.h>",
        "#include <stdint.h>",
        "#include <string.h>",
        "",
        f"typedef char {prefix}_state_bytes_check[(sizeof({prefix}_state) == "
        f"{prefix}_STATE_BYTES) ? 1 : -1];",
        "",
        *[h + "\n" for h in w.helpers.values()],
        *w.constants,
        "",
        f"void {prefix}_init({prefix}_state *s)",
        "{",
        "    memset(s, 0, sizeof *s);",
        "}",
        "",
        f"{real} {prefix}_step({prefix}_state *s, {real} x)",
        "{",
        *[f"    {d}" for d in decls],
        f"    {real} u;",
        *body,
        "    return u;",
        "}",
        "",
        f"int64_t {prefix}_nonfinite_count(const {prefix}_state *s)",
        "{",
        f"    return s->{members[STATE_I]}[{counter}];",
        "}",
        "",
        f"int64_t {prefix}_out_of_range_count(const {prefix}_state *s)",
        "{",
        f"    return s->{members[STATE_I]}[{oor.split(':')[1]}];" if oor else
        "    (void)s;\n    return 0;",
        "}",
        "",
    ]
    return "\n".join(lines)
