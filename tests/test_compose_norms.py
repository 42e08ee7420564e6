"""Normalisation layers in a composition, exported: nn.LayerNorm, nn.RMSNorm, nn.BatchNorm1d /
2d in eval mode (folded at export into a per-channel scale and shift), nn.Softmax and
nn.LogSoftmax between an LSTM and the readout (a play -> nn.LSTM(8) -> norm -> nn.Linear).

Each composed model (seeded: non-trivial affine weights and running statistics) is exported
to C (compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror -pedantic``) and to ONNX (ONNX
Runtime), each run over tests/_export_helpers.record (turning points, ties, signed zeros, NaN
and inf held and counted, excursions beyond the training range clamped and counted) against
the eager compensator, whose step runs the torch layers themselves: float64 within 1e-12 of
the command's scale (FLOAT64_RTOL), float32 within FLOAT32_RTOL = 1e-4 (measured with gcc 12
on x86-64: float64 at most 2.2e-16, float32 at most 1.2e-7). The folded scale and shift
against numpy float64. Refused, in one line naming the layer and what to do: a batch norm
without running statistics (compose; to_c of a step that calls one), a batch norm in
training mode (to_c).
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
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
from _helpers import loop_net
from torch import Tensor, nn

import torchhys
from torchhys.compose import compose
from torchhys.deploy.c import to_c
from torchhys.deploy.c._norms import folded
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.operator import HysteresisOperator
from torchhys.step import OperatorStep, StateBlock

needs_cc = pytest.mark.skipif(CC is None, reason=NO_CC)
HIDDEN = 8
OPTIONS = {"direction": "none"}


LAYERS = {
    "layer": lambda: nn.LayerNorm(HIDDEN),
    "layer_no_affine": lambda: nn.LayerNorm(HIDDEN, elementwise_affine=False),
    "layer_no_bias": lambda: nn.LayerNorm(HIDDEN, bias=False, eps=1e-3),
    "rms": lambda: nn.RMSNorm(HIDDEN),
    "rms_eps_no_affine": lambda: nn.RMSNorm(HIDDEN, eps=1e-3, elementwise_affine=False),
    "batch1d": lambda: nn.BatchNorm1d(HIDDEN),
    "batch1d_no_affine": lambda: nn.BatchNorm1d(HIDDEN, affine=False, eps=1e-3),
    "batch2d": lambda: nn.BatchNorm2d(HIDDEN),
    "softmax": lambda: nn.Softmax(-1),
    "log_softmax": lambda: nn.LogSoftmax(-1),
}
#: one of each in a row (the default tests: one export a format and dtype)
CHAIN = ["layer_no_bias", "batch1d", "rms", "log_softmax", "softmax"]


def norm_of(kind: str, seed: int = 7) -> nn.Module:
    """The normalisation layer ``kind`` over HIDDEN features, with seeded weights and (batch
    norms) running statistics."""
    norm = LAYERS[kind]()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in norm.named_parameters():
            base = 1.0 if name == "weight" else 0.0
            p.copy_(base + 0.5 * torch.randn(p.shape, generator=g, dtype=p.dtype))
        if getattr(norm, "running_mean", None) is not None:
            norm.running_mean.copy_(0.3 * torch.randn(HIDDEN, generator=g))
            norm.running_var.copy_(0.05 + torch.rand(HIDDEN, generator=g))
    return norm


class NormNet(nn.Module):
    """A play, an LSTM on [x, play(x)], normalisations of its features one after the other,
    a readout: a batch norm on (batch, channels, time) (1d) or (batch, channels, time, 1)
    (2d)."""

    def __init__(self, norms: list[nn.Module]) -> None:
        super().__init__()
        self.play = torchhys.Backlash(torch.tensor([0.2]))
        self.lstm = nn.LSTM(2, HIDDEN, batch_first=True)
        self.norms = nn.ModuleList(norms)
        self.lin = nn.Linear(HIDDEN, 1)

    def forward(self, x: Tensor) -> Tensor:
        h, _ = self.lstm(torch.cat([x.unsqueeze(-1), self.play(x)[0]], -1))
        for norm in self.norms:
            if isinstance(norm, nn.BatchNorm2d):
                h = norm(h.transpose(1, 2).unsqueeze(-1)).squeeze(-1).transpose(1, 2)
            elif isinstance(norm, nn.BatchNorm1d):
                h = norm(h.transpose(1, 2)).transpose(1, 2)
            else:
                h = norm(h)
        return self.lin(h).squeeze(-1)


def composed(kind: str) -> torchhys.compose.Composed:
    """The composed NormNet of one layer ``kind`` (or of the ``"chain"``)."""
    torch.manual_seed(0)
    kinds = CHAIN if kind == "chain" else [kind]
    module = NormNet([norm_of(k, 7 + i) for i, k in enumerate(kinds)]).double().eval()
    x = (torch.sin(torch.linspace(0, 6, 100, dtype=torch.float64))
         * torch.linspace(0.4, 1.0, 100, dtype=torch.float64))[None]
    with torch.no_grad():
        y = module(x)
    return compose(module, x=x, y=y)


def samples(model: torchhys.compose.Composed, n: int) -> np.ndarray:
    return record(float(model.in_min), float(model.in_max), n=n, seed=4)


def reference(model: nn.Module, x: np.ndarray, dtype: torch.dtype) -> dict:
    comp = StreamingCompensator(copy.deepcopy(model).to(dtype), **OPTIONS)
    return stepped(comp, x, dtype)


def check_c(kind: str, dtype: torch.dtype, folder: Path, n: int = 600) -> float:
    model = composed(kind)
    x = samples(model, n)
    to_c(model, folder, dtype=dtype, **OPTIONS)
    got = run_c(compile_harness(folder), x)
    ref = reference(model, x, dtype)
    assert np.ptp(ref["u"]) > 1e-3  # the norm's output reaches the command
    return assert_equal_runs(got, ref, FLOAT64_RTOL if dtype == torch.float64 else FLOAT32_RTOL)


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_c(dtype: torch.dtype, tmp_path: Path) -> None:
    check_c("chain", dtype, tmp_path, n=1000)


@needs_cc
@pytest.mark.slow
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("kind", list(LAYERS))
def test_c_of_each_layer(kind: str, dtype: torch.dtype, tmp_path: Path) -> None:
    check_c(kind, dtype, tmp_path, n=2000)


@needs_cc
def test_the_batch_norm_is_one_multiply_add_a_channel(tmp_path: Path) -> None:
    """The C of the batch norm holds the folded scale and shift (numpy float64) and no
    square root or division."""
    model = composed("batch1d")
    to_c(model, tmp_path, **OPTIONS)
    source = (tmp_path / "torchhys_comp.c").read_text()
    block = source.split("aten.batch_norm.default */")[1].split("/*")[0]
    assert "sqrt" not in block and "/" not in block and block.count("*") == 1, block
    bn = model.module.norms[0]
    var, mean = bn.running_var.numpy(), bn.running_mean.numpy()
    scale = bn.weight.detach().numpy() / np.sqrt(var + bn.eps)
    shift = bn.bias.detach().numpy() - mean * scale
    got = folded(bn.weight, bn.bias, bn.running_mean, bn.running_var, bn.eps)
    np.testing.assert_allclose(got[0].numpy(), scale, rtol=1e-15)
    np.testing.assert_allclose(got[1].numpy(), shift, rtol=1e-15, atol=1e-16)
    for value in (*got[0].tolist(), *got[1].tolist()):  # the C's constants: these
        assert repr(value) in source


def check_onnx(kind: str, dtype: torch.dtype, folder: Path, n: int = 400) -> float:
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    model = composed(kind)
    x = samples(model, n)
    got = run_onnx(model, x, folder / "comp.onnx", dtype, **OPTIONS)
    return assert_equal_runs(got, reference(model, x, dtype),
                             FLOAT64_RTOL if dtype == torch.float64 else FLOAT32_RTOL)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_onnx(dtype: torch.dtype, tmp_path: Path) -> None:
    check_onnx("chain", dtype, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("kind", list(LAYERS))
def test_onnx_of_each_layer(kind: str, dtype: torch.dtype, tmp_path: Path) -> None:
    check_onnx(kind, dtype, tmp_path, n=1000)


class NormOpsStep(OperatorStep):
    """A step of the norm templates' other shapes (their C against TorchScript): a layer norm
    over two dims and one over 48 features, an RMS norm with a weight and torch's default
    eps, softmax over a middle dim, log-softmax of a long row, a functional batch norm of a
    (batch, channels, 3) input; a state s that follows x, the features of z = x - s."""

    def __init__(self) -> None:
        super().__init__()
        self.n_outputs = 8
        self.state_spec = [StateBlock("s", 4, from_sample=[1.0, 0.5, 0.0, -1.0])]
        g = torch.Generator().manual_seed(3)
        for name, shape in (("w22", (2, 2)), ("b22", (2, 2)), ("w4", (4,)), ("bn_w", (4,)),
                            ("bn_b", (4,))):
            self.register_buffer(name, 1.0 + 0.5 * torch.randn(shape, generator=g,
                                                                dtype=torch.float64))
        self.register_buffer("mean", 0.2 * torch.randn(4, generator=g, dtype=torch.float64))
        self.register_buffer("var", 0.1 + torch.rand(4, generator=g, dtype=torch.float64))
        self.register_buffer("ramp", torch.linspace(-1.0, 1.0, 48, dtype=torch.float64))

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        s = state[0]
        z = x - s
        a = F.layer_norm(z.reshape(-1, 2, 2) * 3.0 + 1.0, [2, 2], self.w22, self.b22,
                         eps=1e-4).reshape(-1, 4)
        long = F.layer_norm(torch.cat([z] * 12, 1) + self.ramp, [48])
        b = F.rms_norm(z * 3.0 + 0.5, [4], self.w4) + long.narrow(1, 5, 4)
        c = torch.softmax(torch.stack([z, -2.0 * z, z * z], 1) * 4.0, dim=1).sum(1)
        d = torch.log_softmax(torch.cat([z, z * 2.0, -z] * 8, 1) * 3.0, dim=-1).narrow(1, 2, 4)
        e = F.batch_norm(torch.stack([z, z * z, -z], 2), self.mean, self.var, self.bn_w,
                         self.bn_b, training=False, eps=1e-3).sum(2)
        new = torch.clamp(s + 0.3 * (x - s), -5.0, 5.0)
        return torch.cat([a + b + c + d + e, new], 1), [new]


class NormOps(HysteresisOperator):
    """The operator of :class:`NormOpsStep` (its forward runs the step)."""

    n_outputs = 8

    def forward(self, x: Tensor, state: object = None) -> tuple[Tensor, None]:
        xb = x if x.dim() == 2 else x[None]
        f = NormOpsStep().to(xb.dtype).run(xb)
        return (f if x.dim() == 2 else f[0]), None

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return NormOpsStep().to(dtype)


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_norm_templates_of_other_shapes(dtype: torch.dtype, tmp_path: Path) -> None:
    net = loop_net([NormOps(), torchhys.Backlash([0.4])])
    x = record(float(net.in_min), float(net.in_max), n=1000)
    to_c(net, tmp_path, dtype=dtype)
    got = run_c(compile_harness(tmp_path), x)
    ts = run_torchscript(net, x, tmp_path / "comp.pt", dtype)
    assert np.ptp(ts["u"]) > 1e-3
    assert_equal_runs(got, ts, FLOAT64_RTOL if dtype == torch.float64 else FLOAT32_RTOL)


# --- refusals -------------------------------------------------------------------------------


def test_a_batch_norm_without_running_statistics_does_not_compose() -> None:
    module = NormNet([nn.BatchNorm1d(HIDDEN, track_running_stats=False)]).double()
    x = torch.sin(torch.linspace(0, 6, 50, dtype=torch.float64))[None]
    with pytest.raises(ValueError, match=r"node 'norms_0' \(BatchNorm1d\) cannot stream: a batch "
                       r"norm without running statistics \(track_running_stats=False\)") as err:
        compose(module, x=x, y=x)
    assert "\n" not in str(err.value) and ".eval()" in str(err.value)


class BatchNormStep(OperatorStep):
    """A step that calls a batch norm the C refuses: in training mode (``stats``) or without
    running statistics, on the sample repeated (batch, 2 channels, 2)."""

    def __init__(self, stats: bool) -> None:
        super().__init__()
        self.n_outputs = 2
        self.stats = stats
        self.state_spec = [StateBlock("s", 1)]
        self.register_buffer("mean", torch.zeros(2, dtype=torch.float64))
        self.register_buffer("var", torch.ones(2, dtype=torch.float64))

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        v = torch.stack([torch.cat([x, state[0]], 1), torch.cat([state[0], x], 1)], 2)
        if self.stats:
            out = F.batch_norm(v, self.mean.clone(), self.var.clone(), training=True)
        else:
            out = F.batch_norm(v, None, None, training=True)
        return out.sum(2), [x]


class BatchNormOperator(HysteresisOperator):
    """The operator of :class:`BatchNormStep` (its forward runs the step)."""

    n_outputs = 2

    def __init__(self, stats: bool) -> None:
        super().__init__()
        self.stats = stats

    def forward(self, x: Tensor, state: object = None) -> tuple[Tensor, None]:
        xb = x if x.dim() == 2 else x[None]
        f = BatchNormStep(self.stats).to(xb.dtype).run(xb)
        return (f if x.dim() == 2 else f[0]), None

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return BatchNormStep(self.stats).to(dtype)


@pytest.mark.parametrize(("stats", "message"), [
    (True, r"a batch norm in training mode normalises by the batch's own statistics: call "
           r"\.eval\(\)"),
    (False, r"a batch norm without running statistics \(track_running_stats=False\) "
            r"normalises by the batch's own statistics, so its output depends on the batch"),
])
def test_to_c_refuses_a_batch_norm_of_the_batch(stats: bool, message: str,
                                                tmp_path: Path) -> None:
    net = loop_net([BatchNormOperator(stats), torchhys.Backlash([0.4])])
    with pytest.raises(ValueError, match=r"to_c: node '\w+' \(aten\.batch_norm\.default, from "
                       r"comp\.slots\.0\.step \(\S*BatchNormStep\) at test_compose_norms\.py:"
                       r"\d+ in forward\): " + message) as err:
        to_c(net, tmp_path)
    assert "\n" not in str(err.value)
    assert not list(tmp_path.iterdir())
