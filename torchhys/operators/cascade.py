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

Starting state. Each step says how its state starts from a row's first finite sample
(:meth:`~torchhys.step.OperatorStep.initial_state`). The cascade's start is built from its
parts': the first part's from ``x0``, then the second part's from the first part's output
``v0`` at that sample (so an anchored block of the second part, e.g. an EIHO's turning point,
starts at its own first input). Nested cascades compose.
"""

# no `from __future__ import annotations`: TorchScript reads CascadeStep's class annotations
from collections.abc import Mapping, Sequence
from typing import Any, Final

import torch
from torch import Tensor

from torchhys._checks import as_batched_sequence
from torchhys.operator import HysteresisOperator
from torchhys.registry import make_operator, register_operator
from torchhys.step import STATE_KINDS, OperatorStep, custom_start
from torchhys.testing import Example

__all__ = ["Cascade", "CascadeStep"]

OperatorSpec = HysteresisOperator | str | Mapping[str, Any]
"""An operator spec of :func:`~torchhys.registry.make_operator`: an operator, a registered
name, or ``{"name": NAME, **options}``."""


class CascadeStep(OperatorStep):
    """Two operator steps in series: ``second(first(x))`` (see the module docstring).

    State: ``first.state_spec`` + ``second.state_spec``. Features: the second step's. Its
    :meth:`initial_state` is its own (the second part starts from the first part's output),
    which the compensator runs at a row's first finite sample.
    """

    n_first: int
    first_custom: Final[bool]
    second_custom: Final[bool]
    kinds: list[int]
    parts: list[int]
    offsets: list[int]
    sizes: list[int]

    def __init__(self, first: OperatorStep, second: OperatorStep) -> None:
        super().__init__()
        if first.n_outputs != 1:
            raise ValueError(f"the first step of a cascade must have one output, got "
                             f"{type(first).__name__} with n_outputs={first.n_outputs}")
        self.first, self.second = first, second
        self.n_outputs = second.n_outputs
        self.n_first = len(first.state_spec)
        # a part whose start is its own (a nested cascade) runs it; the others start at
        # start + from_sample * (their first input), from these buffers
        self.first_custom = custom_start(first)
        self.second_custom = custom_start(second)
        starts: list[float] = []
        slopes: list[float] = []
        self.kinds, self.parts, self.offsets, self.sizes = [], [], [], []
        for part, step in enumerate((first, second)):
            for block in step.state_spec:
                self.kinds.append(STATE_KINDS.index(block.kind))
                self.parts.append(part)
                self.offsets.append(len(starts))
                self.sizes.append(block.size)
                starts += block.columns("start")
                slopes += block.columns("from_sample")
        self.register_buffer("block_start", torch.tensor(starts, dtype=torch.float64))
        self.register_buffer("block_slope", torch.tensor(slopes, dtype=torch.float64))
        self.state_spec = list(first.state_spec) + list(second.state_spec)

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        v, s1 = self.first(x, state[:self.n_first])
        f, s2 = self.second(v, state[self.n_first:])
        return f, s1 + s2

    def initial_state(self, x0: Tensor) -> list[Tensor]:
        """The state at a row's first sample x0 (batch, 1): the first part's from x0, the
        second part's from the first part's output there."""
        s1 = self.first.initial_state(x0) if self.first_custom else self._affine(0, x0)
        v0, _ = self.first(x0, s1)
        s2 = self.second.initial_state(v0) if self.second_custom else self._affine(1, v0)
        return s1 + s2

    def _affine(self, part: int, x0: Tensor) -> list[Tensor]:
        """The blocks of one part at ``start + from_sample * x0``, in each block's dtype."""
        out: list[Tensor] = []
        x64 = x0.to(torch.float64)
        for j in range(len(self.kinds)):
            if self.parts[j] == part:
                o, n = self.offsets[j], self.sizes[j]
                start = self.block_start.narrow(0, o, n)
                kind = self.kinds[j]
                if kind == 2:  # int64 blocks start at constants (also for a NaN sample)
                    out.append(start.to(torch.long).expand(x0.shape[0], n))
                else:
                    value = start + self.block_slope.narrow(0, o, n) * x64
                    out.append(value.to(x0.dtype) if kind == 0 else value)
        return out


class Cascade(HysteresisOperator):
    """Operators in series: ``Cascade(first, second)(x) = second(first(x))``.

    ``Cascade(a, b, c)`` and ``Cascade([a, b, c])`` are ``c(b(a(x)))``. Each operator is a
    spec of :func:`~torchhys.registry.make_operator`: a
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
