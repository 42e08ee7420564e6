"""The play-hysteresis element, a hysteretic element for feedback loops
(:mod:`torchhys.operators.feedback_element`).

:class:`PlayHysteresis`: a generalised Prandtl-Ishlinskii operator, a linear combination of
v and N plays of v (the widths of a :class:`torchhys.Backlash`, the step
:func:`~torchhys.functional.play_step`) plus a small tanh network of them. State
``(batch, N)``: the play outputs. Its minor loops are congruent (a Prandtl-Ishlinskii
property), which the Bouc-Wen operator's are not. Registered as ``"play_hysteresis"``.

References:
    Krejci, Kuhnen (2001) (Prandtl-Ishlinskii).
"""

# no `from __future__ import annotations`: TorchScript reads the steps' class annotations
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import check_int
from torchhys.functional.backlash import play_step
from torchhys.operators.backlash import Backlash
from torchhys.operators.feedback_element import (
    FeedbackElement,
    _layers,
    _moved,
    _NetStep,
    _tanh_net,
    _zero_last,
)
from torchhys.registry import register_operator
from torchhys.step import StateBlock
from torchhys.testing import Example

__all__ = ["PlayHysteresis", "PlayHysteresisStep"]


def play_hysteresis_step(v: Tensor, state: Tensor, r: Tensor, w: Tensor, layers: list[Tensor]
                         ) -> tuple[Tensor, Tensor]:
    """One sample of :class:`PlayHysteresis`: v (batch, 1), state (batch, N) (the plays),
    half-widths r (N,), weights w (N + 1, 1), the network's ``[w1, b1, w2, b2]`` (empty:
    none) -> (z (batch, 1), the new plays)."""
    p = play_step(v, r, state)
    features = torch.cat([v, p], dim=1)
    z = features @ w
    if len(layers) > 0:
        z = z + _tanh_net(features, layers)
    return z, p


class PlayHysteresisStep(_NetStep):
    """The per-sample step of :class:`PlayHysteresis` (:func:`play_hysteresis_step`).

    State: ``plays`` (N columns, 0 at the first sample: from rest).
    """

    def __init__(self, widths: Tensor, w: Tensor, layers: list[Tensor],
                 dtype: torch.dtype) -> None:
        super().__init__()
        self.n_outputs = 1
        self.state_spec = [StateBlock("plays", int(widths.shape[0]))]
        self.register_buffer("r", (0.5 * widths.detach()).to(dtype).clone())
        self.register_buffer("w", w.detach().to(dtype).clone())
        self._hold_layers(layers, dtype)

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        z, p = play_hysteresis_step(x, state[0], self.r, self.w, self.layers())
        return z, [p]


class PlayHysteresis(FeedbackElement):
    """A generalised Prandtl-Ishlinskii operator: ``z = w . (v, p) + MLP(v, p)``.

    Args:
        widths: initial full dead-band widths of the N plays (learnable), (N,).
        hidden: tanh units of the network (0: the linear combination only).

    Initialised with ``z = v``.
    """

    def __init__(self, widths: Tensor | list[float], hidden: int = 16) -> None:
        super().__init__()
        self.plays = Backlash(torch.as_tensor(widths, dtype=torch.float64), learnable=True)
        self.state_size = self.plays.n_operators
        self.hidden = check_int(hidden, "hidden", minimum=0)
        k = 1 + self.state_size
        self.w = nn.Parameter(torch.cat([torch.ones(1, 1), torch.zeros(k - 1, 1)]))
        if self.hidden:
            self.net = _zero_last(nn.Sequential(nn.Linear(k, hidden), nn.Tanh(),
                                                nn.Linear(hidden, 1)))

    def config(self) -> dict[str, Any]:
        return {"name": "play_hysteresis", "widths": [0.0] * self.state_size,
                "hidden": self.hidden}

    def step(self, v: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        return play_hysteresis_step(v, state, (0.5 * self.plays.get_widths()).to(v.dtype),
                                    self.w.to(v.dtype),
                                    _layers(self.net if self.hidden else None))

    def streaming_step(self, dtype: torch.dtype) -> PlayHysteresisStep:
        """The per-sample step with the current widths and weights, in ``dtype``."""
        return PlayHysteresisStep(self.plays.get_widths(), self.w,
                                  _layers(self.net if self.hidden else None), dtype)


# the step holds its network's weights transposed and contiguous (an exported step reads
# them so); the sequence path reads them as nn.Linear does, through a transposed view:
# the products may round otherwise
register_operator("play_hysteresis", PlayHysteresis, example=Example(
    lambda: _moved(PlayHysteresis([0.2, 0.5, 1.0], hidden=3)), atol=1e-13))
