"""Series composition of operators: ``Cascade(first, second)`` applies ``second`` to the output
of ``first``.

A cascade is an operator of the protocol (:mod:`torchhys.operator`): it trains inside an
:class:`~torchhys.InverseHysteresisNet`, streams through the
:class:`~torchhys.deploy.streaming.StreamingCompensator` and exports. Its use: hysteresis operators
of a filtered input, e.g. ``Cascade(TransferFunction.from_coefficients(b, a), EIHO(...))``,
the features of an inverse model of a plant with linear dynamics after its hysteresis
(``docs/compensation.md``, the stage plant).

Every operator but the last has one output; the cascade has the last one's outputs. Its state
is the list of the operators' states; its step runs the steps in series, and its
``state_spec`` is the first step's blocks followed by the second's.

Starting state. The compensator starts every block at ``start + from_sample * x0`` with the
*cascade's* first sample ``x0``, but the second operator's anchored blocks (those with
``from_sample != 0``, e.g. an EIHO's turning point) must start from *its own* first input,
the first operator's output ``v0``. Where the second step has such blocks the cascade step
adds one block ``"cascade fresh"`` (1 at the first sample, 0 after it) and, while it is 1,
sets those blocks to ``start + from_sample * v0`` before the second step runs (with
``torch.where``, no Python branching on tensor values). Nested cascades compose.
"""

# no `from __future__ import annotations`: TorchScript reads CascadeStep's class annotations
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor

from torchhys._checks import as_batched_sequence
from torchhys.operator import (
    Example,
    HysteresisOperator,
    OperatorStep,
    StateBlock,
    make_operator,
    register_operator,
)

__all__ = ["Cascade", "CascadeStep"]

OperatorSpec = HysteresisOperator | str | Mapping[str, Any]
"""An operator spec of :func:`~torchhys.operator.make_operator`: an operator, a registered
name, or ``{"name": NAME, **options}``."""


class CascadeStep(OperatorStep):
    """Two operator steps in series: ``second(first(x))`` (see the module docstring).

    State: ``first.state_spec`` + ``second.state_spec`` (+ ``"cascade fresh"``, one column
    starting at 1, where the second step has anchored float blocks). Features: the second
    step's.
    """

    n_first: int
    n_second: int
    fresh: bool
    reanchor: list[bool]
    offsets: list[int]
    sizes: list[int]

    def __init__(self, first: OperatorStep, second: OperatorStep) -> None:
        super().__init__()
        if first.n_outputs != 1:
            raise ValueError(f"the first step of a cascade must have one output, got "
                             f"{type(first).__name__} with n_outputs={first.n_outputs}")
        self.first, self.second = first, second
        self.n_outputs = second.n_outputs
        self.n_first, self.n_second = len(first.state_spec), len(second.state_spec)
        starts: list[float] = []
        slopes: list[float] = []
        self.reanchor, self.offsets, self.sizes = [], [], []
        for block in second.state_spec:
            anchored = block.kind != "int64" and any(
                v != 0.0 for v in block.columns("from_sample"))
            self.reanchor.append(anchored)
            self.offsets.append(len(starts))
            self.sizes.append(block.size)
            starts += block.columns("start")
            slopes += block.columns("from_sample")
        self.fresh = any(self.reanchor)
        self.register_buffer("anchor_start", torch.tensor(starts, dtype=torch.float64))
        self.register_buffer("anchor_slope", torch.tensor(slopes, dtype=torch.float64))
        extra = [StateBlock("cascade fresh", 1, start=1.0)] if self.fresh else []
        self.state_spec = list(first.state_spec) + list(second.state_spec) + extra

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        v, s1 = self.first(x, state[:self.n_first])
        s2 = state[self.n_first:self.n_first + self.n_second]
        if self.fresh:
            fresh = state[self.n_first + self.n_second] > 0.5
            v64 = v.to(torch.float64)
            for j in range(self.n_second):
                if self.reanchor[j]:
                    o, n = self.offsets[j], self.sizes[j]
                    init = (self.anchor_start.narrow(0, o, n)
                            + self.anchor_slope.narrow(0, o, n) * v64)
                    s2[j] = torch.where(fresh, init.to(s2[j].dtype), s2[j])
        f, s2 = self.second(v, s2)
        out = s1 + s2
        if self.fresh:
            out.append(torch.zeros_like(state[self.n_first + self.n_second]))
        return f, out


class Cascade(HysteresisOperator):
    """Operators in series: ``Cascade(first, second)(x) = second(first(x))``.

    ``Cascade(a, b, c)`` and ``Cascade([a, b, c])`` are ``c(b(a(x)))``. Each operator is a
    spec of :func:`~torchhys.operator.make_operator`: a
    :class:`~torchhys.HysteresisOperator`, a registered name or a dict
    ``{"name": NAME, **options}`` (so configs can write
    ``{name: cascade, first: {name: transfer_function, order: 2}, second: {name: eiho}}``).

    Args:
        first: the first operator, or a list of all of them (then ``second`` is None).
        second: the second operator.
        *more: further operators, applied after ``second``.

    Shape:
        - x: (time,) or (batch, time)
        - state: the list of the operators' states (None: each starts fresh)
        - returns ``(features, state)``: the last operator's features for ``x``, and the list
          of the states after the last sample; chunked calls equal one call.

    Raises:
        ValueError: fewer than two operators, an unknown name or bad options, an operator
            other than the last with more than one output, a non-causal operator (it would
            need the target of its own input).
        TypeError: a spec of another type, an operator outside the protocol.
    """

    def __init__(self, first: OperatorSpec | Sequence[OperatorSpec],
                 second: OperatorSpec | None = None, *more: OperatorSpec) -> None:
        super().__init__()
        if second is None:
            if more or isinstance(first, (str, Mapping)) or not isinstance(first, Sequence):
                raise ValueError("give the operators as Cascade(first, second, ...) or as one "
                                 f"list Cascade([first, second, ...]), got first={first!r}")
            specs = list(first)
        else:
            specs = [first, second, *more]
        if len(specs) < 2:
            raise ValueError(f"a cascade needs at least two operators, got {len(specs)}")
        ops = [make_operator(s, argument=f"operator {i} of the cascade")
               for i, s in enumerate(specs)]
        for i, op in enumerate(ops):
            if not op.causal:
                raise ValueError(f"operator {i} of the cascade ({type(op).__name__}) is not "
                                 "causal: a cascade takes causal operators only")
            if i < len(ops) - 1 and op.n_outputs != 1:
                raise ValueError(f"operator {i} of the cascade ({type(op).__name__}) feeds the "
                                 f"next one and must have one output, got {op.n_outputs}")
        self.stages = torch.nn.ModuleList(ops)
        self.n_outputs = ops[-1].n_outputs

    def forward(self, x: Tensor, state: Sequence[Any] | None = None
                ) -> tuple[Tensor, list[Any]]:
        xb, squeezed = as_batched_sequence(x, "x")
        n = len(self.stages)
        if state is not None and (isinstance(state, Tensor) or len(state) != n):
            got = type(state).__name__ if isinstance(state, Tensor) else f"{len(state)} states"
            raise ValueError(f"state must be a list of {n} states (one per operator), got {got}")
        v, states = xb, []
        for i, op in enumerate(self.stages):
            v, s = op(v, None if state is None else state[i])
            if i < n - 1 and v.dim() == 3:  # a one-output operator may keep its feature axis
                v = v.squeeze(-1)
            states.append(s)
        return (v[0] if squeezed else v), states

    def calibrate(self, x: Tensor) -> None:
        """Calibrate each operator on its own input (the previous operator's output)."""
        v, _ = as_batched_sequence(x, "x")
        for i, op in enumerate(self.stages):
            op.calibrate(v)
            if i < len(self.stages) - 1:
                with torch.no_grad():
                    v, _ = op(v)
                    v = v.squeeze(-1) if v.dim() == 3 else v

    def streaming_step(self, dtype: torch.dtype) -> CascadeStep:
        """The operators' steps in series (nested :class:`CascadeStep` from the right)."""
        steps = [op.streaming_step(dtype) for op in self.stages]
        step = steps[-1]
        for s in reversed(steps[:-1]):
            step = CascadeStep(s, step)
        return step


register_operator("cascade", Cascade, example=Example(
    # a filter, then an operator whose state starts at its own first input (an anchor); the
    # filter's scan (kernel off) rounds otherwise than its step
    lambda: Cascade({"name": "transfer_function", "order": 1},
                    {"name": "eiho", "a": [1.5, 0.8], "rule": "dominant", "threshold": 0.1,
                     "max_depth": 6}),
    atol=1e-12))
