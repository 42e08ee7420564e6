"""The stateful layers of a composition (its leaves): which modules they are, how the trace
keeps them whole, their steps, and the adapter that runs a leaf's step where the module ran.

A leaf is a torchhys operator (:class:`~torchhys.HysteresisOperator`, the dynamic blocks of
:mod:`torchhys.dynamics` included), a torch recurrent layer (``nn.LSTM``, ``nn.GRU``,
``nn.RNN``) or any module with a ``streaming_step(dtype)``. In the composed step a leaf's
call ``leaf(u)`` on u (batch, 1[, m]) (an operator) or (batch, 1, m) / (1, batch, m) (a
recurrent layer) becomes :class:`LeafStep`: its step on ``u`` as (batch, n_inputs), its
features reshaped back to what the module returns for one sample.
"""

# no `from __future__ import annotations`: TorchScript reads LeafStep's class annotations
from typing import Final

import torch
import torch.fx as fx
from torch import Tensor, nn

from torchhys.compose.recurrent import recurrent_step
from torchhys.operator import HysteresisOperator
from torchhys.step import STATE_KINDS, OperatorStep, check_step, custom_start


def is_leaf(module: nn.Module) -> bool:
    """Whether ``module`` is a stateful leaf of a composition (see the module docstring)."""
    return (isinstance(module, (HysteresisOperator, nn.RNNBase))
            or callable(getattr(module, "streaming_step", None)))


class Tracer(fx.Tracer):
    """A ``torch.fx`` tracer that keeps the stateful leaves (:func:`is_leaf`) and torch's own
    modules whole, and traces through every other module (``nn.Sequential``, a user's)."""

    def is_leaf_module(self, m: nn.Module, module_qualified_name: str) -> bool:
        return is_leaf(m) or super().is_leaf_module(m, module_qualified_name)


def leaf_step(module: nn.Module, dtype: torch.dtype, where: str) -> OperatorStep:
    """The step of leaf ``module`` in ``dtype``; errors name ``where`` (the node)."""
    kind = type(module).__name__
    try:
        if isinstance(module, nn.RNNBase):
            step = recurrent_step(module, dtype)
        else:
            step = module.streaming_step(dtype)
    except NotImplementedError as err:
        raise TypeError(f"{where} has no step ({kind}.streaming_step is not implemented): "
                        "give it streaming_step(dtype) -> torchhys.step.OperatorStep") from err
    except (TypeError, ValueError) as err:
        raise type(err)(f"{where} cannot stream: {err}") from err
    return check_step(step, f"{where}: its step", n_inputs=None)


class LeafStep(nn.Module):
    """A leaf's step where the module ran, in the composed step (see the module docstring).

    ``forward(u, state, start)``: u, the leaf's input for one sample; ``state``, the composed
    step's whole state, of which this leaf's blocks are ``state[offset:offset + n_state]``.
    ``start`` False: (features, new blocks). ``start`` True: the blocks at the first sample of
    ``u`` (its step's ``initial_state``, or ``start + from_sample * u`` block by block), the
    features of the step run from them, and those blocks (the state before the step).
    """

    offset: Final[int]
    n_state: Final[int]
    n_inputs: Final[int]
    custom: Final[bool]
    out_shape: list[int]
    kinds: list[int]
    offsets: list[int]
    sizes: list[int]

    def __init__(self, step: OperatorStep, offset: int, out_shape: list[int]) -> None:
        super().__init__()
        self.step = step
        self.offset, self.n_state = offset, len(step.state_spec)
        self.n_inputs = int(getattr(step, "n_inputs", 1))
        self.out_shape = out_shape
        self.custom = custom_start(step)
        starts: list[float] = []
        slopes: list[float] = []
        self.kinds, self.offsets, self.sizes = [], [], []
        for block in step.state_spec:
            self.kinds.append(STATE_KINDS.index(block.kind))
            self.offsets.append(len(starts))
            self.sizes.append(block.size)
            starts += block.columns("start")
            slopes += block.columns("from_sample")
        if self.n_inputs != 1 and not self.custom and any(s != 0.0 for s in slopes):
            raise ValueError(f"{type(step).__name__}: a block starts from the sample but the "
                             f"step has {self.n_inputs} inputs (it must override initial_state)")
        self.register_buffer("block_start", torch.tensor(starts, dtype=torch.float64))
        self.register_buffer("block_slope", torch.tensor(slopes, dtype=torch.float64))

    def forward(self, u: Tensor, state: list[Tensor], start: bool
                ) -> tuple[Tensor, list[Tensor]]:
        v = u.reshape(-1, self.n_inputs)
        if start:
            s = self.step.initial_state(v) if self.custom else self._affine(v)
        else:
            s = state[self.offset:self.offset + self.n_state]
        f, new = self.step(v, s)
        if start:
            new = s
        return f.reshape(self.out_shape), new

    def _affine(self, v: Tensor) -> list[Tensor]:
        """The blocks at ``start + from_sample * v``, in each block's dtype."""
        out: list[Tensor] = []
        x64 = v.narrow(1, 0, 1).to(torch.float64)
        for j in range(len(self.kinds)):
            o, n = self.offsets[j], self.sizes[j]
            start = self.block_start.narrow(0, o, n)
            kind = self.kinds[j]
            if kind == 2:  # int64 blocks start at constants
                out.append(start.to(torch.long).expand(v.shape[0], n))
            else:
                value = start + self.block_slope.narrow(0, o, n) * x64
                out.append(value.to(v.dtype) if kind == 0 else value)
        return out
