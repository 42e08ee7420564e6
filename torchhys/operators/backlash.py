"""``nn.Module`` wrappers of the play (backlash) operator: a cell and a sequence module."""

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchhys._checks import (
    check_bool,
    check_finite,
    check_floating,
    check_tensor,
    check_widths,
)
from torchhys.functional.backlash import backlash, check_play_state, play_step
from torchhys.operator import HysteresisOperator
from torchhys.registry import register_operator
from torchhys.step import OperatorStep, StateBlock
from torchhys.testing import Example

__all__ = ["Backlash", "BacklashCell", "PlayStep"]

# softplus(_ZERO_WIDTH_RAW) ~ 2e-9: how a learnable zero width is stored
_ZERO_WIDTH_RAW = -20.0


def _inverse_softplus(w: Tensor) -> Tensor:
    safe = w.clamp_min(1e-12)
    raw = torch.where(safe > 20.0, safe, torch.log(torch.expm1(safe)))
    return torch.where(w > 0, raw, torch.full_like(w, _ZERO_WIDTH_RAW))


class _Widths(nn.Module):
    """Holds N dead-band widths, fixed (a buffer) or learnable (kept positive by softplus)."""

    def __init__(self, widths: Tensor | list[float], *, learnable: bool = False) -> None:
        super().__init__()
        widths = torch.as_tensor(widths)
        if not widths.is_floating_point():
            widths = widths.to(torch.get_default_dtype())
        check_widths(widths, "widths")
        self.learnable = check_bool(learnable, "learnable")
        if self.learnable:
            self.raw_widths = nn.Parameter(_inverse_softplus(widths.detach().clone()))
        else:
            self.register_buffer("fixed_widths", widths.detach().clone())

    @property
    def n_operators(self) -> int:
        return (self.raw_widths if self.learnable else self.fixed_widths).shape[0]

    def get_widths(self) -> Tensor:
        """Current dead-band widths, shape (N,)."""
        if self.learnable:
            return F.softplus(self.raw_widths)
        return self.fixed_widths


def _check_cell_state(state: Tensor, batch: int, n: int) -> None:
    check_tensor(state, "state")
    check_floating(state, "state")
    if state.shape != torch.Size([batch, n]):
        raise ValueError(
            f"state must have shape (batch, N) = ({batch}, {n}), got shape {tuple(state.shape)}"
        )
    check_finite(state, "state")


class BacklashCell(_Widths):
    """N play operators advanced one sample at a time, in the manner of ``nn.GRUCell``.

    Args:
        widths: full dead-band widths d_i >= 0, shape (N,).
        learnable: make the widths trainable parameters (kept positive by softplus;
            a zero width is stored as about 2e-9).

    Shape:
        - x_t: (batch,)
        - state: (batch, N), the outputs at the previous sample (zeros if None)
        - returns ``(y_t, state)``, both (batch, N) and equal.
    """

    def forward(self, x_t: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        check_tensor(x_t, "x_t")
        check_floating(x_t, "x_t")
        if x_t.dim() != 1:
            raise ValueError(f"x_t must have shape (batch,), got shape {tuple(x_t.shape)}")
        check_finite(x_t, "x_t")
        n = self.n_operators
        if state is None:
            state = x_t.new_zeros(x_t.shape[0], n)
        else:
            _check_cell_state(state, x_t.shape[0], n)
        r = 0.5 * self.get_widths().to(x_t.dtype)
        y = play_step(x_t.unsqueeze(-1), r, state)
        return y, y


class PlayStep(OperatorStep):
    """N play operators, one sample at a time: :func:`~torchhys.functional.play_step`.

    State: ``plays`` (N columns, 0 at the first sample, as the sequence path starts).
    Features: the N play outputs.

    Args:
        widths: full dead-band widths, shape (N,), in the step's dtype.
    """

    def __init__(self, widths: Tensor) -> None:
        super().__init__()
        self.register_buffer("r", 0.5 * widths.detach().clone())
        self.n_outputs = int(widths.shape[0])
        self.state_spec = [StateBlock("plays", self.n_outputs)]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        y = play_step(x, self.r, state[0])
        return y, [y]


class Backlash(_Widths, HysteresisOperator):
    """N play (backlash) operators over whole sequences, with a carried state.

    Equal to looping :class:`BacklashCell` over time; calling it on consecutive
    chunks with the returned state equals one call on the whole sequence.

    Args:
        widths: full dead-band widths d_i >= 0, shape (N,).
        learnable: make the widths trainable parameters (kept positive by softplus).

    Shape:
        - x: (time,) or (batch, time)
        - state: the outputs before the first sample, (N,) or (batch, N); zeros if None
        - returns ``(y, final_state)``: y is ``x.shape + (N,)``; final_state is the
          outputs at the last sample, (N,) for x of shape (time,), else (batch, N).
    """

    constraints = {"fixed_widths": "nonnegative", "raw_widths": "finite"}

    @property
    def n_outputs(self) -> int:
        """One feature per play operator (N)."""
        return self.n_operators

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        widths = self.get_widths()
        check_play_state(state, x, widths.shape[0], "state")
        y = backlash(x, widths, state=state)
        return y, y[..., -1, :]

    def streaming_step(self, dtype: torch.dtype) -> PlayStep:
        """The per-sample step with the current widths, in ``dtype``."""
        return PlayStep(self.get_widths().detach().to(dtype))


register_operator("backlash", Backlash, example=Example(
    lambda: Backlash(torch.tensor([0.0, 0.3, 0.8], dtype=torch.float64)),
    bad_values={"fixed_widths": -1.0}))
