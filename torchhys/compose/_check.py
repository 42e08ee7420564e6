"""The checks of a composition, each a one-line error naming the node: what the graph calls
its leaves with and uses of them (:func:`check_graph`), the shapes of one pass on an example
(:func:`shape_pass`), and causality, the module against its composed step sample by sample
(:func:`check_causal`)."""

from __future__ import annotations

import math
import operator
from typing import Any

import torch
import torch.fx as fx
from torch import Tensor, nn

from torchhys.compose.graph import ComposedStep, Shapes, describe, leaf_nodes

_REFUSED: tuple[tuple[type, str], ...] = (
    (nn.RNNCellBase, "a cell the module would loop over in time; use nn.LSTM, nn.GRU or "
                     "nn.RNN (whole sequences), whose steps torchhys writes"),
    (nn.MultiheadAttention, "attention reads the whole sequence: not causal"),
    (nn.Transformer, "attention reads the whole sequence: not causal"),
    (nn.TransformerEncoderLayer, "attention reads the whole sequence: not causal"),
    (nn.TransformerDecoderLayer, "attention reads the whole sequence: not causal"),
)


#: why a batch norm without running statistics cannot stream
_BATCH_STATISTICS = ("a batch norm without running statistics (track_running_stats=False) "
                     "normalises by the batch's own statistics, over the whole sequence: give "
                     "it running statistics (track_running_stats=True), train, and call .eval()")


def _first_line(err: BaseException) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


class _NodeError(ValueError):
    """An error of one node's call, named (torch.fx adds lines to it: :meth:`_Recorder.go`
    keeps the first)."""


class _Recorder(fx.Interpreter):
    """Runs a graph and keeps every node's value; an error names the node."""

    def __init__(self, gm: fx.GraphModule, what: str) -> None:
        super().__init__(gm, garbage_collect_values=False)
        self.what = what

    def run_node(self, n: fx.Node) -> Any:
        try:
            return super().run_node(n)
        except _NodeError:
            raise
        except Exception as err:  # the user's maths: any error, named by its node
            raise _NodeError(f"{describe(n, self.module)} failed {self.what}: "
                             f"{type(err).__name__}: {_first_line(err)}") from err

    def go(self, *args: Any) -> Any:
        """:meth:`run`, its error one line."""
        try:
            return self.run(*args)
        except _NodeError as err:
            raise ValueError(_first_line(err)) from err.__cause__


def check_graph(graph: fx.Graph, module: nn.Module) -> None:
    """The module's graph: one input, leaves called on their input alone, only their
    features used, no layer known not to stream (attention, cells, a batch norm without
    running statistics).

    Raises:
        ValueError: naming the node and what was expected.
    """
    inputs = [n for n in graph.nodes if n.op == "placeholder"]
    if len(inputs) != 1:
        raise ValueError(f"{type(module).__name__}.forward must take one input x (batch, time), "
                         f"got {len(inputs)} ({', '.join(n.name for n in inputs)})")
    for node in graph.nodes:
        if node.op != "call_module":
            continue
        sub = module.get_submodule(str(node.target))
        for kind, why in _REFUSED:
            if isinstance(sub, kind):
                raise ValueError(f"{describe(node, module)} cannot stream: {why}")
        if isinstance(sub, nn.modules.batchnorm._BatchNorm) and sub.running_mean is None:
            raise ValueError(f"{describe(node, module)} cannot stream: {_BATCH_STATISTICS}")
    for node in leaf_nodes(graph, module):
        desc, sub = describe(node, module), module.get_submodule(str(node.target))
        if not getattr(sub, "causal", True):
            raise ValueError(f"{desc} is not causal (it needs the target): it cannot stream")
        extra = [a for a in node.args[1:] if a is not None]
        extra += [k for k, v in node.kwargs.items() if v is not None]
        if len(node.args) < 1 or extra:
            raise ValueError(f"{desc} must be called on its input alone ({node.name}(u)): the "
                             "composed step carries its state (an initial state cannot be given)")
        for user in node.users:
            index = user.args[1] if user.target is operator.getitem and len(user.args) > 1 else None
            if index == 0 or (index == 1 and not user.users):
                continue
            returned = "(h, c)" if isinstance(sub, nn.LSTM) else "state"
            raise ValueError(f"{desc}: only its output ({node.name}(u)[0]) may be used, not "
                             f"its returned {returned} ({describe(user, module)} uses it): the "
                             "composed step carries the state")


def _expected_input(sub: nn.Module, B: int, T: int) -> tuple[int, ...]:
    if isinstance(sub, nn.RNNBase):
        return (B, T, sub.input_size) if sub.batch_first else (T, B, sub.input_size)
    m = int(getattr(sub, "n_inputs", 1))
    return (B, T) if m == 1 else (B, T, m)


def shape_pass(graph: fx.Graph, module: nn.Module, x: Tensor) -> Shapes:
    """One pass of the module's graph on example ``x`` (batch, time) in eval mode, checked:
    the output is (batch, time), each leaf's input and features have the batch and time
    where its kind has them.

    Raises:
        ValueError: naming the node (or the module) and the shapes expected and found.
    """
    B, T = x.shape
    gm = fx.GraphModule(module, graph)
    rec = _Recorder(gm, f"on an example x of shape ({B}, {T})")
    was = module.training
    module.eval()
    try:
        with torch.no_grad():
            y = rec.go(x)
    finally:
        module.train(was)
    for node in leaf_nodes(graph, module):
        desc, sub = describe(node, module), module.get_submodule(str(node.target))
        u, out = rec.env[node.args[0]], rec.env[node]
        want = _expected_input(sub, B, T)
        if not isinstance(u, Tensor) or tuple(u.shape) != want:
            got = tuple(u.shape) if isinstance(u, Tensor) else type(u).__name__
            layout = (f" (batch_first={sub.batch_first})" if isinstance(sub, nn.RNNBase)
                      else "")
            raise ValueError(f"{desc} expects its input of shape {want}{layout} on x of shape "
                             f"({B}, {T}), got {got}")
        f = out[0] if isinstance(out, tuple) and out else None
        lead = (T, B) if isinstance(sub, nn.RNNBase) and not sub.batch_first else (B, T)
        if not isinstance(f, Tensor) or tuple(f.shape[:2]) != lead:
            got = tuple(f.shape) if isinstance(f, Tensor) else type(out).__name__
            raise ValueError(f"{desc} must return (features, state) with features of leading "
                             f"shape {lead} on x of shape ({B}, {T}), got {got}")
    if not isinstance(y, Tensor) or tuple(y.shape) != (B, T):
        got = tuple(y.shape) if isinstance(y, Tensor) else type(y).__name__
        raise ValueError(f"{type(module).__name__} must map x (batch, time) to y (batch, time): "
                         f"on x of shape ({B}, {T}) it returned {got}")
    return Shapes(B, T, dict(rec.env))


def _time_slices(full: Tensor, one: Tensor, T: int) -> int | None:
    """The dimension of ``full`` that is time (``T`` there, 1 in ``one``, the rest equal);
    None when the shapes are equal (no time dimension); -1 when they do not correspond."""
    if full.shape == one.shape:
        return None
    if full.dim() != one.dim():
        return -1
    dims = [i for i in range(full.dim()) if full.shape[i] == T and one.shape[i] == 1
            and all(full.shape[j] == one.shape[j] for j in range(full.dim()) if j != i)]
    return dims[0] if len(dims) == 1 else -1


def check_causal(graph: fx.Graph, module: nn.Module, shapes: Shapes, step: ComposedStep,
                 env: dict[fx.Node, fx.Node], x: Tensor) -> None:
    """The composed step run sample by sample on ``x`` (the example of ``shapes``) against
    the module's values on the whole sequence, node by node.

    Raises:
        ValueError: naming the first node (in graph order) whose value for some sample
            differs (not causal), or whose shape does not follow the time dimension.
    """
    B, T = x.shape
    tol = 1e-7 if x.dtype == torch.float64 else 1e-3
    state = step.initial_state(x[:, :1])
    per_sample: list[dict[fx.Node, Any]] = []
    for t in range(T):
        rec = _Recorder(step.graph, f"on one sample (time length 1) at sample {t}")
        with torch.no_grad():
            y_t, state = rec.go(x[:, t:t + 1], state, False)
        if not isinstance(y_t, Tensor) or tuple(y_t.shape) != (B, 1):
            raise ValueError(f"{type(module).__name__} returned shape {tuple(y_t.shape)} on one "
                             f"sample x of shape ({B}, 1), expected ({B}, 1)")
        per_sample.append(rec.env)
    for node in graph.nodes:
        full = shapes.values.get(node)
        if node.op in ("placeholder", "output") or not isinstance(full, Tensor):
            continue
        if not full.is_floating_point() and not full.is_complex():
            full = full.to(x.dtype)
        for t in range(T):
            one = per_sample[t][env[node]]
            if not isinstance(one, Tensor):
                break
            dim = _time_slices(full, one, T)
            if dim == -1:
                raise ValueError(f"{describe(node, module)} has shape {tuple(full.shape)} on x "
                                 f"of shape ({B}, {T}) but {tuple(one.shape)} on one sample: "
                                 f"its value must keep the time dimension ({T} -> 1)")
            a = full if dim is None else full.select(dim, t)
            b = (one if dim is None else one.select(dim, 0)).to(a.dtype)
            diff = (a - b).abs()
            bound = tol * (1.0 + a.abs())
            bad = ~(diff <= bound) & ~(a.isnan() & b.isnan()) & (a != b)  # inf == inf
            if bool(bad.any()):
                d = float(diff[bad].max()) if bool(diff[bad].isfinite().any()) else math.nan
                raise ValueError(f"{describe(node, module)} mixes samples in time: its value "
                                 f"at sample {t} differs by {d:.3g} between the whole "
                                 "sequence and one sample at a time: not causal")
