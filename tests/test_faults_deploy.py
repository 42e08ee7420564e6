"""Faults of the deployed compensator: the generated C compiled with ``-ffast-math`` (refused
by an ``#error``; with the check bypassed, NaN still held and ``exp`` still rounded), one
compensator stepped from several threads, and a wrong state handed to ``step_explicit``."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from _export_helpers import (
    CC,
    FLAGS,
    FLOAT32_RTOL,
    FLOAT64_RTOL,
    NO_CC,
    compile_harness,
    gap,
    recommended,
    record,
    run_c,
    run_torchscript,
    training_range,
)
from _helpers import loop_net
from torch import Tensor

from torchhys import Backlash
from torchhys.deploy._c_files import FAST_MATH_ERROR
from torchhys.deploy._c_writer import Writer
from torchhys.deploy.export_c import to_c
from torchhys.operator import HysteresisOperator, OperatorStep, StateBlock

needs_cc = pytest.mark.skipif(CC is None, reason=NO_CC)

# ------------------------------------------------------------------------------------------
# 1. the generated C under -ffast-math
# ------------------------------------------------------------------------------------------

#: -ffast-math with its macro undefined: the #error bypassed, every unsafe optimisation on
FAST_BYPASSED = ["-std=c99", "-O3", "-ffast-math", "-U__FAST_MATH__"]
DTYPES = {"float64": (torch.float64, FLOAT64_RTOL), "float32": (torch.float32, FLOAT32_RTOL)}


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The recommended network's C (both dtypes) and the TorchScript file's run over a
    record with NaN, inf and samples out of the training range."""
    net = recommended()
    x = record(*training_range(net), n=2000)
    out = {}
    for name, (dtype, _) in DTYPES.items():
        folder = tmp_path_factory.mktemp(f"c_{name}")
        to_c(net, folder, dtype=dtype)
        out[name] = (folder, run_torchscript(net, x, folder / "comp.pt", dtype=dtype))
    return {"x": x, **out}


@needs_cc
@pytest.mark.parametrize("flags", [["-O3", "-ffast-math"], ["-Ofast"]])
def test_generated_c_refuses_to_compile_under_fast_math(exported: dict, flags: list[str]) -> None:
    folder, _ = exported["float64"]
    done = subprocess.run([CC, "-std=c99", *flags, "-c", str(folder / "torchhys_comp.c"),
                           "-o", str(folder / "fast.o")], capture_output=True, text=True)
    assert done.returncode != 0
    assert "#error" in done.stderr and FAST_MATH_ERROR in done.stderr, done.stderr
    assert "compile without -ffast-math or -Ofast" in FAST_MATH_ERROR


@needs_cc
@pytest.mark.parametrize("dtype", list(DTYPES))
@pytest.mark.parametrize("flags", [FLAGS, FAST_BYPASSED], ids=["O2", "fast-math-bypassed"])
def test_generated_c_holds_nan_and_agrees_under_every_flag(exported: dict, dtype: str,
                                                           flags: list[str]) -> None:
    """At -O2 and under -O3 -ffast-math with the #error bypassed: every NaN and inf sample
    held and counted, the commands within the conformance bound of the TorchScript file's
    (before: NaN drove the command to a limit, uncounted, and exp's rounding was folded
    away, a gap of 2 on this record)."""
    folder, ref = exported[dtype]
    got = run_c(compile_harness(folder, flags=flags), exported["x"])
    x = exported["x"]
    assert got["nonfinite"] == ref["nonfinite"] == int((~np.isfinite(x)).sum())
    assert got["out_of_range"] == ref["out_of_range"] > 0
    assert gap(got["u"], ref["u"]) <= DTYPES[dtype][1]


EXP_HARNESS = r"""
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

HELPERS

int main(void)
{
    double x, y[2];
    while (fread(&x, sizeof x, 1, stdin) == 1) {
        y[0] = NAME(x);
        y[1] = exp(x);
        fwrite(y, sizeof y[0], 2, stdout);
    }
    return 0;
}
"""


@needs_cc
def test_the_exp_helper_keeps_its_rounding_under_fast_math(tmp_path: Path) -> None:
    """The double exp of the generated C compiled with -O3 -ffast-math (macro undefined)
    against libm's exp compiled alike: within 1e-12 relative over the normal results (before:
    a relative error of up to 1, its k ln2 reduction folded away)."""
    w = Writer("t")
    name = w.helper("exp", torch.float64)
    src = tmp_path / "exp.c"
    src.write_text(EXP_HARNESS.replace("HELPERS", "\n\n".join(w.helpers.values()))
                   .replace("NAME", name))
    exe = tmp_path / "exp"
    done = subprocess.run([CC, *FAST_BYPASSED, "-o", str(exe), str(src), "-lm"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    g = np.random.default_rng(0)
    x = np.concatenate([g.uniform(-700.0, 709.0, 20_000), g.uniform(-5.0, 5.0, 20_000)])
    y = np.frombuffer(subprocess.run([str(exe)], input=x.tobytes(), capture_output=True,
                                     check=True).stdout, dtype=np.float64).reshape(-1, 2)
    normal = (y[:, 1] > 1e-300) & np.isfinite(y[:, 1])
    assert normal.mean() > 0.99
    assert np.max(np.abs(y[normal, 0] / y[normal, 1] - 1.0)) <= 1e-12


@needs_cc
@pytest.mark.skipif(shutil.which("clang") is None, reason="no clang on PATH")
def test_clang_too_refuses_fast_math(exported: dict) -> None:
    folder, _ = exported["float32"]
    done = subprocess.run(["clang", "-std=c99", "-O2", "-ffast-math", "-c",
                           str(folder / "torchhys_comp.c"), "-o", str(folder / "fast.o")],
                          capture_output=True, text=True)
    assert done.returncode != 0 and FAST_MATH_ERROR in done.stderr


class _TestsStep(OperatorStep):
    """Features that are NaN and inf tests of z = x - (the last sample): log z is NaN where
    the input falls, 1 / z inf where it repeats."""

    def __init__(self) -> None:
        super().__init__()
        self.n_outputs = 4
        self.state_spec = [StateBlock("last", 1, from_sample=[1.0])]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        z = x - state[0]
        log = torch.log(z)
        tests = [torch.isnan(log), torch.isinf(1.0 / z), torch.isfinite(log)]
        return torch.cat([t.to(x.dtype) for t in tests] + [x], 1), [x]


class _Tests(HysteresisOperator):
    n_outputs = 4

    def forward(self, x: Tensor, state: object = None) -> tuple[Tensor, None]:
        xb = x if x.dim() == 2 else x[None]
        f = _TestsStep().to(xb.dtype).run(xb)
        return (f if x.dim() == 2 else f[0]), None

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return _TestsStep().to(dtype)


@needs_cc
@pytest.mark.parametrize("dtype", list(DTYPES))
def test_isnan_isinf_isfinite_hold_under_fast_math(dtype: str, tmp_path: Path) -> None:
    """A step whose features are isnan, isinf and isfinite of values that are NaN and inf
    at some samples, compiled with -O3 -ffast-math (macro undefined): the commands those of
    the TorchScript file (before: x != x and x - x == 0 were folded, the tests constant)."""
    torch_dtype, rtol = DTYPES[dtype]
    net = loop_net([_Tests(), Backlash([0.4])])
    x = record(*training_range(net), n=1000)
    to_c(net, tmp_path, dtype=torch_dtype)
    ref = run_torchscript(net, x, tmp_path / "comp.pt", torch_dtype)
    got = run_c(compile_harness(tmp_path, flags=FAST_BYPASSED), x)
    assert got["nonfinite"] == ref["nonfinite"]
    assert gap(got["u"], ref["u"]) <= rtol
