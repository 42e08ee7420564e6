"""Users' modules of the compose tests: the compositions of issue 46, as a user writes them
(plain nn.Modules of torchhys operators, torch layers and elementwise maths)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

import torchhys
from torchhys.dynamics import TransferFunction


class BacklashLSTM(nn.Module):
    """A play operator, then an LSTM on [x, play(x)], then a linear readout."""

    def __init__(self, hidden: int = 8) -> None:
        super().__init__()
        self.bl = torchhys.Backlash(torch.tensor([0.3]))
        self.lstm = nn.LSTM(2, hidden, batch_first=True)
        self.lin = nn.Linear(hidden, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = torch.cat([x.unsqueeze(-1), self.bl(x)[0]], -1)
        out, _ = self.lstm(f)
        return self.lin(out).squeeze(-1)


class ParallelGRU(nn.Module):
    """Three plays and a GRU of x side by side, into an MLP."""

    def __init__(self) -> None:
        super().__init__()
        self.pi = torchhys.Backlash(torch.tensor([0.0, 0.2, 0.6]))
        self.gru = nn.GRU(1, 6, batch_first=True)
        self.mlp = nn.Sequential(nn.Linear(9, 8), nn.Tanh(), nn.Linear(8, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, _ = self.gru(x.unsqueeze(-1))
        return self.mlp(torch.cat([self.pi(x)[0], h], -1)).squeeze(-1) + 0.5 * x


class FilterEIHOGRU(nn.Module):
    """A transfer function, an EIHO operator of its output (an anchored start: it starts
    from its own first input) and a two-layer time-first GRU on [x, eiho]."""

    def __init__(self) -> None:
        super().__init__()
        self.tf = TransferFunction(order=2)
        self.eiho = torchhys.EIHO(a=0.7)
        self.gru = nn.GRU(2, 5, num_layers=2)
        self.out = nn.Linear(5, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        v = self.tf(x)[0]
        e = self.eiho(v)[0]
        f = torch.stack([x, e], -1).transpose(0, 1)  # (time, batch, 2)
        h, _ = self.gru(f)
        return torch.tanh(self.out(h)).squeeze(-1).transpose(0, 1)


class FilterLSTM(nn.Module):
    """A smooth composition: a filter, an LSTM of [x, filtered x], a sigmoid readout."""

    def __init__(self) -> None:
        super().__init__()
        self.tf = TransferFunction(order=1)
        self.lstm = nn.LSTM(2, 3, batch_first=True)
        self.lin = nn.Linear(3, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = torch.stack([x, self.tf(x)[0]], -1)
        return torch.sigmoid(self.lin(self.lstm(f)[0])).squeeze(-1) * 2.0 - 1.0


MODELS = {"backlash_lstm": BacklashLSTM, "parallel_gru": ParallelGRU,
          "filter_eiho_gru": FilterEIHOGRU}


def make(name: str, seed: int = 0, dtype: torch.dtype = torch.float64) -> nn.Module:
    """A freshly initialised model of ``MODELS`` (seeded) in ``dtype``."""
    torch.manual_seed(seed)
    return MODELS[name]().to(dtype)


def signal(batch: int = 3, time: int = 120, seed: int = 1,
           dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """A smooth random input in about [-1.5, 1.5] (batch, time)."""
    g = torch.Generator().manual_seed(seed)
    w = torch.randn(batch, time, generator=g, dtype=torch.float64).cumsum(1) * 0.2
    return (1.5 * torch.tanh(w)).to(dtype)


class Layers(nn.Module):
    """One recurrent layer of torch (``layer``: any number of layers, time first or batch
    first, with or without bias), then an MLP."""

    def __init__(self, layer: nn.RNNBase) -> None:
        super().__init__()
        self.rnn = layer
        self.mlp = nn.Sequential(nn.Linear(layer.hidden_size, 4), nn.SiLU(), nn.Linear(4, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = x.unsqueeze(-1) if self.rnn.batch_first else x.transpose(0, 1).unsqueeze(-1)
        h, _ = self.rnn(f)
        y = self.mlp(h).squeeze(-1)
        return y if self.rnn.batch_first else y.transpose(0, 1)


class StateSpaceMLP(nn.Module):
    """A two-input state-space layer (torchhys.dynamics.StateSpace) on [x, tanh(x)], then a
    readout."""

    def __init__(self) -> None:
        super().__init__()
        self.ss = torchhys.dynamics.StateSpace(3, 2, n_inputs=2)
        self.lin = nn.Linear(2, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s = self.ss(torch.stack([x, torch.tanh(x)], -1))[0]
        return self.lin(s).squeeze(-1)


def mlp() -> nn.Module:
    """Stateless layers only: nn.Sequential of Linear, Tanh, SiLU, Sigmoid, ReLU (x (batch,
    time) -> y (batch, time))."""
    return nn.Sequential(nn.Unflatten(-1, (-1, 1)), nn.Linear(1, 6), nn.Tanh(),
                         nn.Linear(6, 5), nn.SiLU(), nn.Linear(5, 4), nn.Sigmoid(),
                         nn.Linear(4, 3), nn.ReLU(), nn.Linear(3, 1), nn.Flatten(-2))


_KINDS = {"lstm": nn.LSTM, "gru": nn.GRU, "rnn_tanh": nn.RNN,
          "rnn_relu": lambda *a, **k: nn.RNN(*a, nonlinearity="relu", **k)}


def _layer(kind: str, layers: int, batch_first: bool) -> Layers:
    return Layers(_KINDS[kind](1, 5, num_layers=layers, batch_first=batch_first))


CONFORMANCE: dict[str, Callable[[], nn.Module]] = {
    **{f"{kind}_{n}_{'batch_first' if bf else 'time_first'}":
       (lambda kind=kind, n=n, bf=bf: _layer(kind, n, bf).double())
       for kind in _KINDS for n in (1, 2) for bf in (True, False)},
    "lstm_2_time_first_no_bias": lambda: Layers(nn.LSTM(1, 6, num_layers=2, bias=False)).double(),
    "gru_3_batch_first": lambda: Layers(nn.GRU(1, 5, num_layers=3, batch_first=True)).double(),
    "state_space": lambda: StateSpaceMLP().double(),
    "filter_lstm": lambda: FilterLSTM().double(),
    "mlp": lambda: mlp().double(),
    **{name: (lambda name=name: MODELS[name]().double()) for name in MODELS},
}
"""The compositions of the conformance suite, each a function building the module
(tests/test_conformance.py runs torchhys.testing.check_composed on each): every layer kind
(nn.LSTM, nn.GRU, nn.RNN tanh and relu, 1 and 2 layers, batch first and time first; an
LSTM without bias, a three-layer GRU; StateSpace; a transfer function into an LSTM; Linear
and activations in nn.Sequential) and the three compositions of :data:`MODELS`."""


def with_ranges(build: Callable[[], nn.Module]) -> nn.Module:
    """``compose`` of the module ``build`` makes (seed 0) with its ranges recorded on
    :func:`signal` and the module's own output there: the compensator's default limits,
    input clamp and direction guard then act."""
    from torchhys.compose import compose

    torch.manual_seed(0)
    module = build()
    x = signal()
    with torch.no_grad():
        y = module(x)
    return compose(module, x=x, y=y)
