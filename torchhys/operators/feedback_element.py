"""Hysteretic elements for feedback loops: one sample at a time, with an explicit state.

A loop needs the element's output at sample t before it can advance the linear block, so an
element here is a per-sample step ``step(v, state) -> (z, state)`` on ``v`` (batch, 1); its
sequence path (:meth:`forward`) loops over that step. Both elements are rate-independent:
they see the path of ``v``, not its timing.

- :class:`DuhemHysteresis`: a Duhem operator, ``dz = g_up(z) dv`` while ``v`` rises and
  ``g_down(z) dv`` while it falls, with slopes ``g = a + b z + c |z|`` (plus a small network
  of z where ``hidden > 0``), integrated along a straight path from ``v[t-1]`` to ``v[t]``
  by one RK4 step in ``v`` (the scheme of :func:`torchhys.plants.bouc_wen_state`). The
  Bouc-Wen operator with exponent 1, ``dz = alpha dv - bg |dv| z - bd dv |z|``, is the case
  ``g_up = alpha - bg z - bd |z|``, ``g_down = alpha + bg z - bd |z|``.
  State ``(batch, 2)``: z and the previous v.
- :class:`PlayHysteresis`: a generalised Prandtl-Ishlinskii operator, a linear combination
  of v and N plays of v (the widths of a :class:`torchhys.Backlash`, the step
  :func:`~torchhys.functional.play_step`) plus a small tanh network of them. State
  ``(batch, N)``: the play outputs. Its minor loops are congruent (a Prandtl-Ishlinskii
  property), which the Bouc-Wen operator's are not.

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

from torchhys._checks import as_batched_sequence, check_dtype_of, check_int, check_state
from torchhys.functional.backlash import play_step
from torchhys.operator import HysteresisOperator, OperatorStep, StateBlock
from torchhys.operators.backlash import Backlash
from torchhys.registry import register_operator
from torchhys.testing import Example

__all__ = ["DuhemHysteresis", "DuhemStep", "FeedbackElement", "PlayHysteresis",
           "PlayHysteresisStep"]


def _zero_last(net: nn.Sequential) -> nn.Sequential:
    nn.init.zeros_(net[-1].weight)
    nn.init.zeros_(net[-1].bias)
    return net


def _tanh_net(x: Tensor, layers: list[Tensor]) -> Tensor:
    """``Linear -> tanh -> Linear`` of x (batch, in) with ``layers = [w1t, b1, w2t, b2]``,
    the weights transposed (in, out): ``addmm``, as ``nn.Linear`` computes it."""
    return torch.addmm(layers[3], torch.tanh(torch.addmm(layers[1], x, layers[0])), layers[2])


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


def _moved(op: FeedbackElement) -> FeedbackElement:
    """``op`` off its start (``z = v``), so that every parameter shapes the output."""
    with torch.no_grad():
        for p in op.parameters():
            p.add_(0.3 * torch.randn_like(p))
    return op


# the step holds its network's weights transposed and contiguous (an exported step reads
# them so); the sequence path reads them as nn.Linear does, through a transposed view:
# the products may round otherwise
register_operator("duhem", DuhemHysteresis, example=Example(
    lambda: _moved(DuhemHysteresis(hidden=3)), atol=1e-13))
register_operator("play_hysteresis", PlayHysteresis, example=Example(
    lambda: _moved(PlayHysteresis([0.2, 0.5, 1.0], hidden=3)), atol=1e-13))
