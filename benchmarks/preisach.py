"""Benchmark: the Preisach model, forward + backward, and its identification.

T = 1e5 samples, n = 31 levels (K = 496 relays), batch 1, float32. For each method the time
(median of several repeats) and the peak memory, measured as the growth of the process's
peak resident set size over the resident size before the first call, each method in a fresh
subprocess.

Methods:
    chunked       torchhys.functional.preisach: forward + backward of ``(y * probe).sum()``
                  with respect to the weights (the custom backward recomputes the relays)
    smooth        the same with smooth relays (tau = 0.05), gradients to weights and x
    materialised  relay_states (batch, time, K) @ weights with autograd: the naive layout
    fit           fit_preisach (float64 normal equations, chunked, + Lawson-Hanson NNLS)
    step          the scripted per-sample PreisachStep, time per sample (1e4 samples)
    inverse       the exact inverse (PreisachInverse, linear term 1) of the model's output:
                  its sequence path, a loop over time, time per sample (1e4 samples)
    inverse_step  the inverse's scripted PreisachInverseStep, time per sample (1e4 samples)

Usage: python benchmarks/preisach.py [--repeats N] [--threads N] [--length T]

References:
    I. D. Mayergoyz, Mathematical Models of Hysteresis, Springer, 1991.
"""

from __future__ import annotations

import warnings
from statistics import median

import torch
from _isolated import main_or_run, measure, walk_signal

N_LEVELS = 31
METHODS = ("chunked", "smooth", "materialised", "fit", "step", "inverse", "inverse_step")
PER_SAMPLE = ("step", "inverse", "inverse_step")


def run_one(method: str, T: int, repeats: int) -> dict:
    from torchhys.functional.preisach import preisach, preisach_grid, relay_states
    from torchhys.preisach import Preisach, fit_preisach

    x = walk_signal(T)
    alpha, beta = preisach_grid(-1.0, 1.0, N_LEVELS)
    K = alpha.numel()
    w = torch.rand(K, requires_grad=True)
    probe = torch.randn_like(x)
    xg = x.clone().requires_grad_()
    y_fit = None
    step = None

    def call() -> None:
        nonlocal y_fit, step
        if method == "chunked":
            (preisach(x, w, alpha, beta) * probe).sum().backward()
        elif method == "smooth":
            (preisach(xg, w, alpha, beta, smooth=0.05) * probe).sum().backward()
        elif method == "materialised":
            ((relay_states(x, alpha, beta) @ w) * probe).sum().backward()
        elif method == "fit":
            if y_fit is None:
                with torch.no_grad():
                    y_fit = preisach(x, w, alpha, beta).double()
            fit_preisach(x.double(), y_fit, lo=-1.0, hi=1.0, n=N_LEVELS)
        elif method in ("step", "inverse_step"):
            if step is None:
                model = Preisach(-1.0, 1.0, N_LEVELS)
                with torch.no_grad():
                    model.linear.fill_(1.0)
                    y_fit = model(x[:, :10_000])[0]
                op = model if method == "step" else model.inverse()
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", DeprecationWarning)
                    eager = op.streaming_step(torch.float32)
                    step = (eager, torch.jit.script(eager))
            xs = x[:, :10_000] if method == "step" else y_fit
            state = step[0].initial_state(xs[:, :1])
            with torch.no_grad():
                for xt in xs.unbind(1):
                    _, state = step[1](xt.unsqueeze(1), state)
        elif method == "inverse":
            if step is None:
                model = Preisach(-1.0, 1.0, N_LEVELS)
                with torch.no_grad():
                    model.linear.fill_(1.0)
                    y_fit = model(x[:, :10_000])[0]
                step = model.inverse()
            with torch.no_grad():
                step(y_fit)
        w.grad = None
        xg.grad = None

    times, peak = measure(call, repeats)
    per = median(times) / 10_000 * 1e6 if method in PER_SAMPLE else None
    return {"method": method, "T": T, "K": K, "median_s": median(times), "min_s": min(times),
            "repeats": len(times), "peak_bytes": peak, "us_per_sample": per,
            "relay_bytes": T * K * 4}


def main() -> None:
    ran = main_or_run(__doc__, __file__, METHODS, run_one, few=("fit", "materialised"))
    if ran is None:
        return
    args, rows = ran
    threads = args.threads or torch.get_num_threads()
    print(f"Preisach, T={args.length}, K={rows[0]['K']} relays (n={N_LEVELS}), batch 1, "
          f"float32 (fit: float64), torch {torch.__version__}, {threads} threads\n")
    print("| method | median time (s) | min time (s) | peak memory (MB) | peak / (T K float32) |")
    print("|---|---|---|---|---|")
    for r in rows:
        label = r["method"]
        if r["us_per_sample"] is not None:
            label += f" ({r['us_per_sample']:.1f} us/sample)"
        print(f"| {label} | {r['median_s']:.3f} | {r['min_s']:.3f} "
              f"| {r['peak_bytes'] / 2**20:.0f} | {r['peak_bytes'] / r['relay_bytes']:.2f} |")


if __name__ == "__main__":
    main()
