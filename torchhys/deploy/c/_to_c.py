"""Export a compensator as dependency-free C99, generated from its exported step.

:func:`to_c` builds the :class:`~torchhys.deploy.streaming.StreamingCompensator` of a model, exports
its explicit-state step with ``torch.export`` at batch 1 (static shapes) and writes C from the
graph, one small template per aten operation (:mod:`torchhys.deploy.c._templates`): every tensor a
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
held and counted, the input clamp and the direction guard. The source stops with an
``#error`` where ``__FAST_MATH__`` is defined (``-ffast-math``, ``-Ofast``: GCC, Clang);
its tests of NaN and inf read the numbers' bits and its ``exp`` takes its rounding from
bits too, so that a build that bypasses the check still holds NaN samples
(:mod:`torchhys.deploy.c._finite`). With ``-ffp-contract=off`` (the default of ``-std=c99``)
float64 results equal the TorchScript file's to about 1e-15.
"""

from __future__ import annotations

import copy
import os
import re
from pathlib import Path
from typing import Any

import torch
from torch import fx, nn
from torch.export.graph_signature import InputKind

import torchhys.deploy.c._finite as _finite
from torchhys.deploy.c._files import MEMBERS, files
from torchhys.deploy.c._templates import POINTWISE_OPS, SHAPE_ONLY, TEMPLATES, VIEW_OPS
from torchhys.deploy.c._writer import CTensor, Writer, constant, contiguous_strides
from torchhys.deploy.export import _compensator, _ExplicitStep, write_outputs
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.protocols import check_deployable

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
    if not os.access(path, os.W_OK | os.X_OK):
        raise ValueError(f"out_dir {os.fspath(out_dir)!r} is not writable")
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
             for t in (*check_deployable(model, "model").parameters(), *model.buffers())):
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
            built :class:`~torchhys.deploy.streaming.StreamingCompensator` (then in ``dtype``).
        out_dir: an existing folder. The two files are written atomically: both are
            complete on the disk before either replaces an old file of its name; on an error
            (a full disk) the old pair is left as it was.
        prefix: the C prefix of every name (a C identifier).
        dtype: ``torch.float64`` or ``torch.float32``: the C step's real type (a model in
            another dtype is copied and converted, as ``model.to(dtype)``).
        limits, initial_command, input_range, input_margin, direction: as
            :func:`torchhys.deploy.export.to_torchscript`.

    Returns:
        ``(header_path, source_path)``.

    Shapes:
        The C step: ``x`` (one sample, the desired output in physical units) -> the command
        (one sample); batch 1, the state in the caller's ``PREFIX_state``.

    Raises:
        ValueError: a bad ``prefix``, ``dtype`` or ``out_dir``; an operation in the step
            without a C template (the message names it and the step it came from); see
            :class:`~torchhys.deploy.streaming.StreamingCompensator` for the other options.
        TypeError: see :class:`~torchhys.deploy.streaming.StreamingCompensator`.
    """
    prefix, folder = check_prefix(prefix), _check_out_dir(out_dir)
    comp = _build(model, dtype, limits, initial_command,
                  {"input_range": input_range, "input_margin": input_margin,
                   "direction": direction})
    state = comp.initial_state(1)
    with torch.no_grad():
        ep = torch.export.export(_ExplicitStep(comp), (torch.zeros(1, dtype=dtype), *state),
                                 strict=False)
    w = Writer(prefix)
    u, outputs = _translate(ep, w, [MEMBERS.get(k, f"s{k}") for k in range(len(state))])
    options = {"dtype": str(dtype).replace("torch.", ""), "limits": limits,
               "initial_command": initial_command, "input_range": input_range,
               "input_margin": input_margin, "direction": direction}
    header, source = files(prefix, w, model, comp, state, u, outputs, options)
    h_path, c_path = folder / f"{prefix}.h", folder / f"{prefix}.c"
    # both complete on the disk before either replaces its old version
    write_outputs([(h_path, header.encode()), (c_path, source.encode())])
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
                     "the compensator's own step (torchhys.deploy.streaming.StreamingCompensator)")
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


def _live(graph: fx.Graph, finite: dict[fx.Node, tuple[list[fx.Node], bool]]) -> set[fx.Node]:
    """The nodes the outputs read (a finite test reads its ``t``'s, not their ``t - t``)."""
    out = next(n for n in graph.nodes if n.op == "output")
    live, todo = set(), [out]
    while todo:
        n = todo.pop()
        if n not in live:
            live.add(n)
            todo.extend(finite[n][0] if n in finite else n.all_input_nodes)
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
    # the step's t - t tests of non-finite values, written as tests of bits (_finite)
    finite = {n: t for n in ep.graph.nodes if (t := _finite.finite_test(
        n, lambda p: known.get(p.name) if p.op == "placeholder" else None)) is not None}
    live = _live(ep.graph, finite)
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
            env[node] = _emit(w, node, env, missing, finite.get(node))
        elif node.op == "output":
            w.node += 1
            outs = [w.materialize(env[a]) for a in node.args[0]]
    if missing:
        raise ValueError("to_c: no C template for " + "; ".join(
            f"{op} (from {where})" for op, where in missing.items())
            + " (templates: torchhys.deploy.c._templates.TEMPLATES)")
    return outs[0], outs[1:]


_CAT = torch.ops.aten.cat.default


def _numel(node: fx.Node) -> int | None:
    val = node.meta.get("val")
    return val.numel() if isinstance(val, torch.Tensor) else None


def _outputs_only(node: fx.Node) -> bool:
    """Whether the node's result reaches the step's outputs only (directly or by views)."""
    return all(u.op == "output" or (u.target in VIEW_OPS and _outputs_only(u))
               for u in node.users)


def _emit(w: Writer, node: fx.Node, env: dict, missing: dict[str, str],
          finite: tuple[list[fx.Node], bool] | None = None) -> Any:
    if finite is not None:  # a t - t test: its operands are the t's (not live otherwise)
        terms, ne = finite
        args, kwargs = tuple(env[t] for t in terms), {}
    else:
        args, kwargs = fx.node.map_arg((node.args, node.kwargs), lambda n: env[n])
    spec = _spec(node.meta.get("val"))
    if node.target in SHAPE_ONLY or (_is_known((args, kwargs))
                                     and isinstance(spec, (CTensor, list))):
        if finite is not None:
            return constant(_finite.fold([a.value for a in args], finite[1], spec.shape))
        return _fold(node, args, kwargs)
    emit = TEMPLATES.get(node.target)
    if finite is not None:
        emit = lambda w, spec, *ops: _finite.emit(w, spec, list(ops), ne)  # noqa: E731
    if emit is not None:
        start = len(w.lines)
        w.alias = _outputs_only(node)
        if node.target in POINTWISE_OPS:
            users = list(node.users)
            w.defer = len(users) == 1 and (users[0].target == _CAT or (
                users[0].target in POINTWISE_OPS and _numel(users[0]) == _numel(node)
                is not None))
        elif node.target == _CAT:  # reads each element of its operands once
            w.defer = False
        else:  # a deferred operand is written into a local first
            w.defer = False
            args, kwargs = fx.node.map_aggregate(
                (args, kwargs), lambda x: w.materialize(x) if isinstance(x, CTensor) else x)
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
