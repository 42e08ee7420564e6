"""The steps of torch's layers (torchhys.compose.recurrent, torchhys.compose.stateless): each
run over a sequence against the torch module itself, the final state against torch's (the
published layout), TorchScript against eager, and the layers refused."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from torchhys.compose import GRUStep, LSTMStep, RNNStep, recurrent_step, stateless_step
from torchhys.step import check_step


def _layer(kind: str, layers: int, batch_first: bool, bias: bool) -> nn.RNNBase:
    torch.manual_seed(layers * 7 + batch_first * 3 + bias)
    if kind == "lstm":
        return nn.LSTM(3, 5, num_layers=layers, batch_first=batch_first, bias=bias).double()
    if kind == "gru":
        return nn.GRU(3, 5, num_layers=layers, batch_first=batch_first, bias=bias).double()
    nonlinearity = "relu" if kind == "rnn_relu" else "tanh"
    return nn.RNN(3, 5, num_layers=layers, batch_first=batch_first, bias=bias,
                  nonlinearity=nonlinearity).double()


def _as_columns(h: torch.Tensor) -> torch.Tensor:
    """torch's (num_layers, batch, hidden) as the step's block (batch, num_layers * hidden)."""
    return h.transpose(0, 1).reshape(h.shape[1], -1)


@pytest.mark.parametrize("kind", ["lstm", "gru", "rnn_tanh", "rnn_relu"])
@pytest.mark.parametrize("layers", [1, 2])
@pytest.mark.parametrize("batch_first", [True, False])
@pytest.mark.parametrize("bias", [True, False])
def test_step_equals_the_torch_layer(kind, layers, batch_first, bias):
    layer = _layer(kind, layers, batch_first, bias)
    x = torch.randn(4, 23, 3, dtype=torch.float64)
    out, hidden = layer(x if batch_first else x.transpose(0, 1))
    out = out if batch_first else out.transpose(0, 1)
    step = recurrent_step(layer, torch.float64)
    assert (step.n_inputs, step.n_outputs) == (3, 5)
    assert [(b.name, b.size) for b in step.state_spec] == (
        [("h", 5 * layers), ("c", 5 * layers)] if kind == "lstm" else [("h", 5 * layers)])
    torch.testing.assert_close(step.run(x), out, rtol=0, atol=1e-12)
    # the final state in the published layout (layer-major columns)
    state = step.initial_state(x[:, 0])
    for xt in x.unbind(1):
        _, state = step(xt, state)
    final = list(hidden) if kind == "lstm" else [hidden]
    for got, want in zip(state, final, strict=True):
        torch.testing.assert_close(got, _as_columns(want), rtol=0, atol=1e-12)


@pytest.mark.filterwarnings("ignore:`torch.jit.script` is deprecated:DeprecationWarning")
@pytest.mark.parametrize("cls,layer", [(LSTMStep, nn.LSTM(2, 4, num_layers=2)),
                                       (GRUStep, nn.GRU(2, 4)), (RNNStep, nn.RNN(2, 4))])
def test_scripted_step_equals_eager_and_dtype_is_the_steps(cls, layer):
    step = cls(layer.double())
    assert step.cells[0].w_ih.dtype == torch.float64
    step32 = cls(layer, torch.float32)
    assert step32.cells[0].w_ih.dtype == torch.float32
    scripted = torch.jit.script(step)
    x = torch.randn(3, 2, dtype=torch.float64)
    state = [torch.randn(3, b.size, dtype=torch.float64) for b in step.state_spec]
    got, new = scripted(x, state)
    want, new_eager = step(x, state)
    torch.testing.assert_close(got, want, rtol=0, atol=0)
    for a, b in zip(new, new_eager, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_step_reads_the_weights_and_does_not_train_them():
    layer = nn.LSTM(2, 3).double()
    step = LSTMStep(layer)
    assert not any(p.requires_grad for p in step.buffers())
    assert list(step.parameters()) == []
    with torch.no_grad():
        layer.weight_ih_l0.add_(1.0)
    # a copy: the step keeps the weights it was built with
    assert not torch.equal(step.cells[0].w_ih, layer.weight_ih_l0)
    assert check_step(step, n_inputs=None) is step


def test_refused_layers():
    with pytest.raises(ValueError, match=r"bidirectional.*not causal"):
        recurrent_step(nn.GRU(2, 3, bidirectional=True))
    with pytest.raises(ValueError, match=r"proj_size=2"):
        LSTMStep(nn.LSTM(2, 3, proj_size=2))
    with pytest.raises(TypeError, match=r"must be a torch.nn.GRU, got LSTM"):
        GRUStep(nn.LSTM(2, 3))
    with pytest.raises(TypeError, match=r"Linear has no step: the recurrent layers"):
        recurrent_step(nn.Linear(2, 3))


def test_stateless_steps():
    lin = nn.Linear(3, 2).double()
    step = stateless_step(lin)
    x = torch.randn(4, 3, dtype=torch.float64)
    y, state = step(x, [])
    torch.testing.assert_close(y, lin(x), rtol=0, atol=0)
    assert (step.n_inputs, step.n_outputs, state, step.state_spec) == (3, 2, [], [])
    tanh = stateless_step(nn.Tanh(), torch.float64, width=3)
    assert tanh.n_inputs == 3
    torch.testing.assert_close(tanh.run(x.unsqueeze(0)), torch.tanh(x).unsqueeze(0))
    with pytest.raises(TypeError, match=r"LSTM has no stateless step"):
        stateless_step(nn.LSTM(2, 2))


def test_run_checks_the_input_columns():
    step = GRUStep(nn.GRU(2, 3).double())
    with pytest.raises(ValueError, match=r"x must have shape \(batch, time, 2\)"):
        step.run(torch.zeros(1, 5, 3, dtype=torch.float64))
