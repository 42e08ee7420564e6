"""The exported step's graph written as C, node by node: a template per aten operation
(:mod:`torchhys.deploy.c._templates`), nodes whose tensors are all known folded to constants,
the step's ``t - t`` tests of non-finite values written as tests of bits
(:mod:`torchhys.deploy.c._finite`), and every operation without a template named at once
(a node a template refuses, such as a batch norm in training mode, is named alone, with
what to do)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import torch
from torch import fx
from torch.export.graph_signature import InputKind

import torchhys.deploy.c._finite as _finite
from torchhys.deploy.c._norms import Refused
from torchhys.deploy.c._templates import POINTWISE_OPS, SHAPE_ONLY, TEMPLATES, VIEW_OPS
from torchhys.deploy.c._writer import CTensor, Writer, constant, contiguous_strides


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


def known_tensors(ep: torch.export.ExportedProgram) -> dict[str, torch.Tensor]:
    """The program's parameters, buffers and constant tensors by their placeholders' names."""
    known = {}
    for spec in ep.graph_signature.input_specs:
        if spec.kind in (InputKind.PARAMETER, InputKind.BUFFER, InputKind.CONSTANT_TENSOR):
            src = ep.state_dict if spec.target in ep.state_dict else ep.constants
            known[spec.arg.name] = src[spec.target]
    return known


def translate(ep: torch.export.ExportedProgram, w: Writer, members: list[str],
              conditioned: bool = False, inputs: list[str] | None = None
              ) -> tuple[CTensor, list[CTensor]]:
    """Write the step's statements into ``w``: returns the command's and the new state's
    tensors. The step's inputs are ``x``, the ``conditions`` array where ``conditioned``
    (or the C names of ``inputs`` where given: a one-element input is a C scalar, another
    an array), then the state's members."""
    between = (["conditions"] if conditioned else []) if inputs is None else list(inputs)
    sig = ep.graph_signature
    known = known_tensors(ep)
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
                names = ["x", *between, *(f"s->{m}" for m in members)]
                base = names[k]
                if 0 < k <= len(between) and val.numel() == 1 and val.dim() == 1:
                    w.scalars.add(base)
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
        except Refused as e:  # not a missing template: what to do, at once
            raise ValueError(f"to_c: node {node.name!r} ({node.target}, from "
                             f"{_origin(node)}): {e}") from None
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
