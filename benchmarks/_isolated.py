"""Benchmarks that time each method in a fresh subprocess (so that the peak resident set
size is the method's own): the command line, the timing loop and the runner they share.

A script defines ``run_one(method, T, repeats) -> dict`` (built on :func:`measure`) and calls
:func:`main_or_run` with its methods; the parent process runs ``script --one METHOD`` for
each and collects the JSON rows.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from collections.abc import Callable, Sequence

import torch


def rss_bytes() -> int:
    """The resident set size of this process now."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize()


def walk_signal(T: int) -> torch.Tensor:
    """A seeded test input (1, T), float32: a random-phase sine with a slow envelope."""
    torch.manual_seed(0)
    t = torch.arange(T, dtype=torch.float64)
    walk = (0.05 * torch.randn(T, dtype=torch.float64)).cumsum(0)
    x = (0.6 + 0.4 * torch.sin(t / T * 12.0)) * torch.sin(0.01 * t + walk)
    return x.float().unsqueeze(0)


def measure(call: Callable[[], None], repeats: int) -> tuple[list[float], int]:
    """Wall times of ``repeats`` calls, and the growth of the peak resident set size over the
    resident size before the first call (bytes)."""
    base = rss_bytes()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        call()
        times.append(time.perf_counter() - t0)
    return times, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 - base


def main_or_run(doc: str, script: str, methods: Sequence[str],
                run_one: Callable[[str, int, int], dict],
                few: Sequence[str] = ()) -> tuple[argparse.Namespace, list[dict]] | None:
    """Parse ``--repeats --threads --length``; in a child (``--one METHOD``) print its row and
    return None, else run every method in its own subprocess (at most 3 repeats for those in
    ``few``) and return the arguments and the rows, in order."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    parser.add_argument("--length", type=int, default=100_000)
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.one:
        print(json.dumps(run_one(args.one, args.length, args.repeats)))
        return None
    rows = []
    for method in methods:
        repeats = min(args.repeats, 3) if method in few else args.repeats
        out = subprocess.run(
            [sys.executable, script, "--one", method, "--length", str(args.length),
             "--repeats", str(repeats), "--threads", str(args.threads)],
            check=True, capture_output=True, text=True,
        )
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    return args, rows
