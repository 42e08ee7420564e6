"""Recurrent models for the export tests of compositions (tests/test_compose_export*.py):
a hand-written per-sample step of a play, an LSTM cell and a GRU cell in plain torch
operations over the weights of real ``nn.LSTM`` / ``nn.GRU`` modules, a deployable around
it, and the timing of a generated C step (:func:`c_step_time`, for the latency benchmark).

The cells are written as torch's own (``torch.nn.LSTM`` and ``torch.nn.GRU``, gate orders
``i, f, g, o`` and ``r, z, n``); :func:`check_cells` compares them with the modules."""

from __future__ import annotations

import os
import subprocess
import tempfile
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchhys.step import OperatorStep, StateBlock


def lstm_cell(x: Tensor, h: Tensor, c: Tensor, w_ih: Tensor, w_hh: Tensor, b_ih: Tensor,
              b_hh: Tensor) -> tuple[Tensor, Tensor]:
    """One step of torch's LSTM cell: (h', c')."""
    gates = F.linear(x, w_ih, b_ih) + F.linear(h, w_hh, b_hh)
    i, f, g, o = gates.chunk(4, 1)
    c_new = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
    return torch.sigmoid(o) * torch.tanh(c_new), c_new


def gru_cell(x: Tensor, h: Tensor, w_ih: Tensor, w_hh: Tensor, b_ih: Tensor, b_hh: Tensor
             ) -> Tensor:
    """One step of torch's GRU cell: h'."""
    gi, gh = F.linear(x, w_ih, b_ih), F.linear(h, w_hh, b_hh)
    i_r, i_z, i_n = gi.chunk(3, 1)
    h_r, h_z, h_n = gh.chunk(3, 1)
    r, z = torch.sigmoid(i_r + h_r), torch.sigmoid(i_z + h_z)
    n = torch.tanh(i_n + r * h_n)
    return (1 - z) * n + z * h


class PlayLSTMGRUStep(OperatorStep):
    """x (batch, 1) -> y (batch, 1): a play of half-width ``radius`` (starting at the first
    sample), ``[x, play]`` into an LSTM cell, its h into a GRU cell, a linear read-out.

    State: the play's output (1), the LSTM's h and c, the GRU's h (zeros at the start)."""

    def __init__(self, lstm: nn.LSTM, gru: nn.GRU, out: nn.Linear, radius: float = 0.3) -> None:
        super().__init__()
        self.n_outputs = 1
        n, m = lstm.hidden_size, gru.hidden_size
        self.state_spec = [StateBlock("play", 1, from_sample=1.0), StateBlock("lstm h", n),
                           StateBlock("lstm c", n), StateBlock("gru h", m)]
        self.register_buffer("radius", torch.tensor(radius))
        for name in ("weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0"):
            self.register_buffer("lstm_" + name[:-3], getattr(lstm, name).detach().clone())
            self.register_buffer("gru_" + name[:-3], getattr(gru, name).detach().clone())
        self.register_buffer("out_w", out.weight.detach().clone())
        self.register_buffer("out_b", out.bias.detach().clone())

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        play, h1, c1, h2 = state
        play = torch.maximum(torch.minimum(play, x + self.radius), x - self.radius)
        h1, c1 = lstm_cell(torch.cat([x, play], 1), h1, c1, self.lstm_weight_ih,
                           self.lstm_weight_hh, self.lstm_bias_ih, self.lstm_bias_hh)
        h2 = gru_cell(h1, h2, self.gru_weight_ih, self.gru_weight_hh, self.gru_bias_ih,
                      self.gru_bias_hh)
        y = F.linear(h2, self.out_w, self.out_b)
        return y, [play, h1, c1, h2]


class LastColumn(nn.Module):
    """The compensator's head: features ``[x, step features...]`` -> the last column."""

    def forward(self, f: Tensor) -> Tensor:
        return f[:, -1:]


class StepModel(nn.Module):
    """A minimal deployable around one step: ``streaming_steps`` -> [the step],
    ``streaming_head`` -> :class:`LastColumn`."""

    def __init__(self, step: OperatorStep) -> None:
        super().__init__()
        self.step = step

    def streaming_steps(self, dtype: torch.dtype) -> list[OperatorStep]:
        import copy
        return [copy.deepcopy(self.step).to(dtype)]

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        return LastColumn()


def modules(hidden: int = 16, seed: int = 0, dtype: torch.dtype = torch.float64
            ) -> tuple[nn.LSTM, nn.GRU, nn.Linear]:
    """An LSTM (2 inputs), a GRU and a read-out of ``hidden`` units, torch's own init."""
    torch.manual_seed(seed)
    lstm = nn.LSTM(2, hidden, batch_first=True).to(dtype)
    gru = nn.GRU(hidden, hidden, batch_first=True).to(dtype)
    out = nn.Linear(hidden, 1).to(dtype)
    return lstm, gru, out


def play_lstm_gru(hidden: int = 16, seed: int = 0) -> StepModel:
    """The deployable of :class:`PlayLSTMGRUStep` with ``hidden`` units (float64)."""
    return StepModel(PlayLSTMGRUStep(*modules(hidden, seed)))


class LSTMStep(OperatorStep):
    """x (batch, 1) -> the read-out of one LSTM layer of ``hidden`` units (for timing)."""

    def __init__(self, hidden: int, seed: int = 0) -> None:
        super().__init__()
        torch.manual_seed(seed)
        lstm, out = nn.LSTM(1, hidden).double(), nn.Linear(hidden, 1).double()
        self.n_outputs = 1
        self.state_spec = [StateBlock("h", hidden), StateBlock("c", hidden)]
        for name in ("weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0"):
            self.register_buffer(name[:-3], getattr(lstm, name).detach().clone())
        self.register_buffer("out_w", out.weight.detach().clone())
        self.register_buffer("out_b", out.bias.detach().clone())

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        h, c = lstm_cell(x, state[0], state[1], self.weight_ih, self.weight_hh, self.bias_ih,
                         self.bias_hh)
        return F.linear(h, self.out_w, self.out_b), [h, c]


class GRUStep(OperatorStep):
    """x (batch, 1) -> the read-out of one GRU layer of ``hidden`` units (for timing)."""

    def __init__(self, hidden: int, seed: int = 0) -> None:
        super().__init__()
        torch.manual_seed(seed)
        gru, out = nn.GRU(1, hidden).double(), nn.Linear(hidden, 1).double()
        self.n_outputs = 1
        self.state_spec = [StateBlock("h", hidden)]
        for name in ("weight_ih_l0", "weight_hh_l0", "bias_ih_l0", "bias_hh_l0"):
            self.register_buffer(name[:-3], getattr(gru, name).detach().clone())
        self.register_buffer("out_w", out.weight.detach().clone())
        self.register_buffer("out_b", out.bias.detach().clone())

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        h = gru_cell(x, state[0], self.weight_ih, self.weight_hh, self.bias_ih, self.bias_hh)
        return F.linear(h, self.out_w, self.out_b), [h]


# --- timing of a generated C step ---------------------------------------------------------------

_TIMER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <time.h>
#include "comp.h"

/* timer N: N steps of a triangle wave, after N untimed; prints the mean ns a step (CLOCK:
   wall time, or the process's CPU time, which a loaded machine's other processes do not
   lengthen) */
int main(int argc, char **argv)
{
    comp_state s;
    struct timespec a, b;
    long n, i;
    volatile double sink = 0;
    if (argc != 2 || sscanf(argv[1], "%ld", &n) != 1)
        return 2;
    comp_init(&s);
    for (i = 0; i < n; ++i)
        sink += (double)comp_step(&s, (comp_real)(0.8 * (double)(i % 200) / 200.0 - 0.4));
    clock_gettime(CLOCK, &a);
    for (i = 0; i < n; ++i)
        sink += (double)comp_step(&s, (comp_real)(0.8 * (double)(i % 200) / 200.0 - 0.4));
    clock_gettime(CLOCK, &b);
    printf("%.3f\n", ((double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec))
           / (double)n);
    return sink == 12345.0;
}
"""


def c_step_time(model: nn.Module, *, dtype: torch.dtype = torch.float64,
                flags: tuple[str, ...] = ("-O2",), steps: int = 100_000, repeats: int = 5,
                cpu_time: bool = False, folder: str | os.PathLike | None = None) -> float:
    """The time of one step of ``to_c(model)`` in nanoseconds: the C compiled with
    ``cc -std=c99 FLAGS`` (benchmarks/latency.py's flags); the mean over ``steps`` steps of
    a triangle wave timed after as many untimed ones, the least of ``repeats`` runs (a
    shared machine's interruptions only lengthen a run); ``cpu_time``: the process's CPU
    time instead of the wall time (``CLOCK_PROCESS_CPUTIME_ID``: the time the other
    processes of a loaded machine take is left out). ``model``: a deployable or a built
    StreamingCompensator (in ``dtype``)."""
    from torchhys.deploy.c import to_c

    with tempfile.TemporaryDirectory() as tmp:
        where = Path(folder) if folder is not None else Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        to_c(model, where, prefix="comp", dtype=dtype, limits=(-1e6, 1e6), input_margin=None,
             direction="none")
        (where / "timer.c").write_text(_TIMER)
        exe = where / "timer"
        clock = "CLOCK_PROCESS_CPUTIME_ID" if cpu_time else "CLOCK_MONOTONIC"
        subprocess.run([os.environ.get("CC", "cc"), "-std=c99", *flags, f"-DCLOCK={clock}",
                        "-I", str(where),
                        "-o", str(exe), str(where / "timer.c"), str(where / "comp.c"), "-lm"],
                       check=True)
        runs = [subprocess.run([str(exe), str(steps)], capture_output=True, text=True,
                               check=True) for _ in range(repeats)]
        return min(float(r.stdout.split()[0]) for r in runs)


def check_cells(step: PlayLSTMGRUStep, lstm: nn.LSTM, gru: nn.GRU, out: nn.Linear,
                x: Tensor) -> float:
    """The largest difference of ``step.run(x)`` (x (batch, time)) from the torch modules
    run on the same played input (float64)."""
    y = step.run(x)[..., 0]
    r = float(step.radius)
    p, played = x[:, :1], []
    for xt in x.unbind(1):
        p = torch.maximum(torch.minimum(p, xt[:, None] + r), xt[:, None] - r)
        played.append(p)
    inp = torch.stack([x, torch.cat(played, 1)], 2)
    with torch.no_grad():
        ref = out(gru(lstm(inp)[0])[0])[..., 0]
    return float((y - ref).abs().max())


__all__ = ["GRUStep", "LSTMStep", "LastColumn", "PlayLSTMGRUStep", "StepModel", "c_step_time",
           "check_cells", "composed_layer", "gru_cell", "lstm_cell", "modules",
           "play_lstm_gru"]


class _Layer(nn.Module):
    """x (batch, time) -> an ``nn.LSTM`` / ``nn.GRU`` of ``hidden`` units -> a linear read-out
    (a user's module, for :func:`composed_layer`)."""

    def __init__(self, kind: str, hidden: int) -> None:
        super().__init__()
        self.rnn = {"lstm": nn.LSTM, "gru": nn.GRU}[kind](1, hidden, batch_first=True)
        self.out = nn.Linear(hidden, 1)

    def forward(self, x: Tensor) -> Tensor:
        h, _ = self.rnn(x.unsqueeze(-1))
        return self.out(h).squeeze(-1)


def composed_layer(kind: str, hidden: int, seed: int = 0,
                   dtype: torch.dtype = torch.float64) -> nn.Module:
    """``torchhys.compose.compose`` of one ``nn.LSTM`` (``kind="lstm"``) or ``nn.GRU``
    (``"gru"``) layer of ``hidden`` units and a linear read-out, in ``dtype``: the model
    whose C step :func:`c_step_time` times for the latency table (1 input, 1 output, the
    layer's weights torch's initialisation)."""
    from torchhys.compose import compose

    torch.manual_seed(seed)
    return compose(_Layer(kind, hidden).to(dtype))
