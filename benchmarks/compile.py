"""Benchmark: a training step eager against ``torch.compile`` (default and
``mode="max-autotune-no-cudagraphs"``).

A training step is forward, an MSE loss, backward and an Adam step, on a batch of B = 32
random-walk sequences of T samples (1e4 by default), for two models:

    operators+lstm  a learnable Backlash (8 plays) and a learnable PrandtlIshlinskii (8 plays)
                    feeding an nn.LSTM (hidden 16) and a linear readout
    recommended     the recommended network (configs/compensator.yaml): the re-based EIHO
                    (rule "recent", output "branch") and 16 play operators of the input,
                    64 sigmoid units (torchhys.InverseHysteresisNet)

in float32 and float64, on the CPU and on CUDA where one is present (else its rows say why
they are skipped). Each time is the median over repeats after two warm-up steps, the repeats
interleaved (one step of each mode in turn); the ratio compiled/eager is of one run; the
first step's time includes the compile. The graph breaks are those
``torch._dynamo.explain`` gives for the model's forward (its break reasons): in all, and
inside torchhys's own code (a break whose stack passes through the package). Dynamo does not
trace ``nn.LSTM`` by default (torch's "step_unsupported" break: the LSTM runs eagerly);
``--allow-rnn`` turns on torch's experimental RNN support (``torch._dynamo.config.allow_rnn``).

Usage: python benchmarks/compile.py [--samples 10000] [--repeats 5] [--threads 1]
                                    [--dtypes float32,float64] [--models ...] [--modes ...]
                                    [--allow-rnn]
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor, nn

B = 32
MODES = {"eager": None, "compile": "default", "max-autotune": "max-autotune-no-cudagraphs"}
"""The rows of each model: eager, ``torch.compile(model)``, ``torch.compile(model,
mode="max-autotune-no-cudagraphs")``."""
PACKAGE = str(Path(__file__).resolve().parents[1] / "torchhys")


class OperatorsLSTM(nn.Module):
    """A learnable Backlash and PrandtlIshlinskii feeding an LSTM and a linear readout."""

    def __init__(self, n: int = 8, hidden: int = 16) -> None:
        super().__init__()
        from torchhys import Backlash, PrandtlIshlinskii

        widths = torch.linspace(0.05, 0.8, n)
        self.backlash = Backlash(widths, learnable=True)
        self.pi = PrandtlIshlinskii(widths, learnable=True)
        self.lstm = nn.LSTM(1 + n + 1, hidden, batch_first=True)
        self.readout = nn.Linear(hidden, 1)

    def forward(self, x: Tensor) -> Tensor:
        plays, _ = self.backlash(x)
        pi, _ = self.pi(x)
        h, _ = self.lstm(torch.cat([x[..., None], plays, pi[..., None]], -1))
        return self.readout(h)[..., 0]


class Recommended(nn.Module):
    """The recommended network (configs/compensator.yaml's model), its output alone."""

    def __init__(self) -> None:
        super().__init__()
        from torchhys import Backlash, InverseHysteresisNet

        eiho = {"name": "eiho", "a": 1.0, "rule": "recent", "output": "branch", "threshold": 0.0}
        self.net = InverseHysteresisNet([eiho, Backlash(torch.linspace(0.0, 0.8, 16))],
                                        hidden=64, activation="sigmoid")

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)[0]


MODELS: dict[str, Callable[[], nn.Module]] = {"operators+lstm": OperatorsLSTM,
                                              "recommended": Recommended}


def data(samples: int, dtype: torch.dtype, device: str) -> tuple[Tensor, Tensor]:
    g = torch.Generator().manual_seed(0)
    x = (torch.randn(B, samples, generator=g) * 0.05).cumsum(1).clamp(-1, 1)
    y = torch.tanh(2 * x) + 0.1 * x
    return x.to(dtype=dtype, device=device), y.to(dtype=dtype, device=device)


def graph_breaks(model: nn.Module, x: Tensor) -> tuple[int, int]:
    """``(all, inside torchhys)``: the graph breaks ``torch._dynamo.explain`` finds in
    ``model(x)``."""
    torch._dynamo.reset()
    explanation = torch._dynamo.explain(model)(x)
    ours = sum(1 for r in explanation.break_reasons
               if any(f.filename.startswith(PACKAGE) for f in r.user_stack))
    torch._dynamo.reset()
    return len(explanation.break_reasons), ours


def stepper(model: nn.Module, x: Tensor, y: Tensor, mode: str | None) -> Callable[[], None]:
    """One training step (forward, MSE, backward, Adam step) of ``model``, compiled in
    ``mode`` (None: eager)."""
    forward = model if mode is None else torch.compile(model, mode=mode)
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)

    def step() -> None:
        opt.zero_grad(set_to_none=True)
        loss = torch.nn.functional.mse_loss(forward(x), y)
        loss.backward()
        opt.step()
    return step


def time_steps(steps: dict[str, Callable[[], None]], repeats: int, device: str
               ) -> dict[str, tuple[float, float]]:
    """``(median, first)``: the median seconds of each step after two warm-up calls each,
    and the first call's (which compiles);
    the repeats interleave the steps (one of each in turn), so that a change in the machine's
    load falls on all of them."""
    def timed(step: Callable[[], None]) -> float:
        if device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        step()
        if device == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - t0

    first = {name: timed(step) for name, step in steps.items()}
    for step in steps.values():
        timed(step)
    times: dict[str, list[float]] = {name: [] for name in steps}
    for _ in range(repeats):
        for name, step in steps.items():
            times[name].append(timed(step))
    return {name: (statistics.median(t), first[name]) for name, t in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1,
                        help="CPU threads (1: a shared machine's other loads do not stall "
                             "torch's thread pool)")
    parser.add_argument("--dtypes", default="float32,float64")
    parser.add_argument("--models", default=",".join(MODELS))
    parser.add_argument("--modes", default=",".join(MODES))
    parser.add_argument("--devices", default="cpu,cuda")
    parser.add_argument("--allow-rnn", action="store_true",
                        help="torch._dynamo.config.allow_rnn: Dynamo traces nn.LSTM")
    args = parser.parse_args()
    torch._dynamo.config.allow_rnn = args.allow_rnn
    if args.threads:
        torch.set_num_threads(args.threads)
    modes = args.modes.split(",")
    print(f"B = {B}, T = {args.samples}, median of {args.repeats} steps after 2 warm-up "
          f"(interleaved); torch {torch.__version__}, {torch.get_num_threads()} CPU threads, "
          f"allow_rnn={args.allow_rnn}\n")
    print("| model | dtype | device | mode | step (s) | compiled/eager | first step (s) | "
          "graph breaks (all / in torchhys) |")
    print("|---|---|---|---|---|---|---|---|")
    for device in args.devices.split(","):
        if device == "cuda" and not torch.cuda.is_available():
            print(f"| all | all | cuda | skipped: no CUDA device (torch {torch.__version__}) "
                  "| | | | |")
            continue
        for name in args.models.split(","):
            for dtype_name in args.dtypes.split(","):
                dtype = getattr(torch, dtype_name)
                torch.manual_seed(0)
                model = MODELS[name]().to(dtype=dtype, device=device)
                x, y = data(args.samples, dtype, device)
                breaks = "{} / {}".format(*graph_breaks(model, x))
                torch._dynamo.reset()
                steps = {}
                for mode in modes:  # a copy each, from the same parameters
                    steps[mode] = stepper(copy.deepcopy(model), x, y, MODES[mode])
                seconds = time_steps(steps, args.repeats, device)
                eager = seconds.get("eager")
                for mode in modes:
                    median, first = seconds[mode]
                    ratio = f"{median / eager[0]:.2f}" if eager else ""
                    shown = "" if mode == "eager" else breaks
                    print(f"| {name} | {dtype_name} | {device} | {mode} | {median:.4f} | "
                          f"{ratio} | {first:.1f} | {shown} |", flush=True)
                torch._dynamo.reset()

if __name__ == "__main__":
    main()
