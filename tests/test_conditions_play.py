"""The conditioned play (torchhys.conditions.ConditionedBacklash): against a float64 numpy plain
loop, the ordinary play at theta = 0, chunked calls, its step, gradcheck in x and theta, the
conformance suite (its example without conditions) and the same checks by hand with
conditions, and a model of it streamed by the compensator, compiled as C and run in ONNX
Runtime with its conditions."""

# no `from __future__ import annotations`: TorchScript reads _Head's class annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from numpy.polynomial import legendre
from torch import Tensor, nn

import torchhys
from torchhys.conditions import ConditionedBacklash
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.operator import check_operator
from torchhys.testing import Example, check_conformance

sys.path.insert(0, str(Path(__file__).parent))
from _export_helpers import CC, NO_CC, run_driver  # noqa: E402

DT = torch.float64
R = [0.0, 0.1, 0.25, 0.5]


def _signal(B: int = 2, T: int = 300, n: int = 1, seed: int = 0) -> Tensor:
    """(B, T, 1 + n): nested reversals with noise, conditions drifting smoothly."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 1, T, dtype=DT)
    x = torch.stack([torch.sin(2 * math.pi * (3 + b) * t) * (0.4 + 0.6 * t)
                     + 0.02 * torch.randn(T, generator=g, dtype=DT) for b in range(B)])
    cs = [torch.stack([1.5 + torch.sin(2 * math.pi * (0.7 + 0.3 * j + 0.2 * b) * t + j)
                       for b in range(B)]) * (j + 1) for j in range(n)]
    return torch.stack([x, *cs], -1)


def _op(n: int = 1, degree: int = 2, seed: int = 1, x: Tensor | None = None) -> ConditionedBacklash:
    """Calibrated on ``x`` (default: _signal), theta random of scale 0.5."""
    op = ConditionedBacklash(torch.tensor(R, dtype=DT), n, degree=degree)
    op.calibrate(_signal(n=n) if x is None else x)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        op.theta.copy_(0.5 * torch.randn(op.theta.shape, generator=g, dtype=DT))
    return op


def _numpy_plays(x: np.ndarray, r: np.ndarray, theta: np.ndarray, lo: np.ndarray,
                 hi: np.ndarray, exponents: list[tuple[int, ...]]) -> np.ndarray:
    """The plays by a plain float64 loop: x (B, T, 1 + n) -> (B, T, N)."""
    B, T, _ = x.shape
    out = np.zeros((B, T, len(r)))
    for b in range(B):
        p = np.zeros(len(r))
        for t in range(T):
            cs = 2 * (x[b, t, 1:] - lo) / (hi - lo) - 1
            basis = np.array([np.prod([legendre.legval(cs[i], [0] * e[i] + [1])
                                       for i in range(len(e))]) for e in exponents])
            rc = r * np.exp(theta @ basis)
            for i in range(len(r)):
                p[i] = min(max(p[i], x[b, t, 0] - rc[i]), x[b, t, 0] + rc[i])
            out[b, t] = p
    return out


def _exponents(n: int, degree: int) -> list[tuple[int, ...]]:
    import itertools
    return [e for e in itertools.product(range(degree + 1), repeat=n) if 0 < sum(e) <= degree]


@pytest.mark.parametrize("n, degree", [(1, 1), (1, 3), (2, 2)])
def test_plays_are_the_numpy_loop(n: int, degree: int) -> None:
    x = _signal(T=300, n=n)
    op = _op(n, degree, x=x)
    # the basis' order inside the operator does not matter to the reference: match theta by
    # exponent
    ref_theta = np.zeros((len(R), len(op.exponents)))
    order = _exponents(n, degree)
    theta = op.theta.detach().numpy()
    for k, e in enumerate(op.exponents):
        ref_theta[:, order.index(tuple(e))] = theta[:, k]
    want = _numpy_plays(x.numpy(), np.array(R), ref_theta, op.cond_min.numpy(),
                        op.cond_max.numpy(), order)
    got, last = op(x)
    assert got.shape == (2, 300, len(R))
    np.testing.assert_allclose(got.detach().numpy(), want, rtol=0, atol=1e-13)
    assert torch.equal(last, got[:, -1])
    # the thresholds do move: theta != 0 is not the ordinary play
    plain = torchhys.Backlash(2 * torch.tensor(R, dtype=DT))(x[..., 0])[0]
    assert float((got.detach() - plain).abs().max()) > 0.05


def test_theta_zero_is_the_backlash_of_the_same_thresholds() -> None:
    x = _signal(T=500, n=2)
    op = ConditionedBacklash(torch.tensor(R, dtype=DT), 2, degree=2)
    op.calibrate(x)
    want = torchhys.Backlash(2 * torch.tensor(R, dtype=DT))(x[..., 0])[0]
    assert torch.equal(op(x)[0], want)
    assert torch.equal(op.streaming_step(DT).run(x), want)
    op0 = ConditionedBacklash(torch.tensor(R, dtype=DT), 0)
    assert torch.equal(op0(x[..., 0])[0], want)


def test_chunked_calls_equal_one_call_and_a_row_its_row() -> None:
    x = _signal(T=250, n=2)
    op = _op(2, 2, x=x)
    with torch.no_grad():
        whole, last = op(x)
        parts, state = [], None
        for chunk in x.split([1, 1, 2, 27, 70, 149], dim=1):
            f, state = op(chunk, state)
            parts.append(f)
        assert torch.equal(torch.cat(parts, 1), whole)
        assert torch.equal(state, last)
        row, row_last = op(x[1])
        assert torch.equal(row, whole[1]) and torch.equal(row_last, last[1])
        # a state of shape (N,) continues every row
        f, _ = op(x[:, 10:], whole[0, 9])
        g, _ = op(x[:1, 10:], whole[0, 9].unsqueeze(0))
        assert torch.equal(f[0], g[0])


@pytest.mark.parametrize("n", [0, 1, 2])
def test_the_step_equals_forward(n: int) -> None:
    x = _signal(T=200, n=n)
    op = _op(n, 2, x=x)
    step = op.streaming_step(DT)
    assert step.n_inputs == 1 + n and step.n_outputs == len(R)
    xs = x if n else x[..., 0]
    with torch.no_grad():
        want = op(xs)[0]
        got = step.run(xs)
    torch.testing.assert_close(got, want, rtol=0, atol=1e-15)
    scripted = torch.jit.script(step)
    state = step.initial_state(x[:, 0] if n else x[:, 0, :1])
    xt = x[:, 0] if n else x[:, 0, :1]
    torch.testing.assert_close(scripted(xt, state)[0], step(xt, state)[0], rtol=0, atol=0)


def test_gradcheck_in_x_and_theta() -> None:
    # 80 samples: the scan runs 10 chunks of 8 (its carries); smooth input, no ties
    t = torch.arange(80, dtype=DT)
    x = torch.stack([0.8 * torch.sin(0.31 * t + 0.3) + 0.01 * t,
                     0.4 + 0.3 * torch.cos(0.11 * t + 0.2) + 0.005 * t,
                     -0.2 + 0.5 * torch.sin(0.07 * t)], -1).unsqueeze(0).repeat(2, 1, 1)
    x[1, :, 0] = 0.7 * torch.cos(0.27 * t)
    op = ConditionedBacklash(torch.tensor([0.05, 0.2, 0.45], dtype=DT), 2, degree=2)
    op.calibrate(x)
    theta = (0.3 * torch.randn(op.theta.shape, generator=torch.Generator().manual_seed(2),
                               dtype=DT)).requires_grad_()

    def plays(v: Tensor, th: Tensor) -> Tensor:
        return torch.func.functional_call(op, {"theta": th}, (v,))[0]

    xv = x.clone().requires_grad_()
    assert torch.autograd.gradcheck(plays, (xv, theta), eps=1e-6, atol=1e-8)
    gx, gth = torch.autograd.grad(plays(xv, theta).sum(), (xv, theta))
    assert float(gth.abs().max()) > 0.1 and float(gx[..., 1:].abs().max()) > 0.01


def test_second_derivative_in_x_and_theta() -> None:
    """gradgradcheck: the play's selection is piecewise constant, exp(theta . b) is not."""
    t = torch.arange(30, dtype=DT)
    x = torch.stack([0.8 * torch.sin(0.41 * t + 0.3), 0.3 * torch.cos(0.13 * t)], -1)[None]
    op = ConditionedBacklash(torch.tensor([0.1, 0.3], dtype=DT), 1, degree=2)
    op.calibrate(x)
    theta = torch.tensor([[0.2, -0.3], [0.4, 0.1]], dtype=DT, requires_grad=True)
    xv = x.clone().requires_grad_()
    assert torch.autograd.gradgradcheck(
        lambda v, th: torch.func.functional_call(op, {"theta": th}, (v,))[0], (xv, theta))


def test_gradients_at_ties_follow_the_backlash() -> None:
    """A walk on a grid of 1/8 with flat stretches and thresholds on the grid (ties): at
    theta = 0 the gradient in x is Backlash's (the inactive branch at a tie), and the one in
    theta is the width's times ``2 r_i c~`` for a constant scaled condition c~ = 0.5."""
    from torchhys._conformance import signal
    x = signal(300)
    r = torch.tensor([0.0, 0.125, 0.25, 0.375], dtype=DT)
    g = torch.randn(2, 300, 4, generator=torch.Generator().manual_seed(0), dtype=DT)
    widths = (2 * r).requires_grad_()
    xb = x.clone().requires_grad_()
    gx_ref, gw = torch.autograd.grad((torchhys.functional.backlash(xb, widths) * g).sum(),
                                     (xb, widths))
    op = ConditionedBacklash(r, 1, degree=1)
    op.calibrate(torch.tensor([[[0.0, -1.0], [0.0, 3.0]]], dtype=DT))  # c~ = (c - 1) / 2
    xc = torch.stack([x, torch.full_like(x, 2.0)], -1).requires_grad_()
    gx, gth = torch.autograd.grad((op(xc)[0] * g).sum(), (xc, op.theta))
    torch.testing.assert_close(gx[..., 0], gx_ref, rtol=0, atol=1e-12)
    assert float(gx_ref.abs().max()) > 1.0
    torch.testing.assert_close(gth[:, 0], gw * 2 * r * 0.5, rtol=0, atol=1e-12)


def test_theta_is_learned_from_a_conditioned_loop() -> None:
    """Plays whose width doubles over the condition's range: least squares on theta (Adam)
    recovers the log-slope, which theta = 0 misses."""
    x = _signal(B=3, T=400, n=1)
    x[..., 1] = torch.tensor([0.0, 1.0, 2.0], dtype=DT).view(3, 1)
    true = ConditionedBacklash(torch.tensor([0.3], dtype=DT), 1, degree=1)
    true.calibrate(x)
    with torch.no_grad():
        true.theta.fill_(math.log(2.0) / 2)  # r(c~) = 0.3 * 2 ** (c~ / 2): 0.21 .. 0.42
    y = true(x)[0].detach()
    op = ConditionedBacklash(torch.tensor([0.3], dtype=DT), 1, degree=1)
    op.calibrate(x)
    start = float((op(x)[0] - y).square().mean())
    opt = torch.optim.Adam(op.parameters(), lr=0.05)
    for _ in range(150):
        opt.zero_grad()
        loss = (op(x)[0] - y).square().mean()
        loss.backward()
        opt.step()
    assert abs(float(op.theta) - math.log(2.0) / 2) < 0.01
    assert float((op(x)[0] - y).square().mean()) < 1e-3 * start


# --- the conformance suite and its checks with conditions ---------------------------------------


EXAMPLE = Example(lambda: ConditionedBacklash(torch.tensor([0.0, 0.15, 0.4], dtype=DT), 0),
                  bad_values={"thresholds": -1.0})
"""The suite's example: without conditions, the protocol's one input (x (batch, time));
with conditions the step takes [x, conditions], which the suite does not feed (the checks
by hand below)."""


def test_the_conformance_suite_passes_without_conditions() -> None:
    """Every default check of torchhys.testing.CHECKS holds (none skipped)."""
    got = check_conformance(ConditionedBacklash, EXAMPLE)
    assert got == dict.fromkeys(torchhys.testing.DEFAULT_CHECKS)


@pytest.mark.slow
def test_the_conformance_suite_compiling_checks_without_conditions() -> None:
    """torch.compile, torch.export (dynamic time) and AOTInductor on the same example."""
    got = check_conformance(ConditionedBacklash, EXAMPLE, checks=["compile", "export", "aoti"])
    assert got == dict.fromkeys(["compile", "export", "aoti"])


def test_with_conditions_it_is_no_operator_of_one_input() -> None:
    with pytest.raises(TypeError, match=r"has n_inputs = 2"):
        check_operator(_op(1, 1))
    assert check_operator(ConditionedBacklash(R, 0)).n_inputs == 1


def test_bad_arguments_are_one_line_errors_naming_them() -> None:
    cases = [
        (lambda: ConditionedBacklash([0.1, -0.2]), r"^thresholds must be non-negative"),
        (lambda: ConditionedBacklash([[0.1]]), r"^thresholds must have shape \(N,\)"),
        (lambda: ConditionedBacklash([0.1], -1), r"^n_conditions must be an int >= 0"),
        (lambda: ConditionedBacklash([0.1], 1, degree=0), r"^degree must be an int >= 1"),
        (lambda: ConditionedBacklash([0.1], 1, degree=1.5), r"^degree must be an int >= 1"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError, match=message) as info:
            call()
        assert "\n" not in str(info.value)


def test_bad_input_and_state_are_one_line_errors() -> None:
    op = _op(2, 1)
    x = _signal(T=20, n=2)
    cases = [
        (lambda: op(x[..., :2]), ValueError, r"^x must have shape \(time, 3\) or \(batch, time, "
                                             r"3\) \(the input, then 2 condition column\(s\)\)"),
        (lambda: op(x[..., 0]), ValueError, r"^x must have shape"),
        (lambda: op(x[:, :0]), ValueError, r"^x must have shape"),
        (lambda: op(x.long()), TypeError, r"^x must have a floating-point dtype"),
        (lambda: op("x"), TypeError, r"^x must be a torch\.Tensor"),
        (lambda: op(x.index_put((torch.tensor(0), torch.tensor(3), torch.tensor(1)),
                                torch.tensor(float("nan"), dtype=DT))),
         ValueError, r"^x must be finite, .* \(first at index \(0, 3, 1\)\)"),
        (lambda: op(x, torch.zeros(3, len(R), dtype=DT)), ValueError, r"^state must have shape"),
        (lambda: op(x, torch.full((2, len(R)), float("nan"), dtype=DT)), ValueError,
         r"^state must be finite"),
        (lambda: ConditionedBacklash(R, 2)(x), ValueError,
         r"^ConditionedBacklash is not calibrated: call calibrate\(x\)"),
        (lambda: ConditionedBacklash(R, 2).streaming_step(DT), ValueError,
         r"^ConditionedBacklash is not calibrated"),
        (lambda: ConditionedBacklash(R, 2).calibrate(x * torch.tensor([1.0, 0.0, 1.0],
                                                                       dtype=DT)),
         ValueError, r"^x: condition column 0 is constant \(0\.0\) over the calibration"),
    ]
    for call, error, message in cases:
        with pytest.raises(error, match=message) as info:
            call()
        assert "\n" not in str(info.value)


def test_loading_checks_shapes_and_values_all_or_nothing() -> None:
    op = _op(2, 2)
    before = {k: v.clone() for k, v in op.state_dict().items()}
    assert list(before) == ["theta", "thresholds", "cond_min", "cond_max"]
    bad = [({"thresholds": torch.full((len(R),), -1.0, dtype=DT)}, "thresholds"),
           ({"theta": torch.full_like(before["theta"], float("inf"))}, "theta"),
           ({"cond_max": before["cond_min"] - 1}, "cond_max"),
           ({"theta": torch.zeros(len(R), 2, dtype=DT)}, "theta")]
    for change, key in bad:
        with pytest.raises((ValueError, RuntimeError), match=key):
            op.load_state_dict({**before, **change})
        for k, v in op.state_dict().items():
            assert torch.equal(v, before[k]), k
    fresh = ConditionedBacklash(R, 2, degree=2).double()
    fresh.load_state_dict(before)
    assert torch.equal(fresh(_signal(n=2))[0], op(_signal(n=2))[0])


# --- a model of it, streamed and exported ----------------------------------------------------


class _Head(nn.Module):
    """``u = b0 + b1 x + plays @ w`` on ``[x, conditions..., plays...]`` (batch, 1 + n + N)."""

    n: int

    def __init__(self, w: Tensor, b: Tensor, n: int, dtype: torch.dtype) -> None:
        super().__init__()
        self.register_buffer("w", w.to(dtype).reshape(-1, 1).clone())
        self.register_buffer("b", b.to(dtype).clone())
        self.n = n

    def forward(self, z: Tensor) -> Tensor:
        return self.b[0] + self.b[1] * z[:, :1] + torch.mm(z[:, 1 + self.n:], self.w)


class PlayModel(nn.Module):
    """A conditioned model of the protocol (docs/conditions.md): the conditioned plays on
    ``[x, conditions]`` and an affine readout, ``u = b0 + b1 x + sum_i w_i p_i``."""

    def __init__(self, op: ConditionedBacklash) -> None:
        super().__init__()
        self.op = op
        self.n_conditions = op.n_conditions
        g = torch.Generator().manual_seed(5)
        self.register_buffer("w", torch.randn(op.n_outputs, generator=g, dtype=DT))
        self.register_buffer("b", torch.tensor([0.1, 0.7], dtype=DT))

    @property
    def cond_min(self) -> Tensor:
        return self.op.cond_min

    @property
    def cond_max(self) -> Tensor:
        return self.op.cond_max

    def forward(self, x: Tensor, conditions: Tensor) -> Tensor:
        p, _ = self.op(torch.cat([x.unsqueeze(-1), conditions], -1))
        p = p.unsqueeze(-1) if p.dim() == x.dim() else p  # one feature: (batch, time)
        return self.b[0] + self.b[1] * x + p @ self.w

    def streaming_steps(self, dtype: torch.dtype) -> list:
        return [self.op.streaming_step(dtype)]

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        return _Head(self.w, self.b, self.n_conditions, dtype)


LIMITS = (-1e6, 1e6)


def _model(n: int = 2) -> tuple[PlayModel, Tensor]:
    x = _signal(B=3, T=300, n=n)
    return PlayModel(_op(n, 2, x=x)), x


def test_the_compensator_streams_the_model_with_its_conditions() -> None:
    m, x = _model()
    comp = StreamingCompensator(m, limits=LIMITS, direction="none")
    u = torch.stack([comp.step(x[:, k, 0], x[:, k, 1:]) for k in range(x.shape[1])], 1)
    want = m(x[..., 0], x[..., 1:])
    assert float((u - want).abs().max()) <= 1e-12
    assert torch.equal(comp(x[..., 0], x[..., 1:]), u)
    assert torch.equal(torch.jit.script(comp)(x[..., 0], x[..., 1:]), u)
    # a NaN sample, and a NaN condition, are held and counted; the state is kept
    comp.reset()
    xs, cs = x[0, :, 0].clone(), x[0, :, 1:].clone()
    xs[40], cs[90, 1] = float("nan"), float("nan")
    got = torch.cat([comp.step(xs[k:k + 1], cs[k:k + 1]) for k in range(len(xs))])
    keep = [k for k in range(len(xs)) if k not in (40, 90)]
    ref = m(x[0, keep, 0], x[0, keep, 1:])
    assert float((got[keep] - ref).abs().max()) <= 1e-12
    assert got[40] == got[39] and got[90] == got[89]
    assert comp.nonfinite_count().tolist() == [2]


DRIVER = r"""
#include <stdio.h>
#include "torchhys_comp.h"
int main(void) {
    torchhys_comp_state s;
    double x, c0, c1;
    torchhys_comp_real cs[torchhys_comp_N_CONDITIONS];
    torchhys_comp_init(&s);
    while (scanf("%lf %lf %lf", &x, &c0, &c1) == 3) {
        cs[0] = (torchhys_comp_real)c0;
        cs[1] = (torchhys_comp_real)c1;
        printf("%.17g\n", (double)torchhys_comp_step(&s, (torchhys_comp_real)x, cs));
    }
    printf("%lld %lld\n", (long long)torchhys_comp_nonfinite_count(&s),
           (long long)torchhys_comp_out_of_range_count(&s));
    return 0;
}
"""


def _sequence() -> tuple[PlayModel, Tensor, Tensor]:
    """The model and one row with a NaN sample, a NaN condition, a condition far out."""
    m, x = _model()
    xs, cs = x[1, :, 0].clone(), x[1, :, 1:].clone()
    xs[50], cs[80, 0], cs[120, 1] = float("nan"), float("nan"), 40.0
    return m, xs, cs


def _compensator_run(m: PlayModel, xs: Tensor, cs: Tensor, dtype: torch.dtype
                     ) -> tuple[Tensor, StreamingCompensator]:
    comp = StreamingCompensator(m.to(dtype), limits=LIMITS, direction="none")
    u = torch.cat([comp.step(xs[k:k + 1].to(dtype), cs[k:k + 1].to(dtype))
                   for k in range(len(xs))]).double()
    return u, comp


@pytest.mark.skipif(CC is None, reason=NO_CC)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_c_step_equals_the_torch_compensator(tmp_path: Path, dtype: torch.dtype) -> None:
    from torchhys.deploy.c import to_c
    m, xs, cs = _sequence()
    h, src = to_c(m, tmp_path, direction="none", limits=LIMITS, dtype=dtype)
    assert "const torchhys_comp_real *conditions);" in h.read_text()
    out = run_driver(tmp_path, DRIVER, src, ((a, *b) for a, b in zip(xs, cs, strict=True)))
    u_c = torch.tensor([float(v) for v in out[:len(xs)]], dtype=DT)
    u, comp = _compensator_run(m, xs, cs, dtype)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert float((u_c - u).abs().max()) <= tol * max(1.0, float(u.abs().max()))
    assert [int(v) for v in out[len(xs)].split()] == [
        int(comp.nonfinite_count()), int(comp.out_of_range_count())] == [2, 1]


def test_the_onnx_step_equals_the_torch_compensator(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from torchhys.deploy.export_onnx import load_onnx, to_onnx
    m, xs, cs = _sequence()
    stepper = load_onnx(to_onnx(m, tmp_path / "comp.onnx", direction="none", limits=LIMITS,
                                batch=1))
    assert stepper.metadata["n_conditions"] == "2"
    got = torch.cat([stepper.step(xs[k:k + 1], cs[k:k + 1]) for k in range(len(xs))])
    u, comp = _compensator_run(m, xs, cs, DT)
    assert float((got - u).abs().max()) <= 1e-12
    assert stepper.nonfinite_count().tolist() == comp.nonfinite_count().tolist() == [2]
    assert stepper.out_of_range_count().tolist() == comp.out_of_range_count().tolist()


def test_the_torchscript_file_equals_the_torch_compensator(tmp_path: Path) -> None:
    from torchhys.deploy.export import load_torchscript, to_torchscript
    m, xs, cs = _sequence()
    to_torchscript(m, tmp_path / "comp.pt", direction="none", limits=LIMITS)
    loaded = load_torchscript(tmp_path / "comp.pt")
    got = torch.cat([loaded.step(xs[k:k + 1], cs[k:k + 1]) for k in range(len(xs))])
    u, _ = _compensator_run(m, xs, cs, DT)
    assert torch.equal(got, u)
