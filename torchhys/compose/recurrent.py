"""Per-sample steps of torch's recurrent layers (``nn.LSTM``, ``nn.GRU``, ``nn.RNN``), read
from the trained layer itself.

Each step is an :class:`~torchhys.step.OperatorStep` of ``n_inputs = input_size`` columns
and ``n_outputs = hidden_size`` features (the last layer's hidden state, what the layer
returns as its output at that sample). The weights are copied (detached) into buffers of
the step's dtype; the maths is torch's (``torch.nn.LSTM`` docs), written with
``torch.nn.functional.linear``, ``sigmoid``, ``tanh``, ``relu``, ``mul`` and ``add`` so
that TorchScript, ``torch.export`` and the C generator take it. State (layer-major columns:
layer ``l`` holds columns ``l * hidden_size`` to ``(l + 1) * hidden_size - 1``)::

    layer    blocks                                start
    -------  ------------------------------------  -----------------------
    LSTM     "h" (num_layers * hidden_size),       0 (torch's default h0,
             "c" (num_layers * hidden_size)          c0 of zeros)
    GRU      "h" (num_layers * hidden_size)        0
    RNN      "h" (num_layers * hidden_size)        0

Dropout between layers is a training-time device and is left out (the step is the layer in
``eval()`` mode). Not supported (a ``ValueError`` naming the layer): ``bidirectional=True``
(not causal) and ``proj_size > 0``.

References:
    S. Hochreiter and J. Schmidhuber, Long short-term memory, 1997; K. Cho et al., Learning
    phrase representations using RNN encoder-decoder, 2014 (the GRU); ``torch.nn.LSTM``,
    ``torch.nn.GRU``, ``torch.nn.RNN`` (the conventions: gate order i, f, g, o and r, z, n).
"""

# no `from __future__ import annotations`: TorchScript reads the steps' class annotations
from typing import Final

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchhys.step import OperatorStep, StateBlock

__all__ = ["GRUStep", "LSTMStep", "RNNStep", "recurrent_step"]


def _check_layer(layer: nn.RNNBase, kind: type) -> None:
    name = type(layer).__name__
    if not isinstance(layer, kind):
        raise TypeError(f"layer must be a torch.nn.{kind.__name__}, got {name}")
    if layer.bidirectional:
        raise ValueError(f"{name} is bidirectional: it reads the whole sequence backwards, "
                         "which is not causal; use bidirectional=False")
    if getattr(layer, "proj_size", 0):
        raise ValueError(f"{name} has proj_size={layer.proj_size}: LSTMs with projections "
                         "are not supported; use proj_size=0 and an nn.Linear after the layer")


class _Cell(nn.Module):
    """One layer's weights (buffers): ``w_ih`` (G*H, in), ``w_hh`` (G*H, H), ``b_ih``,
    ``b_hh`` (G*H,; zeros and unused without bias)."""

    has_bias: Final[bool]

    def __init__(self, layer: nn.RNNBase, index: int, dtype: torch.dtype) -> None:
        super().__init__()
        self.has_bias = bool(layer.bias)
        for name in ("weight_ih", "weight_hh", "bias_ih", "bias_hh"):
            if name.startswith("bias") and not self.has_bias:
                value = torch.zeros(layer.weight_hh_l0.shape[0], dtype=dtype)
            else:
                value = getattr(layer, f"{name}_l{index}").detach().to(dtype).clone()
            self.register_buffer(name.replace("weight", "w").replace("bias", "b"), value)

    def gates(self, x: Tensor, h: Tensor) -> tuple[Tensor, Tensor]:
        """The input's and the hidden state's affine maps, (batch, G*H) each."""
        if self.has_bias:
            return F.linear(x, self.w_ih, self.b_ih), F.linear(h, self.w_hh, self.b_hh)
        return F.linear(x, self.w_ih), F.linear(h, self.w_hh)


class _LSTMCell(_Cell):
    def forward(self, x: Tensor, h: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
        gi, gh = self.gates(x, h)
        i, f, g, o = (gi + gh).chunk(4, 1)
        c_new = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        return torch.sigmoid(o) * torch.tanh(c_new), c_new


class _GRUCell(_Cell):
    def forward(self, x: Tensor, h: Tensor) -> Tensor:
        gi, gh = self.gates(x, h)
        i_r, i_z, i_n = gi.chunk(3, 1)
        h_r, h_z, h_n = gh.chunk(3, 1)
        r = torch.sigmoid(i_r + h_r)
        z = torch.sigmoid(i_z + h_z)
        n = torch.tanh(i_n + r * h_n)
        return n + z * (h - n)  # torch's (1 - z) * n + z * h, as its kernel computes it


class _RNNCell(_Cell):
    relu: Final[bool]

    def __init__(self, layer: nn.RNNBase, index: int, dtype: torch.dtype) -> None:
        super().__init__(layer, index, dtype)
        self.relu = layer.mode == "RNN_RELU"

    def forward(self, x: Tensor, h: Tensor) -> Tensor:
        gi, gh = self.gates(x, h)
        if self.relu:
            return torch.relu(gi + gh)
        return torch.tanh(gi + gh)


class _RecurrentStep(OperatorStep):
    """The layers' cells and the state layout (see the module docstring)."""

    hidden: Final[int]
    n_layers: Final[int]

    def __init__(self, layer: nn.RNNBase, kind: type, cell: type, blocks: tuple[str, ...],
                 dtype: torch.dtype | None) -> None:
        super().__init__()
        _check_layer(layer, kind)
        dtype = layer.weight_ih_l0.dtype if dtype is None else dtype
        self.n_inputs = int(layer.input_size)
        self.n_outputs = self.hidden = int(layer.hidden_size)
        self.n_layers = int(layer.num_layers)
        self.cells = nn.ModuleList(cell(layer, i, dtype) for i in range(self.n_layers))
        self.state_spec = [StateBlock(b, self.n_layers * self.hidden) for b in blocks]

    def _layers(self, h: Tensor) -> list[Tensor]:
        """The state's columns of each layer."""
        if self.n_layers == 1:
            return [h]
        return list(h.split(self.hidden, 1))

    @staticmethod
    def _join(hs: list[Tensor]) -> Tensor:
        return hs[0] if len(hs) == 1 else torch.cat(hs, 1)


class LSTMStep(_RecurrentStep):
    """The step of a trained ``nn.LSTM``: x (batch, input_size), state ``[h, c]`` (batch,
    num_layers * hidden_size) each -> (the last layer's h (batch, hidden_size), new state).

    Args:
        layer: the ``nn.LSTM`` (read, not modified).
        dtype: the step's dtype (default: the layer's).

    Raises:
        ValueError: a bidirectional layer or one with ``proj_size > 0``.
    """

    def __init__(self, layer: nn.LSTM, dtype: torch.dtype | None = None) -> None:
        super().__init__(layer, nn.LSTM, _LSTMCell, ("h", "c"), dtype)

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        hs, cs = self._layers(state[0]), self._layers(state[1])
        new_h: list[Tensor] = []
        new_c: list[Tensor] = []
        v = x
        for i, cell in enumerate(self.cells):
            v, c = cell(v, hs[i], cs[i])
            new_h.append(v)
            new_c.append(c)
        return v, [self._join(new_h), self._join(new_c)]


class GRUStep(_RecurrentStep):
    """The step of a trained ``nn.GRU``: x (batch, input_size), state ``[h]`` (batch,
    num_layers * hidden_size) -> (the last layer's h (batch, hidden_size), new state).

    Args:
        layer: the ``nn.GRU`` (read, not modified).
        dtype: the step's dtype (default: the layer's).

    Raises:
        ValueError: a bidirectional layer.
    """

    def __init__(self, layer: nn.GRU, dtype: torch.dtype | None = None) -> None:
        super().__init__(layer, nn.GRU, _GRUCell, ("h",), dtype)

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        hs = self._layers(state[0])
        new_h: list[Tensor] = []
        v = x
        for i, cell in enumerate(self.cells):
            v = cell(v, hs[i])
            new_h.append(v)
        return v, [self._join(new_h)]


class RNNStep(GRUStep):
    """The step of a trained ``nn.RNN`` (``nonlinearity`` ``"tanh"`` or ``"relu"``): x
    (batch, input_size), state ``[h]`` (batch, num_layers * hidden_size) -> (the last
    layer's h (batch, hidden_size), new state).

    Args:
        layer: the ``nn.RNN`` (read, not modified).
        dtype: the step's dtype (default: the layer's).

    Raises:
        ValueError: a bidirectional layer.
    """

    def __init__(self, layer: nn.RNN, dtype: torch.dtype | None = None) -> None:
        _RecurrentStep.__init__(self, layer, nn.RNN, _RNNCell, ("h",), dtype)


_STEPS: dict[type, type] = {nn.LSTM: LSTMStep, nn.GRU: GRUStep, nn.RNN: RNNStep}


def recurrent_step(layer: nn.RNNBase, dtype: torch.dtype | None = None) -> OperatorStep:
    """The step of ``nn.LSTM``, ``nn.GRU`` or ``nn.RNN`` ``layer`` in ``dtype``.

    Raises:
        TypeError: another kind of layer (named, with the kinds supported).
        ValueError: a layer of a kind supported but of options that are not (see the
            module docstring).
    """
    for kind, step in _STEPS.items():
        if type(layer) is kind or isinstance(layer, kind):
            return step(layer, dtype)
    raise TypeError(f"{type(layer).__name__} has no step: the recurrent layers with one are "
                    f"{', '.join('torch.nn.' + k.__name__ for k in _STEPS)}")
