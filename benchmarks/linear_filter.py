"""Benchmark: lfilter forward+backward against a per-sample autograd loop of the DF2T step.

Batch 8, float64, T = 1e4 and 1e5, filter orders 2 and 4 (poles of modulus 0.9). For each
method the forward+backward of ``(y * probe).sum()`` with respect to x, b and a is timed;
the table gives the median of the repeats and the speed-up over the naive loop.

Methods:
    naive   a Python loop of torchhys.functional.linear_filter.df2t_step over x.unbind(1),
            autograd through every step
    scan    lfilter with the pure-torch chunked scan (the fallback without the kernel)
    kernel  lfilter with the compiled C kernel and its fused adjoint (the default on the CPU)

Usage: python benchmarks/linear_filter.py [--quick] [--repeats N] [--threads N]

``--threads`` sets torch's intra-op threads (default 1: on a small machine shared with other
jobs, a second thread that waits for a busy core makes every tensor operation slower).
The measured table is in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from torchhys.functional._filter_kernel import filter_kernel_available, filter_kernel_enabled
from torchhys.functional.linear_filter import df2t_step, lfilter

BATCH = 8


def naive_lfilter(x: torch.Tensor, b: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """The per-sample DF2T loop (a[0] = 1), autograd through every step."""
    z = x.new_zeros(x.shape[0], a.shape[0] - 1)
    out = []
    for x_t in x.unbind(1):
        y, z = df2t_step(x_t.unsqueeze(1), z, b, a[1:])
        out.append(y)
    return torch.cat(out, 1)


def problem(T: int, order: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    x = torch.randn(BATCH, T, generator=g, dtype=torch.float64).requires_grad_()
    angles = np.linspace(0.2, 2.5, order // 2)
    poles = np.concatenate([0.9 * np.exp(1j * angles), 0.9 * np.exp(-1j * angles)])
    a = torch.tensor(np.poly(poles).real, dtype=torch.float64).requires_grad_()
    b = torch.randn(order + 1, generator=g, dtype=torch.float64).requires_grad_()
    probe = torch.randn(BATCH, T, generator=g, dtype=torch.float64)
    return x, b, a, probe


def time_method(method: str, T: int, order: int, repeats: int) -> float:
    """Median seconds of forward + backward."""
    x, b, a, probe = problem(T, order)

    def run() -> None:
        if method == "naive":
            y = naive_lfilter(x, b, a)
        else:
            with filter_kernel_enabled(method == "kernel"):
                y = lfilter(x, b, a)[0]
        (y * probe).sum().backward()
        x.grad = b.grad = a.grad = None

    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="T = 1e4 only")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    methods = ["naive", "scan"] + (["kernel"] if filter_kernel_available(torch.zeros(1)) else [])
    time_method("kernel" if "kernel" in methods else "scan", 100, 2, 2)  # warm-up, compile
    lengths = [10_000] if args.quick else [10_000, 100_000]
    print(f"lfilter forward+backward, batch {BATCH}, float64, torch {torch.__version__}, "
          f"{torch.get_num_threads()} thread(s); median of {args.repeats} repeats "
          "(naive at T = 1e5: 3)\n")
    print("| T | order | naive (ms) | scan (ms) | kernel (ms) | naive / scan "
          "| naive / kernel |")
    print("|---|---|---|---|---|---|---|")
    for T in lengths:
        for order in (2, 4):
            ms = {}
            for method in methods:
                repeats = 3 if method == "naive" and T >= 100_000 else args.repeats
                ms[method] = 1e3 * time_method(method, T, order, repeats)
            kernel = ms.get("kernel", float("nan"))
            print(f"| {T:.0e} | {order} | {ms['naive']:.1f} | {ms['scan']:.1f} | {kernel:.1f} "
                  f"| {ms['naive'] / ms['scan']:.0f}x | {ms['naive'] / kernel:.0f}x |")


if __name__ == "__main__":
    main()
