"""Hysteretic elements for feedback loops: one sample at a time, with an explicit state.

A loop needs the element's output at sample t before it can advance the linear block, so an
element here is a per-sample step ``step(v, state) -> (z, state)`` on ``v`` (batch, 1); its
sequence path (:meth:`forward`) loops over that step. The elements are rate-independent:
they see the path of ``v``, not its timing.

- :class:`~torchhys.operators.duhem.DuhemHysteresis`: a Duhem operator
  (``torchhys/operators/duhem.py``).
- :class:`~torchhys.operators.play_hysteresis.PlayHysteresis`: a generalised
  Prandtl-Ishlinskii operator (``torchhys/operators/play_hysteresis.py``).

Both are operators of the protocol (:mod:`torchhys.operator`), registered as ``"duhem"`` and
``"play_hysteresis"``: a spec ``{"name": "duhem", "hidden": 0}`` builds one
(:func:`torchhys.registry.make_operator`), :meth:`FeedbackElement.config` gives the spec that
rebuilds it (load the state dict after), and each streams and exports like any operator.
Both start from rest (a state of zeros: ``z = 0`` and ``v = 0`` before the first sample).

References:
    P. Duhem (1897); J. W. Macki, P. Nistri, P. Zecca, "Mathematical models for hysteresis",
    SIAM Review 35 (1993) (the Duhem model); Ismail, Ikhouane, Rodellar (2009) (Bouc-Wen as
    a Duhem model); Krejci, Kuhnen (2001) (Prandtl-Ishlinskii).
"""

# no `from __future__ import annotations`: TorchScript reads the steps' class annotations
import abc
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence, check_dtype_of, check_state
from torchhys.operator import HysteresisOperator
from torchhys.step import OperatorStep

__all__ = ["FeedbackElement"]


def _zero_last(net: nn.Sequential) -> nn.Sequential:
    nn.init.zeros_(net[-1].weight)
    nn.init.zeros_(net[-1].bias)
    return net


def _tanh_net(x: Tensor, layers: list[Tensor]) -> Tensor:
    """``Linear -> tanh -> Linear`` of x (batch, in) with ``layers = [w1t, b1, w2t, b2]``,
    the weights transposed (in, out): ``addmm``, as ``nn.Linear`` computes it."""
    return torch.addmm(layers[3], torch.tanh(torch.addmm(layers[1], x, layers[0])), layers[2])


def _layers(net: nn.Module | None) -> list[Tensor]:
    """``[w1t, b1, w2t, b2]`` of a ``Linear -> tanh -> Linear`` network (empty: None)."""
    return [] if net is None else [net[0].weight.t(), net[0].bias, net[2].weight.t(),
                                   net[2].bias]


class FeedbackElement(HysteresisOperator):
    """An operator whose differentiable per-sample step :meth:`step` a feedback loop calls
    (:class:`~torchhys.models.HysteresisFeedback`); its sequence path loops over that step.

    Subclasses set ``state_size`` and implement :meth:`step`, :meth:`config` and
    :meth:`~torchhys.HysteresisOperator.streaming_step`.

    Shape:
        - x: (time,) or (batch, time)
        - state: (state_size,) or (batch, state_size); zeros (rest) if None
        - returns ``(z, state)``: z of x's shape, the state after the last sample.
    """

    n_outputs = 1
    state_size: int

    @abc.abstractmethod
    def step(self, v: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        """v (batch, 1), state (batch, state_size) -> (z (batch, 1), the new state)."""

    @abc.abstractmethod
    def config(self) -> dict[str, Any]:
        """The spec that rebuilds the element (:func:`torchhys.registry.make_operator`; load
        the state dict after)."""

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        xb, squeezed = as_batched_sequence(x, "x")
        weights = [p for n, p in self.named_parameters() if n.startswith("net.")]
        if weights:  # the slope network's layers (its coefficients follow the input)
            xb = check_dtype_of(xb, "x", weights[0].dtype, f"{type(self).__name__} operator")
        B = xb.shape[0]
        s = (xb.new_zeros(B, self.state_size) if state is None
             else check_state(state, B, self.state_size, xb))
        zs = []
        for v_t in xb.unbind(1):
            z, s = self.step(v_t.unsqueeze(1), s)
            zs.append(z)
        out = torch.cat(zs, dim=1)
        return (out[0], s[0]) if squeezed else (out, s)


class _NetStep(OperatorStep):
    """A feedback element's step that holds an optional ``Linear -> tanh -> Linear`` slope
    network as buffers ``w1t, b1, w2t, b2`` (empty without one), in the step's dtype."""

    has_net: bool

    def _hold_layers(self, layers: list[Tensor], dtype: torch.dtype) -> None:
        self.has_net = len(layers) > 0
        empty = torch.zeros(0, dtype=dtype)
        for name, t in zip(("w1t", "b1", "w2t", "b2"), layers or [empty] * 4, strict=True):
            self.register_buffer(name, t.detach().to(dtype).contiguous().clone())

    def layers(self) -> list[Tensor]:
        """The network's ``[w1t, b1, w2t, b2]``, or ``[]`` without one."""
        out: list[Tensor] = []
        if self.has_net:
            out = [self.w1t, self.b1, self.w2t, self.b2]
        return out


def _moved(op: FeedbackElement) -> FeedbackElement:
    """``op`` off its start (``z = v``), so that every parameter shapes the output."""
    with torch.no_grad():
        for p in op.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return op
