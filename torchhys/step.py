"""The per-sample step of an operator (:class:`OperatorStep`) and its state's layout
(:class:`StateBlock`): the half of the operator protocol that export and the streaming
compensator run (see :mod:`torchhys.operator` for the whole protocol)."""

import abc
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchhys._checks import check_choice, check_int, concrete

__all__ = ["STATE_KINDS", "OperatorStep", "StateBlock", "check_step", "custom_start"]

STATE_KINDS = ("float", "float64", "int64")


@dataclass(frozen=True)
class StateBlock:
    """One block of an operator step's state: a ``(batch, size)`` tensor.

    Args:
        name: what it holds (for the layout table and error messages).
        size: number of columns (>= 1).
        kind: ``"float"`` (the compensator's dtype), ``"float64"`` or ``"int64"``.
        start: value of each column at a row's first finite sample (a number, or one per
            column) ...
        from_sample: ... plus this times that sample (a number, or one per column; float
            kinds only).
    """

    name: str
    size: int
    kind: str = "float"
    start: float | Sequence[float] = 0.0
    from_sample: float | Sequence[float] = 0.0

    def __post_init__(self) -> None:
        check_int(self.size, f"StateBlock {self.name!r}: size", minimum=1)
        check_choice(self.kind, f"StateBlock {self.name!r}: kind", STATE_KINDS)
        for field in ("start", "from_sample"):
            values = self.columns(field)
            if len(values) != self.size:
                raise ValueError(f"StateBlock {self.name!r}: {field} needs one value per "
                                 f"column ({self.size}), got {len(values)}")
        if self.kind == "int64" and any(v != 0.0 for v in self.columns("from_sample")):
            raise ValueError(f"StateBlock {self.name!r}: an int64 block cannot start from "
                             "the sample (from_sample must be 0)")

    def columns(self, field: str) -> list[float]:
        """``start`` or ``from_sample`` as one float per column."""
        value = getattr(self, field)
        if isinstance(value, (int, float)):
            return [float(value)] * self.size
        return [float(v) for v in value]


class OperatorStep(nn.Module, abc.ABC):
    """The per-sample step of an operator, for export (see the module docstring).

    Subclasses set ``n_outputs`` and ``state_spec`` in ``__init__`` and implement
    :meth:`forward`. A step of several input columns (a recurrent layer's step, a
    multi-input block: ``x`` (batch, n_inputs)) sets ``n_inputs``; an operator's step, and
    every step the streaming compensator runs, has one (the default).
    """

    # class annotations are read by TorchScript (this module keeps them unquoted); the spec is
    # Python-level layout, not part of the scripted step
    n_outputs: int
    state_spec: list[StateBlock]
    n_inputs: int = 1
    __jit_ignored_attributes__ = ["state_spec"]

    @abc.abstractmethod
    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        """x (batch, n_inputs), state (one (batch, size) tensor per block) -> (features
        (batch, n_outputs), new state)."""

    def initial_state(self, x0: Tensor) -> list[Tensor]:
        """The state at a row's first finite sample ``x0`` (batch, n_inputs), before the step
        runs on it. Default: each block at ``start + from_sample * x0`` (its
        :class:`StateBlock`), which the compensator computes itself for all such steps at once
        (with several inputs the default needs ``from_sample`` 0: the blocks start at
        ``start``). A step whose start
        is not of that form overrides it (in TorchScript- and ``torch.export``-able code,
        e.g. a cascade, whose second part starts from the first part's output); the
        compensator then runs the override at each row's first finite sample."""
        out = []
        for block in self.state_spec:
            dtype = {"float": x0.dtype, "float64": torch.float64, "int64": torch.long}[block.kind]
            start = torch.tensor(block.columns("start"), dtype=torch.float64, device=x0.device)
            slope = torch.tensor(block.columns("from_sample"), dtype=torch.float64,
                                 device=x0.device)
            if self.n_inputs != 1:
                if any(v != 0.0 for v in block.columns("from_sample")):
                    raise ValueError(f"{type(self).__name__}: block {block.name!r} starts "
                                     "from the sample (from_sample != 0) but the step has "
                                     f"{self.n_inputs} inputs: override initial_state")
                value = start.expand(x0.shape[0], block.size)
            else:
                value = start + slope * x0.to(torch.float64)
            out.append(value.to(dtype))
        return out

    def run(self, x: Tensor) -> Tensor:
        """Step through a whole sequence from a fresh state: x (batch, time) (one input) or
        (batch, time, n_inputs) -> (batch, time, n_outputs). For tests and inspection (a
        Python loop)."""
        m = self.n_inputs
        want = 2 if m == 1 else 3
        if x.dim() != want or x.shape[1] == 0 or (m != 1 and x.shape[2] != m):
            shape = "(batch, time)" if m == 1 else f"(batch, time, {m})"
            raise ValueError(f"x must have shape {shape} with time >= 1, got shape "
                             f"{tuple(x.shape)}")
        xs = x.unsqueeze(2) if m == 1 else x
        state = self.initial_state(xs[:, 0])
        outs = []
        for xt in xs.unbind(1):
            f, state = self(xt, state)
            outs.append(f)
        return torch.stack(outs, dim=1)


def check_step(step: object, argument: str = "step", *, n_inputs: int | None = 1
               ) -> OperatorStep:
    """``step``, checked to be an :class:`OperatorStep` with its ``n_outputs`` and a
    ``state_spec`` of :class:`StateBlock` (both set in ``__init__``), and ``n_inputs``
    input columns (default 1, what the streaming compensator feeds; None: any).

    Raises:
        TypeError: naming ``argument`` and what is missing or of another number of inputs.
    """
    kind = type(step).__name__
    if not isinstance(step, OperatorStep):
        raise TypeError(f"{argument} must be a torchhys.step.OperatorStep, got {kind}")
    missing = [m for m in ("n_outputs", "state_spec") if not hasattr(step, m)]
    if missing:
        raise TypeError(f"{argument} ({kind}) has no {', '.join(missing)} (an OperatorStep "
                        "sets both in __init__)")
    if not all(isinstance(b, StateBlock) for b in step.state_spec):
        raise TypeError(f"{argument} ({kind}): state_spec must be a list of StateBlock")
    m = getattr(step, "n_inputs", 1)
    if isinstance(m, bool) or not isinstance(m, int) or m < 1:
        raise TypeError(f"{argument} ({kind}): n_inputs must be an int >= 1, got {m!r}")
    if n_inputs is not None and m != n_inputs:
        raise TypeError(f"{argument} ({kind}) takes {m} input column(s), expected {n_inputs} "
                        "(a step the compensator runs takes x (batch, 1); compose a "
                        "multi-input layer with torchhys.compose.compose)")
    return step


def _check_step_state(state: object, spec: Sequence[StateBlock], batch: int) -> None:
    """Raise ``ValueError`` naming ``state`` unless it is the step's state for ``batch``
    rows: one tensor (batch, size) per block, floating (finite) or int64 by the block's
    kind."""
    if not isinstance(state, list) or len(state) != len(spec):
        got = f"{len(state)} item(s)" if isinstance(state, list) else type(state).__name__
        raise ValueError(f"state must be the list of {len(spec)} tensor(s) this operator "
                         f"returns, got {got}")
    for i, (t, block) in enumerate(zip(state, spec, strict=True)):
        where = f"state[{i}] (block {block.name!r})"
        if not isinstance(t, Tensor) or tuple(t.shape) != (batch, block.size):
            shape = tuple(t.shape) if isinstance(t, Tensor) else type(t).__name__
            raise ValueError(f"{where} must have shape ({batch}, {block.size}), got {shape}")
        if block.kind == "int64":
            if t.dtype != torch.long:
                raise ValueError(f"{where} must be int64, got {t.dtype}")
        elif not t.is_floating_point() or (concrete(t) and not bool(t.isfinite().all())):
            raise ValueError(f"{where} must be floating point and finite")


def custom_start(step: OperatorStep) -> bool:
    """Whether ``step`` overrides :meth:`OperatorStep.initial_state` (its start is not
    ``start + from_sample * x0`` block by block)."""
    return type(step).initial_state is not OperatorStep.initial_state
