"""Streaming of the linear dynamics: chunked calls equal one call; the per-sample step (eager,
TorchScript, torch.export) equals the sequence path; a network with the blocks streams through
the StreamingCompensator equal to the network (exported: tests/test_conformance.py)."""

from __future__ import annotations

import warnings

import pytest
import torch
from _dynamics_helpers import BACKENDS, signal, use_backend
from _helpers import RAW, run_split, step_loop

from torchhys import Backlash, InverseHysteresisNet
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.dynamics import StateSpace, TransferFunction


def _blocks() -> dict[str, torch.nn.Module]:
    torch.manual_seed(0)
    tf = TransferFunction.from_coefficients([0.3, -0.1, 0.2, 0.05],
                                            [1.0, -1.9, 1.5, -0.45])  # order 3
    return {
        "tf": tf,
        "tf strictly proper": TransferFunction(4, feedthrough=False).double(),
        "ss": StateSpace(3, 2).double(),
    }


def _script(step: torch.nn.Module) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():  # torch.jit.script is deprecated in torch 2.13
        warnings.filterwarnings("ignore", message=r"`torch\.jit\.script` is deprecated",
                                category=DeprecationWarning)
        return torch.jit.script(step)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", ["tf", "ss"])
@pytest.mark.parametrize("splits", [[1] * 20, [5, 100, 152], [256, 1], [100, 157]])
def test_chunked_calls_equal_one_call(backend, name, splits):
    block = _blocks()[name]
    x = signal((3, sum(splits)), seed=1)
    with use_backend(backend), torch.no_grad():
        whole, final = block(x)
        chunked, state = run_split(block, x, splits)
    exact = backend == "kernel" and name == "tf"  # the same arithmetic in the same order
    tol = 0 if exact else 1e-12
    torch.testing.assert_close(chunked, whole, rtol=0, atol=tol)
    torch.testing.assert_close(state, final, rtol=0, atol=tol)


@pytest.mark.parametrize("name", ["tf", "tf strictly proper", "ss"])
def test_unbatched_input(name):
    block = _blocks()[name]
    x = signal((40,), seed=2)
    with torch.no_grad():
        y, state = block(x)
        y2, _ = block(x[20:], block(x[:20])[1])
        yb, sb = block(x[None])
    assert y.shape == x.shape + ((block.n_outputs,) if name == "ss" else ())
    torch.testing.assert_close(y, yb[0], rtol=0, atol=0)
    torch.testing.assert_close(state, sb[0], rtol=0, atol=0)
    torch.testing.assert_close(y2, y[20:], rtol=0, atol=1e-13)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("name", ["tf", "tf strictly proper", "ss"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_step_eager_and_scripted_equal_sequence(backend, name, dtype):
    block = _blocks()[name].to(dtype)
    x = signal((2, 300), seed=3).to(dtype)
    with use_backend(backend), torch.no_grad():
        y, final = block(x)
    y = y.reshape(2, 300, -1)
    step = block.streaming_step(dtype)
    assert step.n_outputs == block.n_outputs and step.state_spec[0].size == final.shape[-1]
    # bit for bit: the kernel runs df2t_step's arithmetic; the state-space step's matrix
    # products may sum in another order
    exact = backend == "kernel" and name != "ss" and dtype == torch.float64
    tol = 0 if exact else (1e-12 if dtype == torch.float64 else 1e-5)
    rtol = 1e-5 if dtype == torch.float32 else 0
    for s in (step, _script(step)):
        f, state = step_loop(s, x, step.initial_state(x[:, :1]))
        assert f.shape == y.shape and f.dtype == dtype
        torch.testing.assert_close(f, y, rtol=rtol, atol=tol)
        torch.testing.assert_close(state[0], final, rtol=rtol, atol=tol)
    torch.testing.assert_close(step.run(x), y, rtol=rtol, atol=tol)


@pytest.mark.parametrize("name", ["tf", "ss"])
def test_exported_step_equals_sequence(name):
    block = _blocks()[name].float()
    x = signal((2, 50), seed=4).float()
    step = block.streaming_step(torch.float32)
    state = step.initial_state(x[:, :1])
    exported = torch.export.export(step, (x[:, :1], state)).module()
    with torch.no_grad():
        y, final = block(x)
        f, s = step_loop(exported, x, state)
    torch.testing.assert_close(f, y.reshape(2, 50, -1), rtol=0, atol=1e-5)
    torch.testing.assert_close(s[0], final, rtol=0, atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_network_streams_through_the_compensator(backend):
    blocks = _blocks()
    net = InverseHysteresisNet([blocks["tf"], Backlash([0.2, 0.6]), blocks["ss"],
                                blocks["tf strictly proper"]], hidden=12).double()
    x = 1.2 * torch.sin(torch.linspace(0, 25, 400, dtype=torch.float64))[None].repeat(2, 1)
    x[1] += 0.1 * signal((400,), seed=5)
    net.fit_normalization(x, 0.5 * x)
    with use_backend(backend), torch.no_grad():
        y, _ = net(x)
        comp = StreamingCompensator(net, limits=(-100.0, 100.0), **RAW)
        u = comp(x)
    torch.testing.assert_close(u, y, rtol=0, atol=1e-10)
    blocks = [row[2].split(": ")[-1] for row in comp.layout()]
    assert blocks.count("filter") == 2 and blocks.count("state") == 1
