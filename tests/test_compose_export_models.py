"""The compositions of issue 46, made with ``torchhys.compose.compose`` from users' plain
modules (tests/_compose_models.py: a play -> an LSTM -> a linear layer; three plays and a GRU
side by side into an MLP; a transfer function -> an EIHO operator -> a two-layer GRU), in
every export format: C (compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror -pedantic``),
ONNX (ONNX Runtime), TorchScript and AOTI (slow).

Each composition records its training ranges (``compose(module, x=..., y=...)``), so the
compensator runs with its default limits (the target's range: saturation), input clamp and
direction guard. Each format's commands, counters and final state against the eager
compensator's ``step`` over 3000 samples of tests/_export_helpers.record around the
training input range (turning points, ties, signed zeros, NaN and inf held and counted,
excursions 30 % beyond the range clamped and counted): float64 within 1e-12 of the
command's scale (FLOAT64_RTOL), float32 within FLOAT32_RTOL = 1e-4 (measured with gcc 12,
glibc and onnxruntime on x86-64: float64 at most 2.2e-16 for C, 3.3e-16 for ONNX, 0 for
TorchScript; float32 at most 1.2e-7 for C and ONNX, 0 for TorchScript: the float32
roundings of the sums, ``exp`` and ``tanh``; the float32 compensators themselves are 4e-8
to 2.7e-5 from the float64 ones, the most for the filter -> EIHO -> GRU)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from _compose_models import MODELS, make, signal
from _export_helpers import (
    CC,
    FLOAT32_RTOL,
    FLOAT64_RTOL,
    NO_CC,
    assert_equal_runs,
    compile_harness,
    record,
    run_c,
    stepped,
)

from torchhys.compose import compose
from torchhys.deploy.c import to_c
from torchhys.deploy.export import to_torchscript
from torchhys.deploy.streaming import StreamingCompensator

needs_cc = pytest.mark.skipif(CC is None, reason=NO_CC)
N = 3000
DTYPES = [torch.float64, torch.float32]


def composed(name: str, dtype: torch.dtype = torch.float64) -> torch.nn.Module:
    """The composition ``name`` in ``dtype`` with its ranges recorded on a training signal
    (the float64 module's output as the target). Made afresh in each dtype: a Composed is
    not deep-copied here."""
    module = make(name)
    x = signal()
    with torch.no_grad():
        y = module(x)
    return compose(module.to(dtype), x=x.to(dtype), y=y.to(dtype))


def samples(model: torch.nn.Module, n: int = N) -> np.ndarray:
    return record(float(model.in_min), float(model.in_max), n=n, seed=5)


def reference(name: str, x: np.ndarray, dtype: torch.dtype) -> dict:
    return stepped(StreamingCompensator(composed(name, dtype)), x, dtype)


def tolerance(dtype: torch.dtype) -> float:
    return FLOAT64_RTOL if dtype == torch.float64 else FLOAT32_RTOL


@pytest.mark.parametrize("name", sorted(MODELS))
def test_the_record_exercises_the_guarantees(name: str) -> None:
    x = samples(composed(name))
    ref = reference(name, x, torch.float64)
    assert ref["nonfinite"] == int((~np.isfinite(x)).sum())
    assert ref["out_of_range"] > 0
    assert np.isfinite(ref["u"]).all() and np.ptp(ref["u"]) > 0


@needs_cc
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", sorted(MODELS))
def test_c(name: str, dtype: torch.dtype, tmp_path: Path) -> None:
    model = composed(name, dtype)
    x = samples(composed(name))
    to_c(model, tmp_path, dtype=dtype)
    state = StreamingCompensator(model).initial_state(1)
    got = run_c(compile_harness(tmp_path, state=state), x, state)
    assert_equal_runs(got, reference(name, x, dtype), tolerance(dtype))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", sorted(MODELS))
def test_torchscript(name: str, dtype: torch.dtype, tmp_path: Path) -> None:
    x = samples(composed(name))
    scripted = to_torchscript(composed(name, dtype), tmp_path / "comp.pt")
    assert_equal_runs(stepped(scripted, x, dtype), reference(name, x, dtype), tolerance(dtype))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", sorted(MODELS))
def test_onnx(name: str, dtype: torch.dtype, tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from torchhys.deploy.export_onnx import load_onnx, to_onnx

    x = samples(composed(name))
    to_onnx(composed(name, dtype), tmp_path / "comp.onnx")
    got = stepped(load_onnx(tmp_path / "comp.onnx"), x, dtype)
    assert_equal_runs(got, reference(name, x, dtype), tolerance(dtype))


@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", sorted(MODELS))
def test_aoti(name: str, dtype: torch.dtype, tmp_path: Path) -> None:
    from torchhys.deploy.export import load_aoti, to_aoti

    x = samples(composed(name), 1000)
    to_aoti(composed(name, dtype), tmp_path / "comp.pt2")
    got = stepped(load_aoti(tmp_path / "comp.pt2"), x, dtype)
    assert_equal_runs(got, reference(name, x, dtype), tolerance(dtype))
