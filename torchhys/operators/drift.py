"""A slow drift driven by the input's accumulated variation, and its per-sample step
(identification: :mod:`torchhys.identification.drift`).

The maths is in :mod:`torchhys.functional.drift`: ``d = offset + sum_k w_k (1 - exp(-v /
c_k))``, v the input's total variation since the start of the record. Beside a hysteresis
model (one affine readout of both, e.g. ``operator: [{name: stop_pi}, {name: drift}]`` in a
config) it shifts the loop as the device is used: the ratcheting of a shape-memory alloy
cycled under load, the settling of a seal or a core over its first cycles.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchhys._checks import (
    check_bool,
    check_finite,
    check_nonnegative,
    check_real,
)
from torchhys.functional.drift import (
    check_scales,
    drift,
    drift_step,
)
from torchhys.operator import HysteresisOperator
from torchhys.registry import register_operator
from torchhys.step import OperatorStep, StateBlock
from torchhys.testing import Example

__all__ = ["Drift", "DriftStep"]


class DriftStep(OperatorStep):
    """A :class:`Drift`, one sample at a time.

    State: ``previous`` (the last input, float64; the first sample itself at the start) and
    ``variation`` (the accumulated variation, float64; 0 at the start). Feature: the drift.
    """

    def __init__(self, scales: Tensor, weights: Tensor, offset: Tensor,
                 min_variation: Tensor | None = None) -> None:
        super().__init__()
        self.register_buffer("scales", scales.detach().to(torch.float64).clone())
        self.register_buffer("weights", weights.detach().clone())
        self.register_buffer("offset", offset.detach().clone().reshape(()))
        floor = torch.zeros(()) if min_variation is None else min_variation.detach()
        self.register_buffer("min_variation", floor.to(torch.float64).clone().reshape(()))
        self.n_outputs = 1
        self.state_spec = [StateBlock("previous", 1, kind="float64", from_sample=1.0),
                           StateBlock("variation", 1, kind="float64")]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        d, previous, variation = drift_step(x, state[0], state[1], self.scales, self.weights,
                                            self.offset, self.min_variation)
        return d, [previous, variation]


class Drift(HysteresisOperator):
    """A drift of the accumulated input variation v (see :mod:`torchhys.functional.drift`):

        d = offset + sum_k w_k (1 - exp(-max(v, v_0) / c_k)),
        v[t] = sum_{s <= t} |x[s] - x[s-1]|.

    Identify it with :func:`fit_drift` (weights of one sign: a monotone, decelerating
    drift; ``v_0`` the least variation of the fitted samples).

    Args:
        scales: saturation scales c_k > 0 in input units, (K,) (a full cycle of amplitude A
            adds 2 A to v).
        weights: w_k, (K,); zeros if None.
        offset: the drift at the start.
        learnable: make the weights and the offset trainable (the scales stay fixed).
        min_variation: the floor v_0 >= 0: below it the drift is held at its value there (not
            extrapolated backwards from the variation it was identified on); 0: none.

    Shape:
        - x: (time,) or (batch, time)
        - state: ``(previous input, accumulated variation)`` before the first sample, (2,) or
          (batch, 2); None: a fresh start (no variation before the first sample)
        - returns ``(d, state)``: d the shape of x; the state after the last sample, float64
          (chunked calls with it equal one call).
    """

    n_outputs: int = 1

    def __init__(self, scales: Tensor | Sequence[float], weights: Tensor | Sequence[float] |
                 None = None, *, offset: float = 0.0, learnable: bool = False,
                 min_variation: float = 0.0) -> None:
        super().__init__()
        c = torch.as_tensor(scales)
        if not c.is_floating_point():
            c = c.to(torch.get_default_dtype())
        check_scales(c)
        w = (torch.zeros_like(c) if weights is None
             else torch.as_tensor(weights, dtype=c.dtype).detach().clone())
        if w.shape != c.shape:
            raise ValueError(f"weights must have the shape of scales {tuple(c.shape)}, got "
                             f"{tuple(w.shape)}")
        check_finite(w, "weights")
        check_bool(learnable, "learnable")
        o = torch.tensor(check_real(offset, "offset"), dtype=c.dtype)
        floor = check_nonnegative(min_variation, "min_variation")
        self.register_buffer("scales", c.detach().clone())
        self.register_buffer("min_variation", torch.tensor(floor, dtype=torch.float64))
        if learnable:
            self.weights = nn.Parameter(w)
            self.offset = nn.Parameter(o)
        else:
            self.register_buffer("weights", w)
            self.register_buffer("offset", o)

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        return drift(x, self.scales, self.weights, self.offset, state, self.min_variation)

    def streaming_step(self, dtype: torch.dtype) -> DriftStep:
        """The per-sample step with the current parameters (weights and offset in
        ``dtype``, the accumulation in float64)."""
        return DriftStep(self.scales, self.weights.detach().to(dtype),
                         self.offset.detach().to(dtype), self.min_variation)

    constraints = {"scales": "positive", "weights": "finite", "offset": "finite",
                   "min_variation": "nonnegative"}


register_operator("drift", Drift, example=Example(
    lambda: Drift(torch.tensor([0.5, 2.0], dtype=torch.float64), [0.3, -0.1], offset=0.1),
    bad_values={"scales": 0.0, "min_variation": -1.0}))
