"""Shared parts of the C and ONNX parity tests (tests/test_export_c.py, test_export_onnx.py and
the every-operator checks in test_conformance.py): the record, the recommended network, the
C harness and the three runners (C, ONNX, TorchScript), each returning the commands, the
final state and the two counters of one run."""

from __future__ import annotations

import copy
import shutil
import subprocess
from pathlib import Path

import numpy as np
import torch
from _helpers import loop_data, loop_net

from torchhys import EIHO, Backlash, InverseHysteresisNet
from torchhys.deploy.export import to_torchscript

CC = shutil.which("cc") or shutil.which("gcc")
NO_CC = "no C compiler (cc or gcc) on PATH"
FLAGS = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic"]
FLOAT64_RTOL = 1e-12
FLOAT32_RTOL = 1e-4
N, N32 = 10_000, 3_000

# --- models and records -----------------------------------------------------------------------


def recommended() -> InverseHysteresisNet:
    """The network of configs/compensator.yaml: a re-based EIHO and 16 plays, 64 sigmoids."""
    x, _ = loop_data()
    span = float(x.max() - x.min())
    plays = Backlash(0.4 * span * torch.arange(1, 17, dtype=torch.float64) / 16)
    return loop_net([EIHO(a=1.0, rule="recent", output="branch", threshold=0.0), plays],
                    hidden=64)


def record(low: float, high: float, n: int = N, seed: int = 0) -> np.ndarray:
    """``n`` samples around ``[low, high]``: nested turning points with noise, runs of one
    repeated sample (ties), runs of -0.0, +0.0 and NaN, excursions 30 % beyond the range,
    NaN, +inf and -inf (the first sample NaN: the initial command is held)."""
    g = np.random.default_rng(seed)
    c, h = (low + high) / 2, (high - low) / 2
    t = np.arange(n)
    x = c + h * 0.95 * np.sin(2 * np.pi * t / 700) * (0.55 + 0.45 * np.cos(2 * np.pi * t / 2300))
    x += 0.01 * h * g.standard_normal(n)
    for k in range(800, n, 1500):  # excursions out of the range, both ways
        x[k:k + 60] = c + np.sign(np.sin(k)) * 1.3 * h * np.sin(np.linspace(0, np.pi, 60))
    for k in g.choice(n, 120, replace=False):  # ties: runs of one repeated sample
        x[k:k + 8] = x[k]
    for k in range(350, n, 1100):  # signed zeros (in the range), reversals and holds
        x[k:k + 8] = [0.01, -0.0, np.nan, -0.0, 0.0, -0.01, -0.0, 0.02]
    x[g.choice(n, 40, replace=False)] = np.nan
    x[g.choice(n, 15, replace=False)] = np.inf
    x[g.choice(n, 15, replace=False)] = -np.inf
    x[0] = np.nan
    return x


def training_range(net: InverseHysteresisNet) -> tuple[float, float]:
    return float(net.in_min), float(net.in_max)


# --- the C harness ----------------------------------------------------------------------------


HARNESS = r"""
#include <complex.h> /* a macro I: the header must not use the name */
#include <stdio.h>
#include "NAME.h"

/* Runs the input (binary doubles) twice, NAME_init before each pass: writes the commands of
   both passes, the two counters after the first and the state's members after the second;
   prints LOW HIGH STATE_BYTES. */
int main(int argc, char **argv)
{
    NAME_state s;
    double x, u;
    int64_t counts[2];
    long n = 0, i, pass;
    FILE *in, *out;
    if (argc != 3 || !(in = fopen(argv[1], "rb")) || !(out = fopen(argv[2], "wb")))
        return 2;
    if (sizeof(NAME_state) != NAME_STATE_BYTES)
        return 3;
    for (pass = 0; pass < 2; ++pass) {
        NAME_init(&s);
        rewind(in);
        for (i = 0; fread(&x, sizeof x, 1, in) == 1; ++i) {
            u = (double)NAME_step(&s, (NAME_real)x);
            fwrite(&u, sizeof u, 1, out);
        }
        if (pass == 0) {
            n = i;
            counts[0] = NAME_nonfinite_count(&s);
            counts[1] = NAME_out_of_range_count(&s);
        }
    }
    fwrite(counts, sizeof counts[0], 2, out);
    DUMP_STATE
    printf("%.17g %.17g %ld %ld\n", (double)NAME_LOW, (double)NAME_HIGH,
           (long)NAME_STATE_BYTES, n);
    fclose(in);
    fclose(out);
    return 0;
}
"""


def compile_harness(folder: Path, prefix: str = "torchhys_comp",
                    state: list[torch.Tensor] | None = None, flags: list[str] = FLAGS) -> Path:
    """The harness over ``folder/PREFIX.c``: the contract's names only, or also the state's
    members (their names: torchhys.deploy.c._files.MEMBERS), shaped as ``state``; compiled
    with ``flags``."""
    from torchhys.deploy.c._files import MEMBERS

    dump = "".join(f"fwrite(s.{MEMBERS[k]}, sizeof s.{MEMBERS[k]}[0], {t.numel()}, out);\n"
                   for k, t in enumerate(state or []))
    (folder / "harness.c").write_text(HARNESS.replace("DUMP_STATE", dump).replace("NAME", prefix))
    exe = folder / "harness"
    done = subprocess.run([CC, *flags, "-I", str(folder), "-o", str(exe),
                           str(folder / "harness.c"), str(folder / f"{prefix}.c"), "-lm"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    return exe


def run_driver(folder: Path, driver: str, source: Path, rows: object) -> list[str]:
    """A C driver (``driver``'s text, ``folder/main.c``) compiled with the generated
    ``source`` (``cc -std=c99 -O2 -Wall -Werror``) and run on ``rows`` (each a sequence of
    numbers, one line of stdin): its stdout's lines."""
    (folder / "main.c").write_text(driver)
    exe = folder / "run"
    subprocess.run([CC, "-std=c99", "-O2", "-Wall", "-Werror", "-o", str(exe),
                    str(folder / "main.c"), str(source), "-lm"], check=True)
    lines = "\n".join(" ".join(repr(float(v)) for v in row) for row in rows)
    return subprocess.run([str(exe)], input=lines, capture_output=True, text=True,
                          check=True).stdout.split("\n")


def run_c(exe: Path, x: np.ndarray, state: list[torch.Tensor] | None = None) -> dict:
    """The harness on ``x``: commands, the counters, LOW, HIGH, STATE_BYTES (and the final
    state, in the dtypes and shapes of ``state``, where the harness writes it)."""
    src, dst = exe.parent / "x.bin", exe.parent / "u.bin"
    x.astype(np.float64).tofile(src)
    done = subprocess.run([str(exe), str(src), str(dst)], capture_output=True, text=True)
    assert done.returncode == 0, (done.returncode, done.stderr)
    raw, out = dst.read_bytes(), []
    at = 2 * 8 * len(x) + 16
    for t in state or []:
        n = t.numel() * t.element_size()
        kind = np.uint8 if t.dtype == torch.bool else t.numpy().dtype
        out.append(torch.from_numpy(np.frombuffer(raw[at:at + n], dtype=kind).copy())
                   .reshape(t.shape).to(t.dtype))
        at += n
    assert at == len(raw)
    u = np.frombuffer(raw[:16 * len(x)], dtype=np.float64)
    counts = np.frombuffer(raw[16 * len(x):16 * len(x) + 16], dtype=np.int64)
    low, high, n_bytes, n = done.stdout.split()
    assert int(n) == len(x)
    assert np.array_equal(u[:len(x)], u[len(x):], equal_nan=True)  # NAME_init resets
    return {"u": u[:len(x)], "nonfinite": int(counts[0]), "out_of_range": int(counts[1]),
            "low": float(low), "high": float(high), "state_bytes": int(n_bytes),
            **({"state": out} if state is not None else {})}


# --- the other runners, the comparison --------------------------------------------------------


def stepped(comp: object, x: np.ndarray, dtype: torch.dtype, **more: object) -> dict:
    """A compensator's ``step`` sample by sample over ``x``: commands, state, counters."""
    xt = torch.tensor(x, dtype=dtype)
    u = np.array([float(comp.step(xt[i:i + 1])) for i in range(len(x))])
    return {"u": u, "state": list(comp.state), "nonfinite": int(comp.nonfinite_count()),
            "out_of_range": int(comp.out_of_range_count()), **more}


def run_torchscript(model: torch.nn.Module, x: np.ndarray, path: Path,
                    dtype: torch.dtype = torch.float64, **options) -> dict:
    scripted = to_torchscript(copy.deepcopy(model).to(dtype), path, **options)
    return stepped(scripted, x, dtype, scripted=scripted)


def run_onnx(model: torch.nn.Module, x: np.ndarray, path: Path,
             dtype: torch.dtype = torch.float64, **options) -> dict:
    from torchhys.deploy.export_onnx import load_onnx, to_onnx

    to_onnx(copy.deepcopy(model).to(dtype), path, **options)
    stepper = load_onnx(path)
    return stepped(stepper, x, dtype, stepper=stepper)


def gap(a: np.ndarray | torch.Tensor, b: np.ndarray | torch.Tensor) -> float:
    """The largest difference relative to the reference's scale (at least 1)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    assert np.isfinite(a).all() and np.isfinite(b).all()
    return float(np.max(np.abs(a - b), initial=0.0) / max(1.0, np.max(np.abs(b), initial=0.0)))


def assert_equal_runs(got: dict, ref: dict, rtol: float) -> float:
    """The commands within ``rtol`` of their scale, the counters equal, and the final states
    (where both runs have one) equal: float columns within ``rtol`` of their scale, int64
    and bool ones exactly. Returns the largest gap."""
    worst = gap(got["u"], ref["u"])
    assert worst <= rtol, worst
    assert (got["nonfinite"], got["out_of_range"]) == (ref["nonfinite"], ref["out_of_range"])
    if "state" in got and "state" in ref:
        assert len(got["state"]) == len(ref["state"])
        for i, (a, b) in enumerate(zip(got["state"], ref["state"], strict=True)):
            assert a.dtype == b.dtype and a.shape == b.shape, (i, a.dtype, b.dtype)
            if a.is_floating_point():
                worst = max(worst, gap(a, b))
                assert gap(a, b) <= rtol, (i, gap(a, b))
            else:
                assert torch.equal(a, b), i
    return worst
