"""Preisach streaming: chunked calls equal one call; the per-sample step (eager, TorchScript,
torch.export) equals the sequence path."""

from __future__ import annotations

import warnings

import pytest
import torch
from _helpers import assert_streams_as_eager, run_split, step_loop
from _preisach_helpers import model, signal

from torchhys.operators.preisach import Preisach


@pytest.mark.parametrize("smooth", [None, 0.05])
@pytest.mark.parametrize("splits", [[1] * 30, [5, 100, 152], [256, 1], [100, 157]])
def test_chunked_calls_equal_one_call(smooth, splits):
    m = model(smooth=smooth)
    x = signal(3, sum(splits), 9, seed=5)
    whole, final = m(x)
    chunked, state = run_split(m, x, splits)
    torch.testing.assert_close(chunked, whole, rtol=0, atol=1e-14)
    torch.testing.assert_close(state, final, rtol=0, atol=0)


@pytest.mark.parametrize("smooth", [None, 0.05])
@pytest.mark.parametrize("initial", ["demagnetized", "positive", "negative"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_step_eager_and_scripted_equal_sequence(smooth, initial, dtype):
    m = model(smooth=smooth, initial=initial)
    x = signal(2, 150, 9, seed=6).to(dtype)
    y, final = m.to(dtype)(x)
    step = m.streaming_step(dtype)
    assert step.n_outputs == 1 and step.state_spec[0].size == m.n_relays
    with warnings.catch_warnings():  # torch.jit.script is deprecated in torch 2.13
        warnings.filterwarnings("ignore", message=r"`torch\.jit\.script` is deprecated",
                                category=DeprecationWarning)
        scripted = torch.jit.script(step)
    for s in (step, scripted):
        f, state = step_loop(s, x, step.initial_state(x[:, :1]))
        assert f.shape == (2, 150, 1) and f.dtype == dtype
        tol = 1e-13 if dtype == torch.float64 else 1e-5
        torch.testing.assert_close(f[..., 0], y.detach(), rtol=0, atol=tol)
        torch.testing.assert_close(state[0], final, rtol=0, atol=0)
    torch.testing.assert_close(step.run(x)[..., 0], y.detach(), rtol=0, atol=tol)


@pytest.mark.parametrize("smooth", [None, 0.05])
def test_exported_step_equals_sequence(smooth):
    m = model(smooth=smooth).float()
    x = signal(2, 60, 9, seed=12).float()
    step = m.streaming_step(torch.float32)
    state = step.initial_state(x[:, :1])
    exported = torch.export.export(step, (x[:, :1], state)).module()
    with torch.no_grad():
        y, final = m(x)
        f, state = step_loop(exported, x, step.initial_state(x[:, :1]))
    torch.testing.assert_close(f[..., 0], y, rtol=0, atol=1e-5)
    torch.testing.assert_close(state[0], final, rtol=0, atol=0)


def test_streaming_compensator_of_a_network_with_a_preisach_operator():
    from torchhys.networks import InverseHysteresisNet

    torch.manual_seed(0)
    net = InverseHysteresisNet([Preisach(-1.5, 1.5, 8, smooth=0.1)], hidden=16).double()
    x = 1.2 * torch.sin(torch.linspace(0, 20, 300, dtype=torch.float64))[None]
    net.fit_normalization(x, 0.5 * x)
    assert_streams_as_eager(net, x, atol=1e-12)
