"""Per-sample step latency of the deployed compensator: Python, TorchScript, C++, AOTI, C, ONNX.

    python benchmarks/latency.py [--samples 5000] [--rounds 5] [--skip-aoti] [--c-only]
    python benchmarks/latency.py --adaptive   (the C step static, RLS, NLMS:
                                               benchmarks/latency_adaptive.py)

Four compensators (weights do not matter for latency): the compensation benchmark's deployed
EIHO network (``EIHO(a, rule="recent", output="branch")`` + 16 play operators of the input,
64 sigmoid units), the same with the level dominant-rule EIHO (its configuration before
``output="branch"``), a network of the 16 play operators alone, and the B-H compensator of
``configs/measured.yaml``'s last candidate (40 stops through 4-segment characteristics
beside the exact inverse of a 40-level graded Preisach model, one affine readout); then, in
C rows only, conditioned forms taking one and two operating conditions: the B-H
compensator's operators under a :class:`~torchhys.conditions.ScheduledReadout` of degree 2
(fitted on a synthetic record whose loop moves with the conditions), and the deployed EIHO
network's operators in an :class:`~torchhys.InverseHysteresisNet` of 64 sigmoid units with
``n_conditions`` (its features times a Legendre basis of the conditions of total degree
``--condition-degree``, default 1; random weights, the normalization fitted on that record).
The conditions are a slow signal inside their training ranges, passed to the step at every
sample. ``--nets`` picks some (indices in this order, 0 to 7); with a conditioned net's
unconditioned one in the run, the conditioned row's median is also printed as a ratio to the
unconditioned one's, path by path (the ratio of the medians, and the range of the rounds'
ratios).
Each path runs ``step`` on a batch of one, one thread;
the C++ rows use deploy/cpp/controller (built on first use, ``--rate 0``), which times each
step with a steady clock (TorchScript: the module frozen, ``step_explicit`` with the state
held by the program; AOTI: ``boxed_run``, single-threaded runner). The C rows: the C99
step of :func:`torchhys.deploy.c.to_c` in a C harness compiled here (``cc -std=c99 -O2``, the
compiler's default target, and ``-O3 -march=native``), which times each step with
``clock_gettime(CLOCK_MONOTONIC)`` after a warm-up pass; ``--c-only`` runs these alone (no
libtorch, no AOTI compile). ONNX Runtime (through ``torchhys.deploy.export_onnx``'s
stepper, from Python, one thread) where that module and onnxruntime are installed. Every
model is in ``--dtype`` (default float64, the C step's). Every row runs
``--rounds`` times, the rows interleaved, so that a change of load on a shared CPU touches
all of them; the table gives the median of the round medians with their range, and the
median of the round p99s, in microseconds.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from torchhys import (
    EIHO,
    Backlash,
    InverseHysteresisNet,
    Preisach,
    PreisachInverse,
    StopPrandtlIshlinskii,
)
from torchhys.conditions import ScheduledReadout
from torchhys.deploy.export import load_aoti, load_torchscript, to_aoti, to_torchscript
from torchhys.deploy.streaming import StreamingCompensator

ROOT = Path(__file__).resolve().parents[1]


def controller() -> Path:
    src = [ROOT / "deploy" / "cpp" / "controller.cpp", ROOT / "deploy" / "cpp" / "build.sh"]
    h = hashlib.sha256(torch.__version__.encode())
    for s in src:
        h.update(s.read_bytes())
    out = ROOT / "build" / "cpp-test" / h.hexdigest()[:16]
    if not (out / "controller").exists():
        subprocess.run(["bash", str(src[1]), str(out)], check=True,
                       env=dict(os.environ, PYTHON=sys.executable))
    return out / "controller"


C_PRELUDE = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include "comp.h"

static int cmp(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static double now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec * 1e9 + (double)t.tv_nsec;
}
"""
"""The C timers' includes, sort comparator and clock."""

C_TIMER = C_PRELUDE + r"""
/* timer REF.bin: steps the compensator over the reference (binary doubles) once untimed,
   then, from a fresh state, once timing every step; prints median_us and p99_us */
int main(int argc, char **argv)
{
    FILE *in;
    long n, i;
    double *x, *t, t0, sink = 0;
    comp_state s;
    if (argc != 2 || !(in = fopen(argv[1], "rb")))
        return 2;
    fseek(in, 0, SEEK_END);
    n = ftell(in) / (long)sizeof(double);
    rewind(in);
    x = malloc((size_t)n * sizeof *x);
    t = malloc((size_t)n * sizeof *t);
    if (!x || !t || fread(x, sizeof *x, (size_t)n, in) != (size_t)n)
        return 3;
    comp_init(&s);
    for (i = 0; i < n; ++i)
        sink += (double)comp_step(&s, (comp_real)x[i]);
    comp_init(&s);
    for (i = 0; i < n; ++i) {
        t0 = now_ns();
        sink += (double)comp_step(&s, (comp_real)x[i]);
        t[i] = now_ns() - t0;
    }
    qsort(t, (size_t)n, sizeof *t, cmp);
    printf("median_us %.4f p99_us %.4f sink %g\n", t[n / 2] / 1e3, t[(long)(0.99 * n)] / 1e3,
           sink);
    return 0;
}
"""

C_TIMER_CONDITIONS = C_PRELUDE + r"""
/* timer REF.bin: the unconditioned timer's loops, the reference's samples being x and its
   comp_N_CONDITIONS conditions (binary doubles, interleaved); the conditions are converted
   to comp_real before the loops and passed to each step */
int main(int argc, char **argv)
{
    FILE *in;
    long n, i, j;
    const long w = 1 + comp_N_CONDITIONS;
    double *x, *t, t0, sink = 0;
    comp_real *c;
    comp_state s;
    if (argc != 2 || !(in = fopen(argv[1], "rb")))
        return 2;
    fseek(in, 0, SEEK_END);
    n = ftell(in) / (long)(w * sizeof(double));
    rewind(in);
    x = malloc((size_t)(n * w) * sizeof *x);
    c = malloc((size_t)(n * comp_N_CONDITIONS) * sizeof *c);
    t = malloc((size_t)n * sizeof *t);
    if (!x || !c || !t || fread(x, sizeof *x, (size_t)(n * w), in) != (size_t)(n * w))
        return 3;
    for (i = 0; i < n; ++i)
        for (j = 0; j < comp_N_CONDITIONS; ++j)
            c[i * comp_N_CONDITIONS + j] = (comp_real)x[i * w + 1 + j];
    comp_init(&s);
    for (i = 0; i < n; ++i)
        sink += (double)comp_step(&s, (comp_real)x[i * w], c + i * comp_N_CONDITIONS);
    comp_init(&s);
    for (i = 0; i < n; ++i) {
        t0 = now_ns();
        sink += (double)comp_step(&s, (comp_real)x[i * w], c + i * comp_N_CONDITIONS);
        t[i] = now_ns() - t0;
    }
    qsort(t, (size_t)n, sizeof *t, cmp);
    printf("median_us %.4f p99_us %.4f sink %g\n", t[n / 2] / 1e3, t[(long)(0.99 * n)] / 1e3,
           sink);
    return 0;
}
"""

#: the C rows' compiler flags
C_FLAGS = {"C, cc -O2": ["-O2"], "C, cc -O3 -march=native": ["-O3", "-march=native"]}


def c_timer(comp: StreamingCompensator, folder: Path, flags: list[str]) -> Path:
    """The compensator's C step (``to_c``, prefix ``comp``) in the timing harness (that of
    the conditions for a conditioned compensator), compiled with ``cc -std=c99 FLAGS`` into
    ``folder``."""
    from torchhys.deploy.c import to_c

    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "comp.c").exists():
        to_c(comp, folder, prefix="comp", dtype=comp.low.dtype)
        (folder / "timer.c").write_text(C_TIMER if comp.n_conditions == 0
                                        else C_TIMER_CONDITIONS)
    exe = folder / ("timer" + "".join(flags).replace("=", "_").replace("-", "_"))
    subprocess.run([os.environ.get("CC", "cc"), "-std=c99", *flags, "-I", str(folder), "-o",
                    str(exe), str(folder / "timer.c"), str(folder / "comp.c"), "-lm"],
                   check=True)
    return exe


def time_c(exe: Path, x: torch.Tensor, tmp: Path,
           conditions: torch.Tensor | None = None) -> tuple[float, float]:
    """The harness's median and p99 (us) over x (time,), and the conditions (time, n) of a
    conditioned compensator beside each sample."""
    ref = tmp / "ref.bin"
    if conditions is None:
        ref.write_bytes(x.to(torch.float64).numpy().tobytes())
    else:
        rows = torch.cat([x.unsqueeze(1), conditions], 1)
        ref.write_bytes(rows.to(torch.float64).contiguous().numpy().tobytes())
    res = subprocess.run([str(exe), str(ref)], capture_output=True, text=True, check=True)
    fields = res.stdout.split()
    values = dict(zip(fields[::2], fields[1::2], strict=False))
    return float(values["median_us"]), float(values["p99_us"])


def onnx_stepper(comp: StreamingCompensator, path: Path):
    """ONNX Runtime's stepper of the compensator (one thread), or None where
    ``torchhys.deploy.export_onnx`` or onnxruntime is missing."""
    try:
        import onnxruntime  # noqa: F401

        from torchhys.deploy.export_onnx import load_onnx, to_onnx
    except ImportError:
        return None
    to_onnx(comp, path)
    return load_onnx(path, threads=1)


def preisach_inverse() -> PreisachInverse:
    """The exact inverse of a Preisach model on 40 levels graded towards 0 over the input's
    range (``configs/measured.yaml``'s last candidate fits one on a B-H loop)."""
    model = Preisach(-70.0, 70.0, 40, scale=7.0)
    with torch.no_grad():
        model.linear.fill_(1.0)
    return model.inverse()


def models() -> dict[str, InverseHysteresisNet]:
    t = torch.linspace(0, 60, 2000)
    y = 70 * torch.sin(t) * torch.exp(-t / 60)
    plays = torch.linspace(0.0, 56.0, 16)
    nets = {
        "re-based EIHO (recent) + 16 plays": InverseHysteresisNet(
            [EIHO(a=0.5, rule="recent", output="branch"), Backlash(plays)], hidden=64),
        "level EIHO (dominant) + 16 plays": InverseHysteresisNet(
            [EIHO(a=0.5, rule="dominant"), Backlash(plays)], hidden=64),
        "16 plays": InverseHysteresisNet(Backlash(plays), hidden=64),
        "40 stops + graded Preisach inverse": InverseHysteresisNet(
            [StopPrandtlIshlinskii(torch.linspace(1.75, 70.0, 40), torch.full((40, 4), 0.01)),
             preisach_inverse()], hidden=1, activation="identity"),
    }
    for net in nets.values():
        net.fit_normalization(y, y / 12)
    return nets


#: the conditioned nets, after those of :func:`models` (C rows only): name, conditions, the
#: index of the unconditioned net of :func:`models` it is compared with
CONDITIONED = (("40 stops + graded Preisach inverse, 1 condition", 1, 3),
               ("40 stops + graded Preisach inverse, 2 conditions", 2, 3),
               ("re-based EIHO (recent) + 16 plays, 1 condition", 1, 0),
               ("re-based EIHO (recent) + 16 plays, 2 conditions", 2, 0))


#: the conditions' training ranges (a coil voltage in V, a temperature in C, say)
CONDITION_RANGES = ((0.0, 2.0), (20.0, 60.0))


def condition_signal(t: torch.Tensor, n: int, phase: float = 0.0) -> torch.Tensor:
    """n slow conditions at times t (time,), each sweeping its range: (time, n)."""
    cols = [lo + (hi - lo) * (0.5 + 0.5 * torch.sin(0.05 * (k + 1) * t + phase + k))
            for k, (lo, hi) in enumerate(CONDITION_RANGES[:n])]
    return torch.stack(cols, 1)


def synthetic(n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Three rows of the models' input x (3, time), n conditions c (3, time, n) sweeping their
    ranges, and a target y (3, time) whose gain, offset and play width move with them."""
    t = torch.linspace(0, 60, 2000)
    x = (70 * torch.sin(t) * torch.exp(-t / 60)).repeat(3, 1)
    c = torch.stack([condition_signal(t, n, phase=2.0 * r) for r in range(3)])
    s = [(c[..., k] - lo) / (hi - lo) for k, (lo, hi) in enumerate(CONDITION_RANGES[:n])]
    s2 = s[1] if n > 1 else torch.zeros_like(s[0])
    play = Backlash(torch.tensor([8.0]))(x)[0][..., 0]
    y = ((1 + 0.3 * s[0] - 0.2 * s2) * x + (0.5 + 0.5 * s[0]) * play) / 24 + 0.5 * s[0] * s2
    return x, c, y


def scheduled(n: int) -> ScheduledReadout:
    """The B-H compensator's operators (fresh ones) under a readout scheduled on n
    conditions (degree 2), fitted on :func:`synthetic`'s record."""
    ops = [StopPrandtlIshlinskii(torch.linspace(1.75, 70.0, 40), torch.full((40, 4), 0.01)),
           preisach_inverse()]
    return ScheduledReadout(ops, n, degree=2).fit(*synthetic(n))


def conditioned_net(n: int, degree: int = 1) -> InverseHysteresisNet:
    """The deployed EIHO network's operators (fresh ones) in a network of 64 sigmoid units
    taking n conditions (a Legendre basis of total degree ``degree``): random weights, the
    normalization (and the conditions' ranges) fitted on :func:`synthetic`'s record."""
    x, c, y = synthetic(n)
    net = InverseHysteresisNet(
        [EIHO(a=0.5, rule="recent", output="branch"), Backlash(torch.linspace(0.0, 56.0, 16))],
        hidden=64, n_conditions=n, condition_degree=degree)
    net.fit_normalization(x, y, conditions=c)
    return net


def reference_times(n: int) -> torch.Tensor:
    """The reference's n sample times."""
    return torch.linspace(0, 100, n)


def reference(n: int) -> torch.Tensor:
    t = reference_times(n)
    return 60 * torch.sin(t) * torch.cos(0.13 * t)


def time_python(step, x: torch.Tensor) -> tuple[float, float]:
    samples = [x[i:i + 1] for i in range(x.numel())]
    with torch.no_grad():
        for s in samples[:200]:
            step(s)
        ts = []
        for s in samples:
            t0 = time.perf_counter_ns()
            step(s)
            ts.append(time.perf_counter_ns() - t0)
    ts.sort()
    return ts[len(ts) // 2] / 1e3, ts[int(0.99 * len(ts))] / 1e3


def time_cpp(binary: Path, model: Path, x: torch.Tensor, tmp: Path) -> tuple[float, float]:
    ref = tmp / "ref.csv"
    ref.write_text("y_ref\n" + "\n".join(f"{v:.9g}" for v in x.tolist()) + "\n")
    res = subprocess.run([str(binary), str(model), str(ref), str(tmp / "out.csv"), "--rate",
                          "0"], capture_output=True, text=True, check=True)
    fields = res.stdout.split()
    values = dict(zip(fields[::2], fields[1::2], strict=False))
    return float(values["median_us"]), float(values["p99_us"])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=5000)
    parser.add_argument("--rounds", type=int, default=5,
                        help="runs of every row, interleaved; the table gives the median of "
                        "their medians and the range (the CPU may be shared)")
    parser.add_argument("--skip-aoti", action="store_true", help="skip the (slow) AOTI compile")
    parser.add_argument("--skip-python", action="store_true", help="C++ rows only")
    parser.add_argument("--nets", type=int, nargs="*", default=None,
                        help="indices of the compensators to time (default: all): 0-3 the "
                        "unconditioned ones, 4 and 5 the B-H compensator scheduled on 1 and 2 "
                        "conditions, 6 and 7 net 0 with 1 and 2 conditions (C rows only)")
    parser.add_argument("--condition-degree", type=int, default=1,
                        help="the Legendre basis's total degree of nets 6 and 7 (default 1)")
    parser.add_argument("--c-only", action="store_true",
                        help="the C rows only (no libtorch, no AOTI compile)")
    parser.add_argument("--skip-onnx", action="store_true", help="no ONNX Runtime row")
    parser.add_argument("--dtype", choices=["float64", "float32"], default="float64",
                        help="the compensators' dtype (default float64)")
    parser.add_argument("--adaptive", action="store_true",
                        help="the C step static against adaptive RLS and NLMS instead "
                        "(benchmarks/latency_adaptive.py)")
    args = parser.parse_args(argv)
    if args.adaptive:
        if str(ROOT) not in sys.path:  # run as a file
            sys.path.insert(0, str(ROOT))
        from benchmarks.latency_adaptive import main as adaptive_main

        adaptive_main(["--samples", str(args.samples), "--rounds", str(args.rounds)])
        return
    if args.samples < 200 or args.rounds < 1 or args.condition_degree < 1:
        parser.error("--samples must be at least 200, --rounds and --condition-degree at "
                     "least 1")
    torch.set_num_threads(1)
    dtype = getattr(torch, args.dtype)
    x = reference(args.samples).to(dtype)
    binary = None if args.c_only else controller()
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        runs: list[tuple[str, str, object]] = []  # (compensator, path, () -> (median, p99))
        for k, (name, net) in enumerate(models().items()):
            if args.nets is not None and k not in args.nets:
                continue
            comp = StreamingCompensator(net.to(dtype), limits=(-10.0, 10.0))
            for path, flags in C_FLAGS.items():
                exe = c_timer(comp, tmp / f"c{k}", flags)
                runs.append((name, path, lambda e=exe: time_c(e, x, tmp)))
            if args.c_only:
                continue
            ts_path = tmp / f"comp{k}.pt"
            to_torchscript(comp, ts_path)
            if not args.skip_onnx:
                ort = onnx_stepper(comp, tmp / f"comp{k}.onnx")
                if ort is not None:
                    def run_onnx(r=ort) -> tuple[float, float]:
                        r.reset()
                        return time_python(r.step, x)

                    runs.append((name, "ONNX Runtime, Python", run_onnx))
            if not args.skip_python:
                runs.append((name, "eager Python", lambda c=comp: time_python(c.step, x)))
                ts = load_torchscript(ts_path)
                runs.append((name, "TorchScript, Python", lambda m=ts: time_python(m.step, x)))
            runs.append((name, "TorchScript, C++",
                         lambda p=ts_path: time_cpp(binary, p, x, tmp)))
            if not args.skip_aoti:
                aoti_path = tmp / f"comp{k}.pt2"
                start = time.perf_counter()
                to_aoti(comp, aoti_path)
                print(f"{name}: AOTI compile {time.perf_counter() - start:.0f} s", flush=True)
                if not args.skip_python:
                    runner = load_aoti(aoti_path)

                    def run_aoti(r=runner) -> tuple[float, float]:
                        r.reset()
                        return time_python(r.step, x)

                    runs.append((name, "AOTI, Python", run_aoti))
                runs.append((name, "AOTI, C++", lambda p=aoti_path: time_cpp(binary, p, x, tmp)))
        for k, (name, n, base) in enumerate(CONDITIONED, start=len(models())):
            if args.nets is not None and k not in args.nets:
                continue
            model = scheduled(n) if base == 3 else conditioned_net(n, args.condition_degree)
            comp = StreamingCompensator(model.to(dtype), limits=(-10.0, 10.0))
            c = condition_signal(reference_times(args.samples), n).to(dtype)
            for path, flags in C_FLAGS.items():
                exe = c_timer(comp, tmp / f"c{k}", flags)
                runs.append((name, path, lambda e=exe, c=c: time_c(e, x, tmp, c)))
        results: list[list[tuple[float, float]]] = [[] for _ in runs]
        for _ in range(args.rounds):
            for j, (_, _, run) in enumerate(runs):
                results[j].append(run())
    print(f"\n{args.samples} steps, batch 1, one thread, {args.dtype}; {args.rounds} interleaved "
          "rounds: median of the round medians (range), median of the round p99s; load "
          f"average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs\n")
    print("| compensator | path | median (us) | p99 (us) |")
    print("|---|---|---|---|")
    for (name, path, _), res in zip(runs, results, strict=True):
        meds = sorted(r[0] for r in res)
        p99 = sorted(r[1] for r in res)[len(res) // 2]
        digits = 2 if meds[-1] < 10 else 1
        spread = (f" ({meds[0]:.{digits}f} to {meds[-1]:.{digits}f})" if len(meds) > 1
                  else "")
        print(f"| {name} | {path} | {meds[len(meds) // 2]:.{digits}f}{spread} | "
              f"{p99:.{digits}f} |")
    ratios(runs, results)


def ratios(runs: list[tuple[str, str, object]],
           results: list[list[tuple[float, float]]]) -> None:
    """Print each conditioned C row's median over its unconditioned net's on the same path
    (the ratio of the medians of the round medians; the range of the rounds' ratios), where
    both are in the run."""
    unconditioned = list(models())
    medians = {(name, path): [r[0] for r in res]
               for (name, path, _), res in zip(runs, results, strict=True)}
    bases = {name: unconditioned[k] for name, _, k in CONDITIONED}
    lines = []
    for (name, path, _), res in zip(runs, results, strict=True):
        if name not in bases or (bases[name], path) not in medians:
            continue
        meds, base = [r[0] for r in res], medians[bases[name], path]
        per_round = sorted(m / b for m, b in zip(meds, base, strict=True))
        ratio = sorted(meds)[len(meds) // 2] / sorted(base)[len(meds) // 2]
        spread = (f" (rounds {per_round[0]:.2f} to {per_round[-1]:.2f})" if len(meds) > 1
                  else "")
        lines.append(f"| {name} | {path} | {ratio:.2f}{spread} |")
    if lines:
        print("\nconditioned over unconditioned (the net without its conditions), medians of "
              "the same run\n")
        print("| compensator | path | ratio |")
        print("|---|---|---|")
        print("\n".join(lines))


if __name__ == "__main__":
    main()
