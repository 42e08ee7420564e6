"""The composed step: a traced module's graph run on one sample, each stateful leaf replaced
by its step with the state threaded through.

:func:`build_step` takes the ``torch.fx`` graph of a user's module (traced by
:class:`~torchhys.compose._leaves.Tracer`) and the shapes of one pass on an example
(:class:`Shapes`), and writes a new graph ``(x, state, start) -> (y, new state)`` on inputs
with a time dimension of length 1: every node of the module's graph is copied as it is
(``torch.stack``, ``cat``, ``unsqueeze``, ``nn.Linear``, activations run unchanged on one
sample), every leaf call becomes a :class:`~torchhys.compose._leaves.LeafStep`. The graph is
a ``torch.fx.GraphModule`` (TorchScript- and ``torch.export``-able Python);
:class:`ComposedStep` wraps it as one :class:`~torchhys.step.OperatorStep`.

State: the leaves' blocks in the order of the graph, each named ``"<node>.<block>"``.
Start: a leaf fed by the input itself starts as its step does (``start + from_sample *
x0``), as does a leaf whose blocks start at constants; where some leaf starts from its own
first input otherwise (an operator with an anchored block after a filter or a layer), the
step is a :class:`ComposedStartStep`, whose ``initial_state(x0)`` runs the graph once on
``x0``, each leaf starting from its first input.
"""

# no `from __future__ import annotations`: TorchScript reads the steps' class annotations
import copy
import dataclasses
import operator
from collections.abc import Mapping
from typing import Any

import torch
import torch.fx as fx
from torch import Tensor, nn

from torchhys.compose._leaves import LeafStep, is_leaf, leaf_step
from torchhys.step import OperatorStep, StateBlock, custom_start

__all__ = ["ComposedStartStep", "ComposedStep", "Shapes", "build_step", "describe", "leaf_tails"]


@dataclasses.dataclass
class Shapes:
    """One pass of the module on an example: the example's batch and time, and each node's
    value (tensors, tuples of them, or other Python values)."""

    batch: int
    time: int
    values: Mapping[fx.Node, Any]


def describe(node: fx.Node, root: nn.Module) -> str:
    """``node 'name' (what it calls)`` for messages."""
    if node.op == "call_module":
        what = type(root.get_submodule(str(node.target))).__name__
    elif node.op == "call_function":
        target = node.target
        mod = getattr(target, "__module__", None) or ""
        name = getattr(target, "__name__", str(target))
        mod = "torch" if mod.startswith("torch") else "operator" if mod == "_operator" else mod
        what = f"{mod}.{name}".lstrip(".")
    elif node.op == "call_method":
        what = f"Tensor.{node.target}"
    else:
        what = node.op
    return f"node {node.name!r} ({what})"


class ComposedStep(OperatorStep):
    """A composition's per-sample step: x (batch, 1), state (its leaves' blocks, see the
    module docstring) -> (the module's output for the sample (batch, 1), new state).

    Written for TorchScript and ``torch.export``; built by :func:`build_step` (through
    :meth:`~torchhys.compose.Composed.streaming_steps`).
    """

    def __init__(self, graph: fx.GraphModule, state_spec: list[StateBlock]) -> None:
        super().__init__()
        self.graph = graph
        self.n_outputs = 1
        self.state_spec = state_spec

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        if not torch.jit.is_scripting():
            self._check_state(x, state)
        return self.graph(x, state, False)

    @torch.jit.unused
    def _check_state(self, x: Tensor, state: list[Tensor]) -> None:
        if not isinstance(x, Tensor) or x.dim() != 2 or x.shape[1] != 1:
            got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
            raise ValueError(f"{type(self).__name__}: x must have shape (batch, 1), got {got}")
        spec, batch = self.state_spec, x.shape[0]
        if not isinstance(state, list) or len(state) != len(spec):
            got = f"{len(state)} item(s)" if isinstance(state, list) else type(state).__name__
            raise ValueError(f"{type(self).__name__}: state must be the list of {len(spec)} "
                             f"tensor(s) of its state_spec, got {got}")
        for i, (t, block) in enumerate(zip(state, spec, strict=True)):
            if not isinstance(t, Tensor) or tuple(t.shape) != (batch, block.size):
                got = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
                raise ValueError(f"{type(self).__name__}: state[{i}] (block {block.name!r}) "
                                 f"must have shape ({batch}, {block.size}), got {got}")
            if (block.kind == "int64") != (t.dtype == torch.long):
                want = "int64" if block.kind == "int64" else "floating point"
                raise ValueError(f"{type(self).__name__}: state[{i}] (block {block.name!r}) "
                                 f"must be {want}, got {t.dtype}")


class ComposedStartStep(ComposedStep):
    """A :class:`ComposedStep` whose start is its own: :meth:`initial_state` runs the graph
    on the first sample, each leaf starting from its own first input."""

    def initial_state(self, x0: Tensor) -> list[Tensor]:
        """The state at a row's first sample x0 (batch, 1)."""
        empty: list[Tensor] = []
        return self.graph(x0, empty, True)[1]


def _copy_root(module: nn.Module, dtype: torch.dtype) -> nn.Module:
    """A detached copy of ``module`` in ``dtype`` in eval mode, for the step's graph."""
    root = copy.deepcopy(module)
    root.to(dtype).eval()
    for p in root.parameters():
        p.requires_grad_(False)
    return root


def _tail(value: Tensor, time_first: bool) -> list[int]:
    """The shape of a leaf's features (``value`` on the example) for one sample, with -1 for
    the batch: (batch, 1, ...), or (1, batch, ...) for a recurrent layer's time-first
    output."""
    return ([1, -1] if time_first else [-1, 1]) + list(value.shape[2:])


def leaf_tails(graph: fx.Graph, module: nn.Module, shapes: Shapes) -> dict[str, list[int]]:
    """Each leaf node's (by name) features shape for one sample, -1 for the batch."""
    out = {}
    for node in leaf_nodes(graph, module):
        sub = module.get_submodule(str(node.target))
        time_first = isinstance(sub, nn.RNNBase) and not sub.batch_first
        out[node.name] = _tail(shapes.values[node][0], time_first)
    return out


def leaf_nodes(graph: fx.Graph, root: nn.Module) -> list[fx.Node]:
    """The graph's calls of stateful leaves, in graph order."""
    return [n for n in graph.nodes
            if n.op == "call_module" and is_leaf(root.get_submodule(str(n.target)))]


def build_step(graph: fx.Graph, module: nn.Module, tails: dict[str, list[int]],
               dtype: torch.dtype) -> tuple[ComposedStep, dict[fx.Node, fx.Node]]:
    """The composed step of ``module``'s traced ``graph`` in ``dtype``, and the map of the
    graph's nodes to the step graph's (for the causality check). ``tails``: each leaf's
    features shape for one sample (:func:`leaf_tails`).

    Raises:
        ValueError, TypeError: a leaf that cannot stream (named).
    """
    root = _copy_root(module, dtype)
    new = fx.Graph()
    x = new.placeholder("x", type_expr=Tensor)
    state = new.placeholder("state", type_expr=list[Tensor])
    start = new.placeholder("start", type_expr=bool)
    env: dict[fx.Node, fx.Node] = {}
    spec: list[StateBlock] = []
    custom = False
    states: fx.Node | None = None
    leaves = set(leaf_nodes(graph, module))
    out = None
    for node in graph.nodes:
        if node.op == "placeholder":
            env[node] = x
        elif node.op == "output":
            out = env[node.args[0]]
        elif node in leaves:
            sub = module.get_submodule(str(node.target))
            step = leaf_step(sub, dtype, describe(node, module))
            tail = tails[node.name]
            name = f"_step_{node.name}"
            root.add_module(name, LeafStep(step, len(spec), tail))
            fed_by_x = node.args[0].op == "placeholder"
            constant = all(v == 0.0 for b in step.state_spec for v in b.columns("from_sample"))
            custom |= custom_start(step) or not (fed_by_x or constant)
            spec += [dataclasses.replace(b, name=f"{node.name}.{b.name}") for b in step.state_spec]
            call = new.call_module(name, (env[node.args[0]], state, start))
            env[node] = call
            s = new.call_function(operator.getitem, (call, 1))
            states = s if states is None else new.call_function(operator.add, (states, s))
        else:
            env[node] = new.node_copy(node, lambda n: env[n])
    new.output((out, state if states is None else states))
    gm = fx.GraphModule(root, new, class_name="ComposedGraph")
    kind = ComposedStartStep if custom else ComposedStep
    return kind(gm, spec), env
