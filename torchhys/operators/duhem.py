"""The Duhem operator, a hysteretic element for feedback loops
(:mod:`torchhys.operators.feedback_element`).

:class:`DuhemHysteresis`: ``dz = g_up(z) dv`` while ``v`` rises and ``g_down(z) dv`` while it
falls, with slopes ``g = a + b z + c |z|`` (plus a small network of z where ``hidden > 0``),
integrated along a straight path from ``v[t-1]`` to ``v[t]`` by one RK4 step in ``v`` (the
scheme of :func:`torchhys.plants.bouc_wen_state`). The Bouc-Wen operator with exponent 1,
``dz = alpha dv - bg |dv| z - bd dv |z|``, is the case ``g_up = alpha - bg z - bd |z|``,
``g_down = alpha + bg z - bd |z|``. State ``(batch, 2)``: z and the previous v. Registered as
``"duhem"``.

References:
    P. Duhem (1897); J. W. Macki, P. Nistri, P. Zecca, "Mathematical models for hysteresis",
    SIAM Review 35 (1993) (the Duhem model); Ismail, Ikhouane, Rodellar (2009) (Bouc-Wen as
    a Duhem model).
"""

# no `from __future__ import annotations`: TorchScript reads the steps' class annotations
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import check_int
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

__all__ = ["DuhemHysteresis", "DuhemStep"]


def _duhem_slope(z: Tensor, c0: Tensor, c1: Tensor, c2: Tensor, move: Tensor,
                 layers: list[Tensor]) -> Tensor:
    """dz over the whole step, at z."""
    out = torch.addcmul(torch.addcmul(c0, c1, z), c2, z.abs())
    if len(layers) > 0:
        out = out + (_tanh_net(z, layers) * move).sum(1, keepdim=True)
    return out


def duhem_step(v: Tensor, state: Tensor, coef: Tensor, layers: list[Tensor]
               ) -> tuple[Tensor, Tensor]:
    """One sample of the Duhem operator: v (batch, 1), state (batch, 2) (z and the previous
    v), slopes ``coef`` (2, 3) (rows up, down; columns 1, z, |z|), the slope network's
    ``[w1, b1, w2, b2]`` (empty: none) -> (z (batch, 1), the new state)."""
    z, v_prev = state[:, :1], state[:, 1:]
    dv = v - v_prev
    up = dv.clamp_min(0.0)
    move = torch.cat([up, dv - up], dim=1)  # (B, 2); at dv = 0 the gradient goes one way
    c = move @ coef                                                         # (B, 3)
    c0, c1, c2 = c[:, :1], c[:, 1:2], c[:, 2:]
    k1 = _duhem_slope(z, c0, c1, c2, move, layers)
    k2 = _duhem_slope(z + 0.5 * k1, c0, c1, c2, move, layers)
    k3 = _duhem_slope(z + 0.5 * k2, c0, c1, c2, move, layers)
    k4 = _duhem_slope(z + k3, c0, c1, c2, move, layers)
    z = z + (k1 + k4 + 2 * (k2 + k3)) / 6
    return z, torch.cat([z, v], dim=1)


class DuhemStep(_NetStep):
    """The per-sample step of :class:`DuhemHysteresis` (:func:`duhem_step`).

    State: ``duhem`` (2 columns, z and the previous v, 0 at the first sample: from rest).
    """

    def __init__(self, coef: Tensor, layers: list[Tensor], dtype: torch.dtype) -> None:
        super().__init__()
        self.n_outputs = 1
        self.state_spec = [StateBlock("duhem", 2)]
        self.register_buffer("coef", coef.detach().to(dtype).clone())
        self._hold_layers(layers, dtype)

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        z, s = duhem_step(x, state[0], self.coef, self.layers())
        return z, [s]


class DuhemHysteresis(FeedbackElement):
    """The Duhem operator with affine-in-|z| slopes (module docstring).

    Args:
        hidden: tanh units of the slope network (0: the affine slopes only).

    Initialised with slopes 1 (``z = v`` from rest).
    """

    state_size = 2

    def __init__(self, hidden: int = 0) -> None:
        super().__init__()
        self.hidden = check_int(hidden, "hidden", minimum=0)
        # rows: up, down; columns: 1, z, |z|
        self.coef = nn.Parameter(torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
        if self.hidden:
            self.net = _zero_last(nn.Sequential(nn.Linear(1, hidden), nn.Tanh(),
                                                nn.Linear(hidden, 2)))

    def config(self) -> dict[str, Any]:
        return {"name": "duhem", "hidden": self.hidden}

    def step(self, v: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        return duhem_step(v, state, self.coef.to(v.dtype),
                          _layers(self.net if self.hidden else None))

    def streaming_step(self, dtype: torch.dtype) -> DuhemStep:
        """The per-sample step with the current slopes, in ``dtype``."""
        return DuhemStep(self.coef, _layers(self.net if self.hidden else None), dtype)


# the step holds its network's weights transposed and contiguous (an exported step reads
# them so); the sequence path reads them as nn.Linear does, through a transposed view:
# the products may round otherwise
register_operator("duhem", DuhemHysteresis, example=Example(
    lambda: _moved(DuhemHysteresis(hidden=3)), atol=1e-13))
