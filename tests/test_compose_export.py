"""A recurrent composition in every export format: a play, an LSTM cell and a GRU cell (16
units each, the weights of real ``nn.LSTM`` / ``nn.GRU`` modules) in one hand-written step
(tests/_recurrent_models.py), deployed through the StreamingCompensator and exported to C
(compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror -pedantic``), ONNX (ONNX Runtime),
TorchScript and AOTI (slow).

Each format's commands, counters and final state against the eager compensator's ``step``
over a record of 3000 samples around the training input range (turning points, ties, signed
zeros, NaN and inf held and counted, excursions 30 % beyond the range clamped and counted):
float64 within 1e-12 of the command's scale (FLOAT64_RTOL); float32 within FLOAT32_RTOL =
1e-4, the bound of every export test (measured with gcc 12, glibc and onnxruntime 1.x on
x86-64: float64 1.1e-16 for C and ONNX, 0 for TorchScript; float32 6e-8 for C, 8.9e-8 for
ONNX, 0 for TorchScript: the float32 roundings of the gates' sums and of ``exp`` and ``tanh``; the
float32 compensator itself is 4.8e-8 from the float64 one)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from _export_helpers import (
    CC,
    FLOAT32_RTOL,
    FLOAT64_RTOL,
    NO_CC,
    assert_equal_runs,
    compile_harness,
    record,
    run_c,
    run_onnx,
    run_torchscript,
    stepped,
)
from _recurrent_models import PlayLSTMGRUStep, check_cells, modules, play_lstm_gru

from torchhys.deploy.c import to_c
from torchhys.deploy.streaming import StreamingCompensator

needs_cc = pytest.mark.skipif(CC is None, reason=NO_CC)
OPTIONS = {"limits": (-3.0, 3.0), "input_range": (-1.0, 1.0)}
N = 3000


def samples(n: int = N) -> np.ndarray:
    return record(-1.0, 1.0, n=n, seed=3)


def reference(model: torch.nn.Module, x: np.ndarray, dtype: torch.dtype, **options) -> dict:
    import copy

    comp = StreamingCompensator(copy.deepcopy(model).to(dtype), **{**OPTIONS, **options})
    return stepped(comp, x, dtype)


def tolerance(dtype: torch.dtype) -> float:
    return FLOAT64_RTOL if dtype == torch.float64 else FLOAT32_RTOL


def test_the_hand_written_cells_are_torchs() -> None:
    lstm, gru, out = modules()
    step = PlayLSTMGRUStep(lstm, gru, out)
    x = torch.tensor(samples(400)[1:], dtype=torch.float64).clamp(-1, 1).nan_to_num(0.0)
    assert check_cells(step, lstm, gru, out, x[None]) < 1e-14


def test_the_reference_holds_and_counts() -> None:
    x = samples()
    ref = reference(play_lstm_gru(), x, torch.float64)
    assert ref["nonfinite"] == int((~np.isfinite(x)).sum())
    assert ref["out_of_range"] == int((np.isfinite(x) & (np.abs(x) > 1.1)).sum()) > 0
    assert np.isfinite(ref["u"]).all() and np.ptp(ref["u"]) > 0.05


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("options", [{}, {"direction": "increasing", "initial_command": 0.5}])
def test_c(dtype: torch.dtype, options: dict, tmp_path: Path) -> None:
    model, x = play_lstm_gru(), samples()
    to_c(model, tmp_path, dtype=dtype, **OPTIONS, **options)
    comp = StreamingCompensator(model.to(dtype), **OPTIONS, **options)
    c = run_c(compile_harness(tmp_path, state=comp.initial_state(1)), x,
              comp.initial_state(1))
    assert_equal_runs(c, reference(model, x, dtype, **options), tolerance(dtype))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_torchscript(dtype: torch.dtype, tmp_path: Path) -> None:
    model, x = play_lstm_gru(), samples()
    ts = run_torchscript(model, x, tmp_path / "comp.pt", dtype, **OPTIONS)
    assert_equal_runs(ts, reference(model, x, dtype), tolerance(dtype))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_onnx(dtype: torch.dtype, tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    model, x = play_lstm_gru(), samples()
    got = run_onnx(model, x, tmp_path / "comp.onnx", dtype, **OPTIONS)
    assert_equal_runs(got, reference(model, x, dtype), tolerance(dtype))


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_aoti(dtype: torch.dtype, tmp_path: Path) -> None:
    from torchhys.deploy.export import load_aoti, to_aoti

    model, x = play_lstm_gru(), samples(1000)
    to_aoti(model.to(dtype), tmp_path / "comp.pt2", **OPTIONS)
    got = stepped(load_aoti(tmp_path / "comp.pt2"), x, dtype)
    assert_equal_runs(got, reference(model, x, dtype), tolerance(dtype))


@needs_cc
@pytest.mark.parametrize("kind", ["lstm", "gru"])
def test_the_c_step_time_of_a_layer(kind: str) -> None:
    """tests/_recurrent_models.c_step_time (for the latency benchmark) compiles and times the
    C step of a composed layer: a positive time, longer for more units."""
    from _recurrent_models import c_step_time, composed_layer

    small = c_step_time(composed_layer(kind, 4), steps=2000, repeats=3, cpu_time=True)
    large = c_step_time(composed_layer(kind, 48), steps=2000, repeats=3, cpu_time=True)
    assert 0 < small < large
