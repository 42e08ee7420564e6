"""Benchmark: play-operator forward+backward against the naive per-sample autograd loop.

B = 32 sequences, N = 15 operators, float32, T = 1e4 and 1e5. For each method the
forward+backward of ``(y * probe).sum()`` is timed (median of several repeats) and
its peak memory measured as the growth of the process's peak resident set size
over the resident size before the call, each method in a fresh subprocess.

Methods:
    naive   per-sample loop of torch.minimum/torch.maximum over x.unbind(1), autograd
    scan    torchhys.functional.backlash with the pure-torch blocked scan
    kernel  torchhys.functional.backlash with the compiled CPU kernel (the default)

Usage: python benchmarks/backlash.py [--quick] [--repeats N]
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time

import torch

B, N = 32, 15


def naive_backlash(x: torch.Tensor, widths: torch.Tensor, y0: torch.Tensor) -> torch.Tensor:
    r = 0.5 * widths
    s = y0
    out = []
    for x_t in x.unbind(1):
        x_t = x_t.unsqueeze(-1)
        s = torch.minimum(x_t + r, torch.maximum(x_t - r, s))
        out.append(s)
    return torch.stack(out, 1)


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()


def run_one(method: str, T: int, repeats: int) -> dict:
    from torchhys.functional import backlash
    from torchhys.functional._kernel import kernel_available, kernel_enabled

    torch.manual_seed(0)
    x = torch.randn(B, T).cumsum(1).mul_(0.05).requires_grad_()
    widths = torch.linspace(1 / 6, 15 / 6, N).requires_grad_()
    y0 = torch.zeros(B, N)
    probe = torch.randn(B, T, N)

    def step() -> None:
        if method == "naive":
            y = naive_backlash(x, widths, y0)
        else:
            with kernel_enabled(method == "kernel"):
                y = backlash(x, widths, state=y0)
        (y * probe).sum().backward()
        x.grad = None
        widths.grad = None

    if method == "kernel" and not kernel_available(x):
        return {"method": method, "T": T, "error": "no compiled kernel"}
    # warm-up on a short sequence (kernel compilation, allocator)
    base = _rss_bytes()
    t0 = time.perf_counter()
    step()
    first = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - base
    times = [first]
    for _ in range(repeats - 1):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    return {
        "method": method,
        "T": T,
        "median_s": statistics.median(times),
        "repeats": len(times),
        "peak_bytes": peak,
        "output_bytes": B * T * N * 4,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="T = 1e4 only")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--one", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one[0], int(args.one[1]), args.repeats)))
        return
    lengths = [10_000] if args.quick else [10_000, 100_000]
    rows = []
    for T in lengths:
        for method in ("naive", "scan", "kernel"):
            repeats = 2 if (method == "naive" and T >= 100_000) else args.repeats
            out = subprocess.run(
                [sys.executable, __file__, "--one", method, str(T), "--repeats", str(repeats)],
                check=True, capture_output=True, text=True,
            )
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"play operators, forward+backward, B={B}, N={N}, float32, "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads\n")
    print("| T | method | median time (s) | speed-up vs naive | peak memory (MB) "
          "| peak / output |")
    print("|---|---|---|---|---|---|")
    for T in lengths:
        ref = next(r for r in rows if r["T"] == T and r["method"] == "naive")
        for r in (r for r in rows if r["T"] == T):
            if "error" in r:
                print(f"| {T:.0e} | {r['method']} | {r['error']} | | | |")
                continue
            print(
                f"| {T:.0e} | {r['method']} | {r['median_s']:.3f} "
                f"| {ref['median_s'] / r['median_s']:.1f}x "
                f"| {r['peak_bytes'] / 2**20:.0f} | {r['peak_bytes'] / r['output_bytes']:.2f} |"
            )


if __name__ == "__main__":
    main()
