"""Shared test inputs and references (test modules import these, never each other)."""

from __future__ import annotations

import importlib.util
import math
import types
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from torchhys import InverseHysteresisNet, signals
from torchhys.init import least_squares_output

if TYPE_CHECKING:  # the streaming module is not imported by tests that do not stream
    from torchhys.deploy.streaming import StreamingCompensator

# --- inputs -----------------------------------------------------------------------------------


RAW = {"direction": "none", "input_margin": None}
"""Options of a compensator without its direction guard and input clamp: the model's own
streaming path, compared with its sequence path (tests of the guard and the clamp: in
tests/test_streaming_direction.py)."""


def random_walk(seed: int, T: int = 300, quantize: bool = True) -> torch.Tensor:
    """A float64 random walk (time,) with flat stretches; quantized: exact threshold ties."""
    g = torch.Generator().manual_seed(seed)
    steps = torch.randn(T, generator=g, dtype=torch.float64)
    steps[torch.rand(T, generator=g) < 0.2] = 0.0  # flat stretches / repeated samples
    x = steps.cumsum(0)
    return (x * 4).round() / 4 if quantize else x  # quantized: exact ties with the threshold


def batch() -> torch.Tensor:
    """Three random walks of 120 samples, (3, 120), quantized and not."""
    return torch.stack([random_walk(s, T=120, quantize=s % 2 == 0) for s in range(3)])


def smooth_input(T: int = 40) -> torch.Tensor:
    """A smooth float64 input (time,) whose turning points fall between samples."""
    t = torch.linspace(0.05, 3.0, T, dtype=torch.float64)
    return torch.sin(2 * t) + 0.3 * t  # turning points between samples, away from x_e


def inputs(T: int = 400) -> torch.Tensor:
    """Random walks with flat stretches and exact ties, noise, nested minor loops: (5, T)."""
    rows = [random_walk(s, T=T, quantize=s % 2 == 0) for s in range(3)]
    t = torch.linspace(0.0, 10.0, T, dtype=torch.float64)
    g = torch.Generator().manual_seed(7)
    rows.append(3 * torch.sin(t) + 0.05 * torch.randn(T, generator=g, dtype=torch.float64))
    rows.append(signals.nested_reversals(t, amplitude=4.0, n_reversals=24, ratio=0.85))
    return torch.stack(rows)


# --- running modules --------------------------------------------------------------------------


def chunks(x: torch.Tensor, sizes: list[int]) -> list[torch.Tensor]:
    """``x`` cut along time into chunks of the given sizes (repeated cyclically)."""
    out, start = [], 0
    while start < x.shape[-1]:
        size = sizes[len(out) % len(sizes)]
        out.append(x[..., start : start + size])
        start += size
    return out


def run_chunked(module: torch.nn.Module, x: torch.Tensor, sizes: list[int], **kw) -> torch.Tensor:
    """``module`` called chunk by chunk with the carried state; outputs joined along time."""
    state, outs = None, []
    for c in chunks(x, sizes):
        y, state = module(c, state, **kw)
        outs.append(y)
    return torch.cat(outs, dim=-1)


def run_split(module: Callable[[torch.Tensor, Any], tuple[torch.Tensor, Any]], x: torch.Tensor,
              splits: list[int]) -> tuple[torch.Tensor, Any]:
    """``module(chunk, state) -> (y, state)`` called on ``x`` (batch, time, ...) cut along time
    into chunks of the sizes ``splits`` (summing to time), the state carried from a None start:
    the outputs joined along time, (batch, time, ...), and the state after the last chunk.
    Unlike :func:`run_chunked`, outputs may carry feature axes after time."""
    parts, state = [], None
    for chunk in x.split(splits, dim=1):
        y, state = module(chunk, state)
        parts.append(y)
    return torch.cat(parts, dim=1), state


def sine_loops(amplitudes: list[float], periods: int = 3, n: int = 128) -> torch.Tensor:
    """Rows of float64 cosines of the given amplitudes (e.g. flux density, T), from the
    positive tip, ``periods`` periods of n samples: (rows, periods n)."""
    t = torch.arange(periods * n, dtype=torch.float64) / n
    return torch.stack([b * torch.cos(2 * math.pi * t) for b in amplitudes])


def net_of(ops: list, dtype: torch.dtype, x: torch.Tensor) -> InverseHysteresisNet:
    """A seeded network over ``ops`` with its normalization fitted to (x, tanh x)."""
    torch.manual_seed(0)
    net = InverseHysteresisNet(ops, hidden=6).to(dtype)
    net.fit_normalization(x.to(dtype), torch.tanh(x.to(dtype)))
    return net


def assert_streams_as_eager(net: InverseHysteresisNet, x: torch.Tensor, atol: float,
                            limits: tuple[float, float] = (-100.0, 100.0)) -> None:
    """A :class:`StreamingCompensator` of ``net`` (command limits wide enough not to act)
    equals the network's sequence path on ``x`` within ``atol``."""
    from torchhys.deploy.streaming import StreamingCompensator

    with torch.no_grad():
        y, _ = net(x)
        u = StreamingCompensator(net, limits=limits, **RAW)(x)
    torch.testing.assert_close(u, y, rtol=0, atol=atol)


def assert_torchscript_as_eager(net: InverseHysteresisNet, x: torch.Tensor, path: Path,
                                atol: float, limits: tuple[float, float] = (-50.0, 50.0)
                                ) -> None:
    """``to_torchscript(net, path)`` loaded back equals the network's sequence path and its
    eager :class:`StreamingCompensator` on ``x`` within ``atol`` times the output's scale (at
    least 1), in x's shape and dtype, and stepping it sample by sample from a reset equals
    its sequence call exactly."""
    import warnings

    from torchhys.deploy.export import to_torchscript
    from torchhys.deploy.streaming import StreamingCompensator

    to_torchscript(net, path, limits=limits, **RAW)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"`torch\.jit\.load` is deprecated",
                                category=DeprecationWarning)
        loaded = torch.jit.load(str(path))
    with torch.no_grad():
        ref, _ = net(x)
        eager = StreamingCompensator(net, limits=limits, **RAW)(x)
    seq = loaded(x)
    assert seq.shape == x.shape and seq.dtype == x.dtype
    tol = atol * max(1.0, float(ref.abs().max()))
    torch.testing.assert_close(seq, ref, rtol=0, atol=tol)
    torch.testing.assert_close(seq, eager, rtol=0, atol=tol)
    loaded.reset()
    steps = torch.stack([loaded.step(xt) for xt in x.unbind(-1)], dim=-1)
    torch.testing.assert_close(steps, seq, rtol=0, atol=0)


def assert_aoti_as_eager(net: InverseHysteresisNet, x: torch.Tensor, path: Path,
                         atol: float = 1e-12) -> None:
    """``to_aoti(net, path)`` (batch 1, command limits wide enough not to act) stepped over
    the sequence ``x`` (time,) equals the network's sequence path within ``atol``."""
    from torchhys.deploy.export import load_aoti, to_aoti

    to_aoti(net, path, limits=(-1e6, 1e6), **RAW)
    stepper = load_aoti(path)
    with torch.no_grad():
        expected = net(x)[0]
    out = torch.cat([stepper.step(v.reshape(1)).reshape(-1) for v in x])
    torch.testing.assert_close(out.double(), expected, rtol=0, atol=atol)


def step_loop(step: Callable[[torch.Tensor, Any], tuple[torch.Tensor, Any]], x: torch.Tensor,
              state: Any) -> tuple[torch.Tensor, Any]:
    """An operator step (eager, scripted or exported) run over x (batch, time) from
    ``state``: its features (batch, time, n_outputs) and its final state."""
    outs = []
    for xt in x.unbind(1):
        f, state = step(xt.unsqueeze(1), state)
        outs.append(f)
    return torch.stack(outs, 1), state


def scripted_run(step: torch.nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, list]:
    """An operator step scripted by TorchScript, stepped over x (batch, time) from its
    initial state: its features (batch, time, n_outputs) and its final state."""
    import warnings

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"`torch\.jit\.script` is deprecated",
                                category=DeprecationWarning)
        scripted = torch.jit.script(step)
    return step_loop(scripted, x, step.initial_state(x[:, :1]))


def steps_of(comp: StreamingCompensator, x: torch.Tensor) -> torch.Tensor:
    """The compensator stepped sample by sample from a reset: (batch, time)."""
    comp.reset()
    return torch.stack([comp.step(xt) for xt in x.unbind(-1)], dim=-1)


# --- references -------------------------------------------------------------------------------


def per_op_features(comp: StreamingCompensator, x: torch.Tensor) -> torch.Tensor:
    """Each operator step's output (batch, time, features), as the compensator runs it."""
    return torch.cat([slot.step.run(x) for slot in comp.slots], dim=-1)


def play_reference(x: np.ndarray, widths: np.ndarray, y0: np.ndarray | None = None) -> np.ndarray:
    """Plain float64 loop of the play operator: x (B, T), widths (N,) -> (B, T, N)."""
    x = np.asarray(x, dtype=np.float64)
    widths = np.asarray(widths, dtype=np.float64)
    B, T = x.shape
    N = widths.shape[0]
    state = np.zeros((B, N)) if y0 is None else np.broadcast_to(y0, (B, N)).astype(np.float64)
    y = np.empty((B, T, N))
    for b in range(B):
        s = state[b].copy()
        for t in range(T):
            for n in range(N):
                r = widths[n] / 2.0
                s[n] = min(x[b, t] + r, max(x[b, t] - r, s[n]))
            y[b, t] = s
    return y


def load_benchmark(file_name: str) -> types.ModuleType:
    """A script of benchmarks/ imported as a module (the folder is not a package)."""
    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location(Path(file_name).stem,
                                                  root / "benchmarks" / file_name)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def loop_data(T: int = 600) -> tuple[torch.Tensor, torch.Tensor]:
    """The training loop: x = sin(t) (1 + 0.1 t), y = x + 0.2 cos t, t in [0, 2 pi]."""
    t = torch.linspace(0.0, 2 * torch.pi, T, dtype=torch.float64)
    x = torch.sin(t) * (1 + 0.1 * t)
    return x[None], (x + 0.2 * torch.cos(t))[None]


def loop_net(operators: list, hidden: int = 8, activation: str = "sigmoid"
             ) -> InverseHysteresisNet:
    """A float64 network on ``loop_data`` (normalization, ranges and direction recorded) whose
    output layer is the ridge least-squares fit of the target
    (:func:`torchhys.init.least_squares_output`): a model that follows it (the C and ONNX
    exports' parity tests)."""
    torch.manual_seed(0)
    net = InverseHysteresisNet(operators, hidden=hidden, activation=activation).double()
    x, y = loop_data()
    net.fit_normalization(x, y)
    least_squares_output(net, x, y)
    return net
