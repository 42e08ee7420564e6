"""The compositions of issue 46, made with ``torchhys.compose.compose`` from users' plain
modules (tests/_compose_models.py: a play -> an LSTM -> a linear layer; three plays and a GRU
side by side into an MLP; a transfer function -> an EIHO operator -> a two-layer GRU), in
every export format: C (compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror -pedantic``),
ONNX (ONNX Runtime), TorchScript and AOTI; and each recurrent layer kind of torch
(``nn.RNN`` relu and tanh, a two-layer ``nn.LSTM`` without bias, a three-layer ``nn.GRU``,
time first and batch first) into an MLP, in C and ONNX. The default run: C in both dtypes,
TorchScript in float64, ONNX of the first composition in float64; the rest is marked slow.

Each composition records its training ranges (``compose(module, x=..., y=...)``), so the
compensator runs with its default limits (the target's range: saturation), input clamp and
direction guard. Each format's commands, counters and final state against the eager
compensator's ``step`` over 2000 samples of tests/_export_helpers.record around the
training input range (turning points, ties, signed zeros, NaN and inf held and counted,
excursions 30 % beyond the range clamped and counted): float64 within 1e-12 of the
command's scale (FLOAT64_RTOL), float32 within FLOAT32_RTOL = 1e-4 (measured with gcc 12,
glibc and onnxruntime on x86-64: float64 at most 2.2e-16 for C, 3.3e-16 for ONNX, 0 for
TorchScript; float32 at most 1.2e-7 for C and ONNX, 0 for TorchScript: the float32
roundings of the sums, ``exp`` and ``tanh``; the float32 compensators themselves are 4e-8
to 5.5e-4 from the float64 ones, the most for the filter -> EIHO -> GRU)."""

from __future__ import annotations

import copy
import importlib.util
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
N = 2000
DTYPES = [torch.float64, torch.float32]
#: float32 through the Python runners (TorchScript, ONNX) in the slow run only
DTYPES_SLOW32 = [torch.float64, pytest.param(torch.float32, marks=pytest.mark.slow)]


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


_REFERENCES: dict[tuple, dict] = {}


def reference(name: str, x: np.ndarray, dtype: torch.dtype) -> dict:
    """The eager compensator's run (computed once per model, dtype and record)."""
    key = (name, str(dtype), x.tobytes())
    if key not in _REFERENCES:
        _REFERENCES[key] = stepped(StreamingCompensator(composed(name, dtype)), x, dtype)
    return _REFERENCES[key]


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


@pytest.mark.parametrize("dtype", DTYPES_SLOW32)
@pytest.mark.parametrize("name", sorted(MODELS))
def test_torchscript(name: str, dtype: torch.dtype, tmp_path: Path) -> None:
    x = samples(composed(name))
    scripted = to_torchscript(composed(name, dtype), tmp_path / "comp.pt")
    assert_equal_runs(stepped(scripted, x, dtype), reference(name, x, dtype), tolerance(dtype))


@pytest.mark.parametrize("dtype", DTYPES_SLOW32)
@pytest.mark.parametrize("name", [n if n == "backlash_lstm" else pytest.param(
    n, marks=pytest.mark.slow) for n in sorted(MODELS)])
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


class Layers(torch.nn.Module):
    """One recurrent layer kind of torch (``layer``, several layers, time first or batch
    first, with or without bias), then an MLP: every recurrent step in C and ONNX."""

    def __init__(self, layer: torch.nn.RNNBase) -> None:
        super().__init__()
        self.rnn = layer
        self.mlp = torch.nn.Sequential(torch.nn.Linear(layer.hidden_size, 4), torch.nn.SiLU(),
                                       torch.nn.Linear(4, 1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = x.unsqueeze(-1) if self.rnn.batch_first else x.transpose(0, 1).unsqueeze(-1)
        h, _ = self.rnn(f)
        y = self.mlp(h).squeeze(-1)
        return y if self.rnn.batch_first else y.transpose(0, 1)


LAYERS = {
    "rnn_relu_2": lambda: torch.nn.RNN(1, 8, num_layers=2, nonlinearity="relu"),
    "rnn_tanh": lambda: torch.nn.RNN(1, 6, batch_first=True),
    "lstm_2_nobias": lambda: torch.nn.LSTM(1, 6, num_layers=2, bias=False),
    "gru_3": lambda: torch.nn.GRU(1, 5, num_layers=3, batch_first=True),
}


def layer_model(kind: str, dtype: torch.dtype) -> torch.nn.Module:
    torch.manual_seed(2)
    module = Layers(LAYERS[kind]()).double()
    x = signal()
    with torch.no_grad():
        y = module(x)
    return compose(module.to(dtype), x=x.to(dtype), y=y.to(dtype))


@needs_cc
@pytest.mark.slow
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind", sorted(LAYERS))
def test_every_recurrent_layer_in_c_and_onnx(kind: str, dtype: torch.dtype, tmp_path: Path
                                             ) -> None:
    x = samples(layer_model(kind, torch.float64), 1000)
    ref = stepped(StreamingCompensator(layer_model(kind, dtype)), x, dtype)
    model = layer_model(kind, dtype)
    to_c(model, tmp_path, dtype=dtype)
    state = StreamingCompensator(model).initial_state(1)
    assert_equal_runs(run_c(compile_harness(tmp_path, state=state), x, state), ref,
                      tolerance(dtype))
    if importlib.util.find_spec("onnxruntime") and importlib.util.find_spec("onnxscript"):
        from torchhys.deploy.export_onnx import load_onnx, to_onnx

        to_onnx(layer_model(kind, dtype), tmp_path / "comp.onnx")
        assert_equal_runs(stepped(load_onnx(tmp_path / "comp.onnx"), x, dtype), ref,
                          tolerance(dtype))


def test_a_float64_composition_converts_to_a_float32_c_step(tmp_path: Path) -> None:
    """``to_c(model, dtype=float32)`` copies and converts a float64 Composed (as
    ``model.to(float32)``): its C step runs as the eager float32 compensator of that copy."""
    model = composed("parallel_gru")
    x = samples(model, 1000)
    to_c(model, tmp_path, dtype=torch.float32)
    got = run_c(compile_harness(tmp_path), x)
    ref = stepped(StreamingCompensator(copy.deepcopy(model).to(torch.float32)), x,
                  torch.float32)
    assert_equal_runs(got, ref, FLOAT32_RTOL)
    assert model.in_min.dtype == torch.float64  # the model itself is left as it was
