"""Benchmark: the stop-type Prandtl-Ishlinskii model, forward + backward, and its fit.

T = 1e5 samples, N = 20 stops of K = 4 segments (the candidate of configs/measured.yaml),
batch 1, float32. For each method the time (median of several repeats) and the peak memory
(growth of the process's peak resident set size, each method in a fresh subprocess).

Methods:
    forward    StopPrandtlIshlinskii.forward, no gradient
    backward   forward + backward of ``(y * probe).sum()`` to the slopes W and the input x
    loop       the same through a per-sample Python loop of play_step with autograd (the
               naive layout), on the first 1e4 samples, time scaled to T
    fit        fit_stop_pi (float64 normal equations, chunked, + Lawson-Hanson NNLS)
    step       the scripted per-sample StopPIStep, time per sample (1e4 samples)
    inverse    StopPIInverse.forward (the exact inverse, a loop over time) of the model's
               output, no gradient, on the first 1e4 samples, time scaled to T
    inverse_step  the scripted per-sample StopPIInverseStep, time per sample (1e4 samples)

Usage: python benchmarks/stop_pi.py [--repeats N] [--threads N] [--length T]
"""

from __future__ import annotations

from statistics import median

import torch
from _isolated import main_or_run, measure, walk_signal

N, K = 20, 4
METHODS = ("forward", "backward", "loop", "fit", "step", "inverse", "inverse_step")
LOOP = 10_000


def run_one(method: str, T: int, repeats: int) -> dict:
    from torchhys import StopPrandtlIshlinskii, fit_stop_pi
    from torchhys.functional import play_step
    from torchhys.functional.stop_pi import stop_characteristic
    from torchhys.identification.fitting import play_width_grid

    x = walk_signal(T)
    r = play_width_grid(x, N, power=2.0)
    torch.manual_seed(1)
    model = StopPrandtlIshlinskii(r, torch.rand(N, K), linear_weight=0.1, learnable=True)
    probe = torch.randn_like(x)
    xg = x.clone().requires_grad_()
    state: dict = {}

    def call() -> None:
        if method == "forward":
            with torch.no_grad():
                model(x)
        elif method == "backward":
            (model(xg)[0] * probe).sum().backward()
        elif method == "loop":
            p = torch.zeros(1, N)
            out = []
            for t in range(LOOP):
                u = xg[:, t:t + 1] - model.center
                p = play_step(u, r, p)
                out.append(model.offset + model.linear_weight * u
                           + stop_characteristic((u - p).unsqueeze(1), r, model.weights))
            (torch.cat(out, 1) * probe[:, :LOOP]).sum().backward()
        elif method == "fit":
            if "y" not in state:
                with torch.no_grad():
                    state["y"] = model(x)[0].double()
            fit_stop_pi(x.double(), state["y"], r.double(), segments=K, ridge=1e-6)
        elif method == "step":
            if "step" not in state:
                state["step"] = torch.jit.script(model.streaming_step(torch.float32))
            step, s = state["step"], [torch.zeros(1, N)]
            with torch.no_grad():
                for xt in x[:, :LOOP].unbind(1):
                    _, s = step(xt.unsqueeze(1), s)
        elif method in ("inverse", "inverse_step"):
            if "y" not in state:
                with torch.no_grad():
                    state["y"] = model(x)[0][:, :LOOP]
                    inverse = model.inverse()
                state["inverse"] = (inverse if method == "inverse" else
                                    torch.jit.script(inverse.streaming_step(torch.float32)))
            with torch.no_grad():
                if method == "inverse":
                    state["inverse"](state["y"])
                else:
                    s = [torch.zeros(1, N)]
                    for yt in state["y"].unbind(1):
                        _, s = state["inverse"](yt.unsqueeze(1), s)
        model.zero_grad()
        xg.grad = None

    times, peak = measure(call, repeats)
    seconds = median(times) * (T / LOOP if method in ("loop", "inverse") else 1.0)
    per = (seconds / T if method == "inverse" else seconds / LOOP if method.endswith("step")
           else None)
    per = None if per is None else per * 1e6
    return {"method": method, "T": T, "median_s": seconds, "repeats": len(times),
            "peak_bytes": peak, "us_per_sample": per}


def main() -> None:
    ran = main_or_run(__doc__, __file__, METHODS, run_one,
                      few=("fit", "loop", "inverse", "inverse_step"))
    if ran is None:
        return
    args, rows = ran
    threads = args.threads or torch.get_num_threads()
    print(f"stop-type PI, T={args.length}, N={N} stops x K={K} segments, batch 1, float32 "
          f"(fit: float64), torch {torch.__version__}, {threads} threads\n")
    loop = next(r["median_s"] for r in rows if r["method"] == "loop")
    print("| method | median time (s) | peak memory (MB) | loop / backward |")
    print("|---|---|---|---|")
    for r in rows:
        label = r["method"]
        if r["us_per_sample"] is not None:
            label += f" ({r['us_per_sample']:.1f} us/sample)"
        ratio = f"{loop / r['median_s']:.0f}x" if r["method"] == "backward" else ""
        print(f"| {label} | {r['median_s']:.3f} | {r['peak_bytes'] / 2**20:.0f} | {ratio} |")


if __name__ == "__main__":
    main()
