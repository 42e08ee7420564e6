"""The exp and tanh of a float that the float32 C step uses (and its sigmoid, from that exp)
(torchhys.deploy.c._libm: libm-free, so that their loops vectorize), against the C
library's ``expf``, ``1 / (1 + expf(-x))`` and ``tanhf``.

Compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror -pedantic`` over 4.1 million floats
(a grid over [-120, 120], uniform over [-1, 1] and [-20, 20], log-spaced magnitudes from
1e-45 to 1e38 of both signs, random bit patterns) and edge inputs (+-0, +-inf, NaN, the
overflow and underflow thresholds): measured with gcc 12 and glibc 2.36, the exp within 1 ulp
of expf (91 % the same float), the tanh within 4 ulp of tanhf (76 % the same float, 2
inputs 4 apart, near 0.22), the float32 step's sigmoid (``1 / (1 + exp(-x))`` with that
exp) within 4 ulp of the same with expf (96 % the same float); NaN, inf, 0 and +-1 where
libm gives them, the sign kept. Against torch's float32 kernels: within 1, 4 and 2 ulp. And
a generated float32 LSTM step's loops of them vectorize at ``-O2`` (GCC only). Skipped
without a C compiler.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from torchhys.deploy.c._writer import Writer

CC = shutil.which("cc") or shutil.which("gcc")
needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler (cc or gcc) on PATH")
FLAGS = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic"]

HARNESS = r"""
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

HELPERS

/* binary floats in -> (exp, expf, the step's sigmoid, 1 / (1 + expf(-x)), tanh, tanhf) out */
int main(int argc, char **argv)
{
    FILE *in, *out;
    float x, y[6];
    if (argc != 3 || !(in = fopen(argv[1], "rb")) || !(out = fopen(argv[2], "wb")))
        return 2;
    while (fread(&x, sizeof x, 1, in) == 1) {
        y[0] = EXP(x);
        y[1] = expf(x);
        y[2] = SIGMOID(x);
        y[3] = 1.0f / (1.0f + expf(-x));
        y[4] = TANH(x);
        y[5] = tanhf(x);
        fwrite(y, sizeof y[0], 6, out);
    }
    fclose(in);
    fclose(out);
    return 0;
}
"""

EDGES = [0.0, -0.0, 1.0, -1.0, np.inf, -np.inf, np.nan, 88.72, 88.73, -87.33, -103.97,
         -104.0, 104.0, 105.0, 9.0, 9.01, 10.0, 11.0, 1e-30, -1e-30, 1e-45, -1e-45, 1e-8]


def inputs(seed: int = 0) -> np.ndarray:
    g = np.random.default_rng(seed)
    bits = g.integers(0, 2**32, 500_000, dtype=np.uint64).astype(np.uint32).view(np.float32)
    mags = 10.0 ** g.uniform(-45, 38, 300_000)
    with np.errstate(over="ignore", invalid="ignore"):
        return np.concatenate([
            np.array(EDGES, dtype=np.float32), np.linspace(-120, 120, 2_000_001, dtype=np.float32),
            g.uniform(-1, 1, 500_000).astype(np.float32),
            g.uniform(-20, 20, 500_000).astype(np.float32), mags.astype(np.float32),
            (-mags).astype(np.float32), bits])


def ulps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance of two finite floats of one sign in units in the last place."""
    return np.abs(np.abs(a).view(np.int32).astype(np.int64)
                  - np.abs(b).view(np.int32).astype(np.int64))


@pytest.fixture(scope="module")
def results(tmp_path_factory: pytest.TempPathFactory) -> tuple[np.ndarray, np.ndarray]:
    tmp = tmp_path_factory.mktemp("libm_float")
    w = Writer("t")
    names = {k: w.helper(k, torch.float32) for k in ("exp", "tanh")}
    src = HARNESS.replace("HELPERS", "\n\n".join(w.helpers.values()))
    src = src.replace("SIGMOID(x)", f"1.0f / (1.0f + {names['exp']}(-x))")  # the template's
    for k, name in names.items():
        src = src.replace(f"{k.upper()}(x)", f"{name}(x)")
    (tmp / "f.c").write_text(src)
    done = subprocess.run([CC, *FLAGS, "-o", str(tmp / "f"), str(tmp / "f.c"), "-lm"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    x = inputs()
    x.tofile(tmp / "x.bin")
    subprocess.run([str(tmp / "f"), str(tmp / "x.bin"), str(tmp / "y.bin")], check=True)
    return x, np.fromfile(tmp / "y.bin", dtype=np.float32).reshape(-1, 6)


@needs_cc
@pytest.mark.parametrize("column, bound", [(0, 1), (2, 4), (4, 4)],
                         ids=["exp", "sigmoid", "tanh"])
def test_within_a_few_ulp_of_libm(column: int, bound: int, results: tuple) -> None:
    x, y = results
    ours, libm = y[:, column], y[:, column + 1]
    nan = np.isnan(libm)
    assert np.array_equal(np.isnan(ours), nan) and np.array_equal(nan, np.isnan(x))
    assert np.array_equal(np.signbit(ours[~nan]), np.signbit(libm[~nan]))
    edge = ~nan & (np.isinf(libm) | (libm == 0) | (np.abs(libm) == 1))
    assert np.array_equal(ours[edge], libm[edge])  # inf, 0 and +-1 where libm gives them
    rest = ~nan & ~edge
    d = ulps(ours[rest], libm[rest])
    assert d.max() <= bound, (d.max(), x[rest][np.argmax(d)])


@needs_cc
@pytest.mark.parametrize("column, op, bound", [(0, torch.exp, 1), (2, torch.sigmoid, 4),
                                               (4, torch.tanh, 4)],
                         ids=["exp", "sigmoid", "tanh"])
def test_within_a_few_ulp_of_torch(column: int, op, bound: int, results: tuple) -> None:
    """Against torch's float32 kernels (the eager compensator's): NaN, inf and 0 where they
    are, within ``bound`` ulp elsewhere (measured: 1, 4 and 2)."""
    x, y = results
    ours, ref = y[:, column], op(torch.from_numpy(x)).numpy()
    nan = np.isnan(ref)
    assert np.array_equal(np.isnan(ours), nan)
    edge = ~nan & (np.isinf(ref) | (ref == 0))
    assert np.array_equal(ours[edge], ref[edge])
    d = ulps(ours[~nan & ~edge], ref[~nan & ~edge])
    assert d.max() <= bound, (d.max(), x[~nan & ~edge][np.argmax(d)])


@needs_cc
@pytest.mark.skipif(CC is not None and "Free Software Foundation" not in subprocess.run(
    [CC, "--version"], capture_output=True, text=True).stdout, reason="not GCC")
def test_a_float32_lstm_step_s_loops_vectorize_at_O2(tmp_path: Path) -> None:
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from _recurrent_models import LSTMStep, StepModel

    from torchhys.deploy.c import to_c

    _, c = to_c(StepModel(LSTMStep(16)), tmp_path, prefix="comp", dtype=torch.float32,
                limits=(-9.0, 9.0))
    lines = c.read_text().splitlines()
    at = [i + 1 for i, line in enumerate(lines) if "comp_tanh_float(" in line
          and "static" not in line]
    assert at
    done = subprocess.run([CC, *FLAGS, "-fopt-info-vec-optimized", "-c", str(c), "-o",
                           str(tmp_path / "comp.o")], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    loops = {int(m) for m in re.findall(r"comp\.c:(\d+):\d+: optimized: loop vectorized",
                                        done.stderr)}
    assert all(line - 1 in loops for line in at), (at, sorted(loops))
