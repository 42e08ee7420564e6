"""Per-sample step time of an LSTM and a GRU (one layer and a linear read-out) in torchhys's
generated C against RTNeural's compile-time API, and of a composed model's C step.

RTNeural (github jatinchowdhury18/RTNeural, header-only C++) is read from ``--rtneural DIR``
or ``$RTNEURAL_DIR`` (a checkout of its repository); without it its columns are skipped with
the reason printed. A C++ driver is written to a temporary folder for every model:
``RTNeural::ModelT<double, IN, 1, LSTMLayerT<double, IN, H> | GRULayerT<...>,
DenseT<double, H, 1>>`` with the torch module's weights (loaded as RTNeural's
``torch_helpers`` loads a state dict: the matrices transposed, the GRU's r and z blocks
swapped, the LSTM's two biases summed), compiled with ``c++ -std=c++17 FLAGS`` against the
STL backend (no Eigen or xsimd: ``RTNEURAL_USE_EIGEN`` and ``RTNEURAL_USE_XSIMD`` unset) and,
where the checkout holds ``modules/Eigen``, the Eigen backend (``-DRTNEURAL_USE_EIGEN=1``,
RTNeural's default in its CMake build; ``-DEIGEN_STACK_ALLOCATION_LIMIT=0``: Eigen's check
of fixed-size matrices on the stack stops the 64-unit LSTM in double otherwise). The
torchhys step is :func:`torchhys.deploy.c.to_c` of the module composed by
:func:`torchhys.compose.compose` (the compensator's saturation and NaN guard included; no
input clamp, no direction guard), compiled with ``cc -std=c99 FLAGS``. The flags: ``-O2``
and ``-O3 -march=native``, as benchmarks/latency.py builds the generated C.

Both programs step the same triangle wave (0.8 (i mod 200) / 200 - 0.4), ``steps`` steps
untimed, then ``rounds`` rounds of ``steps`` timed steps each, and print the median round's
time per step; the programs run ``repeats`` times, interleaved, and the table gives the
median. Before timing, each program's first outputs are compared with the torch module's
(float64): the ``max |diff|`` column.
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor, nn

from .accuracy import PlaysGRU, Recurrent

FLAGS = {"-O2": ("-O2",), "-O3 -march=native": ("-O3", "-march=native")}
SIZES = (16, 32, 64)
KINDS = ("lstm", "gru")
CHECK = 400
"""Outputs compared with the torch module before timing."""


def wave(n: int) -> Tensor:
    """The input both programs step: 0.8 (i mod 200) / 200 - 0.4, float64."""
    i = torch.arange(n, dtype=torch.float64)
    return 0.8 * torch.remainder(i, 200) / 200 - 0.4


# --- RTNeural ----------------------------------------------------------------------------


def rtneural_dir(arg: str | os.PathLike | None) -> tuple[Path | None, str]:
    """The RTNeural checkout (``--rtneural``, else ``$RTNEURAL_DIR``), or None and why."""
    where = arg if arg is not None else os.environ.get("RTNEURAL_DIR")
    if not where:
        return None, "no --rtneural DIR and no RTNEURAL_DIR"
    path = Path(where)
    if not (path / "RTNeural" / "RTNeural.h").is_file():
        return None, f"{path} holds no RTNeural/RTNeural.h (expected a checkout of RTNeural)"
    return path, ""


def _vec(v: Tensor) -> str:
    return "{" + ", ".join(f"{float(a):.17g}" for a in v.flatten()) + "}"


def _mat(m: Tensor) -> str:
    return "{" + ", ".join(_vec(r) for r in m) + "}"


def _swap_rz(m: Tensor, h: int) -> Tensor:
    """Columns (last dim) r, z, n -> z, r, n (torch_helpers' ``swap_rz``)."""
    return torch.cat([m[..., h:2 * h], m[..., :h], m[..., 2 * h:]], -1)


_DRIVER = r"""
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <vector>
#include "RTNeural/RTNeural.h"

using T = double;
using Model = RTNeural::ModelT<T, IN, 1, RTNeural::LAYER<T, IN, H>, RTNeural::DenseT<T, H, 1>>;

static Model *make()
{
    static Model m;
    auto &rnn = m.get<0>();
    rnn.setWVals(std::vector<std::vector<T>> WVALS);
    rnn.setUVals(std::vector<std::vector<T>> UVALS);
    rnn.setBVals(BTYPE BVALS);
    auto &out = m.get<1>();
    out.setWeights(std::vector<std::vector<T>> DWEIGHTS);
    std::vector<T> bias DBIAS;
    out.setBias(bias.data());
    m.reset();
    return &m;
}

static inline T input(long i, T *in)
{
    T x = (T)(0.8 * (double)(i % 200) / 200.0 - 0.4);
    for (int k = 0; k < IN; ++k)
        in[k] = x;
    return x;
}

/* driver -c K: the first K outputs; driver N R: N steps untimed, R rounds of N steps,
   prints the median round's ns per step */
int main(int argc, char **argv)
{
    Model &m = *make();
    alignas(32) T in[IN < 2 ? 2 : IN];
    if (argc == 3 && argv[1][0] == '-') {
        long k = std::atol(argv[2]);
        for (long i = 0; i < k; ++i) {
            input(i, in);
            std::printf("%.17g\n", (double)m.forward(in));
        }
        return 0;
    }
    if (argc != 3)
        return 2;
    long n = std::atol(argv[1]), rounds = std::atol(argv[2]);
    volatile T sink = 0;
    for (long i = 0; i < n; ++i) {
        input(i, in);
        sink = sink + m.forward(in);
    }
    std::vector<double> t;
    for (long r = 0; r < rounds; ++r) {
        auto a = std::chrono::steady_clock::now();
        for (long i = 0; i < n; ++i) {
            input(i, in);
            sink = sink + m.forward(in);
        }
        auto b = std::chrono::steady_clock::now();
        t.push_back(std::chrono::duration<double, std::nano>(b - a).count() / (double)n);
    }
    std::sort(t.begin(), t.end());
    std::printf("%.3f\n", t[t.size() / 2]);
    return sink == 12345.0;
}
"""


def rtneural_source(rnn: nn.LSTM | nn.GRU, out: nn.Linear) -> str:
    """The C++ driver of an ``nn.LSTM`` or ``nn.GRU`` (one layer) and its read-out."""
    h, n_in = rnn.hidden_size, rnn.input_size
    w_ih, w_hh = rnn.weight_ih_l0.detach().double(), rnn.weight_hh_l0.detach().double()
    b_ih, b_hh = rnn.bias_ih_l0.detach().double(), rnn.bias_hh_l0.detach().double()
    if isinstance(rnn, nn.LSTM):
        layer, btype = "LSTMLayerT", "std::vector<T>"
        wv, uv, bv = _mat(w_ih.T), _mat(w_hh.T), _vec(b_ih + b_hh)
    else:
        layer, btype = "GRULayerT", "std::vector<std::vector<T>>"
        wv, uv = _mat(_swap_rz(w_ih.T, h)), _mat(_swap_rz(w_hh.T, h))
        bv = _mat(_swap_rz(torch.stack([b_ih, b_hh]), h))
    subs = {"LAYER": layer, "BTYPE": btype, "WVALS": wv, "UVALS": uv, "BVALS": bv,
            "DWEIGHTS": _mat(out.weight.detach().double()),
            "DBIAS": _vec(out.bias.detach().double())}
    src = _DRIVER
    for k, v in subs.items():
        src = src.replace(k, v)
    return f"#define IN {n_in}\n#define H {h}\n" + src


def build_rtneural(rnn: nn.LSTM | nn.GRU, out: nn.Linear, root: Path, folder: Path,
                   flags: Sequence[str], eigen: bool) -> Path:
    """The compiled driver (``c++ -std=c++17``); ``eigen``: RTNeural's Eigen backend."""
    folder.mkdir(parents=True, exist_ok=True)
    src = folder / "driver.cpp"
    src.write_text(rtneural_source(rnn, out))
    exe = folder / ("rtneural" + ("_eigen" if eigen else "_stl") + _tag(flags))
    # Eigen refuses fixed-size matrices over 128 KiB on the stack (the LSTM 64's in double)
    backend = (["-DRTNEURAL_USE_EIGEN=1", "-DEIGEN_STACK_ALLOCATION_LIMIT=0", "-I",
                str(root / "modules" / "Eigen")] if eigen else [])
    subprocess.run([os.environ.get("CXX", "c++"), "-std=c++17", *flags,
                    "-DRTNEURAL_DEFAULT_ALIGNMENT=16", *backend, "-I", str(root),
                    "-o", str(exe), str(src)], check=True, capture_output=True, text=True)
    return exe


def _tag(flags: Sequence[str]) -> str:
    return "".join(flags).replace("=", "_").replace("-", "_")


# --- torchhys's C ------------------------------------------------------------------------

_C_TIMER = r"""
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

/* timer -c K: the first K outputs; timer N R: N steps untimed, R rounds of N steps, prints
   the median round's ns per step */
int main(int argc, char **argv)
{
    comp_state s;
    long n, rounds, i, r;
    double *t, a;
    volatile double sink = 0;
    comp_init(&s);
    if (argc == 3 && argv[1][0] == '-') {
        n = atol(argv[2]);
        for (i = 0; i < n; ++i)
            printf("%.17g\n", (double)comp_step(&s, (comp_real)(0.8 * (double)(i % 200)
                                                                 / 200.0 - 0.4)));
        return 0;
    }
    if (argc != 3)
        return 2;
    n = atol(argv[1]);
    rounds = atol(argv[2]);
    t = malloc((size_t)rounds * sizeof *t);
    if (!t)
        return 3;
    for (i = 0; i < n; ++i)
        sink = sink + (double)comp_step(&s, (comp_real)(0.8 * (double)(i % 200) / 200.0 - 0.4));
    for (r = 0; r < rounds; ++r) {
        a = now_ns();
        for (i = 0; i < n; ++i)
            sink = sink + (double)comp_step(&s, (comp_real)(0.8 * (double)(i % 200) / 200.0
                                                            - 0.4));
        t[r] = (now_ns() - a) / (double)n;
    }
    qsort(t, (size_t)rounds, sizeof *t, cmp);
    printf("%.3f\n", t[rounds / 2]);
    return sink == 12345.0;
}
"""


def composed(model: nn.Module) -> nn.Module:
    """``torchhys.compose.compose`` of a plain module (raises ImportError where absent)."""
    from torchhys.compose import compose

    return compose(model)


def build_c(model: nn.Module, folder: Path, flags: Sequence[str]) -> Path:
    """The C step of the composed ``model`` (float64) in the timer, compiled into ``folder``."""
    from torchhys.deploy.c import to_c

    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / "comp.c").exists():
        to_c(composed(model), folder, prefix="comp", dtype=torch.float64,
             limits=(-1e6, 1e6), input_margin=None, direction="none")
        (folder / "timer.c").write_text(_C_TIMER)
    exe = folder / ("timer" + _tag(flags))
    subprocess.run([os.environ.get("CC", "cc"), "-std=c99", *flags, "-I", str(folder), "-o",
                    str(exe), str(folder / "timer.c"), str(folder / "comp.c"), "-lm"],
                   check=True, capture_output=True, text=True)
    return exe


# --- running -----------------------------------------------------------------------------


def outputs(exe: Path, k: int = CHECK) -> Tensor:
    out = subprocess.run([str(exe), "-c", str(k)], capture_output=True, text=True, check=True)
    return torch.tensor([float(v) for v in out.stdout.split()], dtype=torch.float64)


def reference(model: nn.Module, k: int = CHECK, n_in: int = 1) -> Tensor:
    """The torch model's first ``k`` outputs on the wave (float64); ``n_in`` > 1: the wave
    repeated on every input of the recurrent layer (as the driver feeds it)."""
    x = wave(k)[None]
    with torch.no_grad():
        if n_in == 1:
            return model(x)[0]
        return model.out(model.rnn(x[..., None].expand(-1, -1, n_in))[0])[0, :, 0]


def step_ns(exe: Path, steps: int, rounds: int) -> float:
    out = subprocess.run([str(exe), str(steps), str(rounds)], capture_output=True, text=True,
                         check=True)
    return float(out.stdout.split()[0])


class Entry(NamedTuple):
    """One program to time: its row, its column, how to build it and its reference."""

    row: str
    column: str
    build: Callable[[], Path]
    ref: Tensor


class Result(NamedTuple):
    row: str
    column: str
    ns: float | None
    diff: float | None
    note: str = ""


def time_all(entries: list[Entry], steps: int, rounds: int, repeats: int,
             log: Callable[[str], None] = print) -> list[Result]:
    """Build and check every program, then time them, interleaved, ``repeats`` times."""
    built: list[tuple[Entry, Path, float]] = []
    results = []
    for e in entries:  # the failed ones first, then the timed ones: markdown orders them
        try:
            exe = e.build()
        except (ImportError, ValueError, TypeError, NotImplementedError,
                subprocess.CalledProcessError) as err:
            why = getattr(err, "stderr", None) or str(err)
            log(f"  {e.row} / {e.column}: not built: {why.strip().splitlines()[-1][:200]}")
            results.append(Result(e.row, e.column, None, None, "not built"))
            continue
        got = outputs(exe, len(e.ref))
        built.append((e, exe, float((got - e.ref).abs().max())))
    times: dict[int, list[float]] = {i: [] for i in range(len(built))}
    for _ in range(repeats):
        for i, (_, exe, _) in enumerate(built):
            times[i].append(step_ns(exe, steps, rounds))
    for i, (e, _, diff) in enumerate(built):
        results.append(Result(e.row, e.column, statistics.median(times[i]), diff))
    return results


def entries(root: Path | None, tmp: Path, sizes: Sequence[int], flags: dict[str, tuple],
            eigen: bool) -> list[Entry]:
    """The programs: each LSTM and GRU size in torchhys's C and in RTNeural, the composed
    model (8 plays + GRU 8 + linear) in torchhys's C beside RTNeural's GRU of the same
    layer (9 inputs, the plays left out: RTNeural has no play operator)."""
    out = []
    for kind in KINDS:
        for h in sizes:
            torch.manual_seed(h)
            model = Recurrent(kind, h).double().eval()
            row = f"{kind.upper()} {h}"
            for fname, fl in flags.items():
                d = tmp / f"{kind}{h}"
                out.append(Entry(row, f"torchhys C {fname}",
                                 lambda m=model, d=d, fl=fl: build_c(m, d / "c", fl),
                                 reference(model)))
                if root is not None:
                    for e in (False, True) if eigen else (False,):
                        col = f"RTNeural {'Eigen' if e else 'STL'} {fname}"
                        out.append(Entry(row, col, lambda m=model, d=d, fl=fl, e=e:
                                         build_rtneural(m.rnn, m.out, root, d / "rt", fl, e),
                                         reference(model)))
    torch.manual_seed(0)
    comp = PlaysGRU(8, 8).double().eval()
    gru = Recurrent("gru", 8).double().eval()
    gru.rnn = nn.GRU(9, 8, batch_first=True).double()
    for fname, fl in flags.items():
        out.append(Entry("8 plays + GRU 8 + linear", f"torchhys C {fname}",
                         lambda fl=fl: build_c(comp, tmp / "plays_gru" / "c", fl),
                         reference(comp)))
        if root is not None:
            for e in (False, True) if eigen else (False,):
                out.append(Entry("8 plays + GRU 8 + linear",
                                 f"RTNeural {'Eigen' if e else 'STL'} {fname}",
                                 lambda fl=fl, e=e, g=gru: build_rtneural(
                                     g.rnn, g.out, root, tmp / "gru9" / "rt", fl, e),
                                 reference(gru, n_in=9)))
    return out


def markdown(results: list[Result]) -> str:
    """Rows: the models; columns: ns per step, and torchhys / RTNeural for each flag set."""
    def order(r: Result) -> tuple:
        flag = next((i for i, f in enumerate(FLAGS) if r.column.endswith(f)), len(FLAGS))
        who = next((i for i, w in enumerate(("torchhys", "RTNeural STL", "RTNeural Eigen"))
                    if r.column.startswith(w)), 3)
        kind, _, size = r.row.partition(" ")
        model = (KINDS.index(kind.lower()), int(size)) if kind.lower() in KINDS else (9, 0)
        return model, flag, who

    results = sorted(results, key=order)
    rows = list(dict.fromkeys(r.row for r in results))
    cols = sorted(dict.fromkeys(r.column for r in results),
                  key=lambda c: order(Result("LSTM 0", c, None, None))[1:])
    cell = {(r.row, r.column): r for r in results}
    ratios = []
    for fname in FLAGS:
        for backend in ("STL", "Eigen"):
            if f"RTNeural {backend} {fname}" in cols:
                ratios.append((fname, backend))
    head = " | ".join(f"{c} (ns)" for c in cols)
    rhead = "".join(f" | torchhys / RTNeural {b} {f}" for f, b in ratios)
    lines = [f"| model | {head}{rhead} | max abs diff vs torch |",
             "|---" * (2 + len(cols) + len(ratios)) + "|"]
    for row in rows:
        cells = []
        for c in cols:
            r = cell.get((row, c))
            cells.append("-" if r is None or r.ns is None else f"{r.ns:.0f}")
        rc = ""
        for f, b in ratios:
            a, ref = cell.get((row, f"torchhys C {f}")), cell.get((row, f"RTNeural {b} {f}"))
            ok = a is not None and ref is not None and a.ns and ref.ns
            rc += f" | {a.ns / ref.ns:.2f}" if ok else " | -"
        diffs = [r.diff for r in results if r.row == row and r.diff is not None]
        diff = f"{max(diffs):.1e}" if diffs else "-"
        lines.append(f"| {row} | {' | '.join(cells)}{rc} | {diff} |")
    return "\n".join(lines)


def run(rtneural: str | None, sizes: Sequence[int] = SIZES, steps: int = 20000,
        rounds: int = 7, repeats: int = 7, flags: dict[str, tuple] | None = None,
        log: Callable[[str], None] = print, keep: Path | None = None) -> list[Result]:
    """Build, check and time every program; print why RTNeural is skipped where it is."""
    root, why = rtneural_dir(rtneural)
    if root is None:
        log(f"RTNeural columns skipped: {why}")
    if shutil.which(os.environ.get("CXX", "c++")) is None and root is not None:
        log("RTNeural columns skipped: no C++ compiler (c++) on PATH")
        root = None
    eigen = root is not None and (root / "modules" / "Eigen" / "Eigen" / "Dense").is_file()
    with tempfile.TemporaryDirectory() as tmp:
        where = keep if keep is not None else Path(tmp)
        return time_all(entries(root, where, sizes, flags or FLAGS, eigen), steps, rounds,
                        repeats, log)
