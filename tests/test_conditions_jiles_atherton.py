"""The conditioned Jiles-Atherton model (torchhys.conditions.ConditionedJilesAtherton): against a
float64 numpy loop, JilesAtherton at theta = 0, chunked calls, its step, gradcheck in x, raw
and theta, the conformance suite (its example without conditions), bad input, and a model of
it streamed by the compensator, compiled as C and run in ONNX Runtime with its conditions."""

# no `from __future__ import annotations`: test_conditions_play's head is scripted
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import Tensor

import torchhys
from torchhys.conditions import ConditionedJilesAtherton
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.testing import Example, check_conformance

sys.path.insert(0, str(Path(__file__).parent))
from _export_helpers import CC, NO_CC, run_driver  # noqa: E402
from test_conditions_play import DRIVER, LIMITS, PlayModel, _signal  # noqa: E402

DT = torch.float64


def _op(n: int = 1, degree: int = 2, x: Tensor | None = None, scale: float = 0.1,
        seed: int = 1) -> ConditionedJilesAtherton:
    op = ConditionedJilesAtherton(n, degree=degree)
    op.calibrate(_signal(n=n) if x is None else x)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        op.theta.copy_(scale * torch.randn(op.theta.shape, generator=g, dtype=DT))
    return op


def _langevin(z: float) -> tuple[float, float]:
    """L(z) and L'(z) (series below |z| = 0.1, where the closed forms cancel)."""
    if abs(z) < 0.1:
        z2 = z * z
        return z * (1 / 3 - z2 * (1 / 45 - z2 * 2 / 945)), 1 / 3 - z2 * (1 / 15 - z2 * 2 / 189)
    return 1 / math.tanh(z) - 1 / z, 1 / z ** 2 - 1 / math.sinh(z) ** 2


def _numpy_ja(x: np.ndarray, raw: np.ndarray, theta: np.ndarray, lo: np.ndarray,
              hi: np.ndarray, exponents: list[list[int]], mu0: float, substeps: int
              ) -> np.ndarray:
    """The inverse JA model by a plain float64 loop, each sample's parameters from its
    conditions: x (B, T, 1 + n) -> H (B, T)."""
    from numpy.polynomial import legendre
    B, T, _ = x.shape
    out = np.zeros((B, T))
    for row in range(B):
        b_prev = h = 0.0
        for t in range(T):
            cs = 2 * (x[row, t, 1:] - lo) / (hi - lo) - 1
            basis = np.array([np.prod([legendre.legval(cs[i], [0] * e[i] + [1])
                                       for i in range(len(e))]) for e in exponents])
            z = raw + theta @ basis
            ms, a, k, alpha = np.exp(z[:4])
            c = 1 / (1 + np.exp(-z[4]))
            db = (x[row, t, 0] - b_prev) / substeps
            delta = 1.0 if db >= 0 else -1.0
            bs = b_prev
            for _ in range(substeps):
                m = bs / mu0 - h
                he = (h + alpha * m) / a
                lz, dlz = _langevin(he)
                man = ms * lz
                gap = man - (m - c * man) / (1 - c)
                irr = delta * gap / k if delta * gap > 0 else 0.0
                chi_ = max((1 - c) * irr + c * ms / a * dlz, 0.0)
                chi = chi_ / max(1 - alpha * chi_, 0.01)
                h += db / (mu0 * (1 + chi))
                bs += db
            b_prev = x[row, t, 0]
            out[row, t] = h
    return out


@pytest.mark.parametrize("n, degree", [(1, 2), (2, 1)])
def test_the_field_is_the_numpy_loop(n: int, degree: int) -> None:
    x = _signal(T=200, n=n)
    op = _op(n, degree, x=x)
    want = _numpy_ja(x.numpy(), op.raw.detach().numpy(), op.theta.detach().numpy(),
                     op.cond_min.numpy(), op.cond_max.numpy(), op.exponents, op.mu0,
                     op.substeps)
    h, last = op(x)
    h = h.detach()
    scale = float(np.abs(want).max())
    np.testing.assert_allclose(h.numpy(), want, rtol=0, atol=1e-10 * scale)
    assert torch.equal(last[:, 1], h[:, -1]) and torch.equal(last[:, 0], x[:, -1, 0])
    plain = torchhys.JilesAtherton()(x[..., 0])[0]
    assert float((h - plain).abs().max()) > 0.05 * scale  # the conditions move the loop


def test_theta_zero_is_the_jiles_atherton_of_the_same_parameters() -> None:
    x = _signal(T=150, n=2)
    kw = dict(ms=8e5, a=40.0, k=60.0, alpha=2e-4, c=0.3, substeps=3)
    op = ConditionedJilesAtherton(2, degree=2, **kw)
    op.calibrate(x)
    want = torchhys.JilesAtherton(**kw)(x[..., 0])[0]
    assert torch.equal(op(x)[0], want)
    assert torch.equal(op.streaming_step(DT).run(x)[..., 0], want)
    assert torch.equal(ConditionedJilesAtherton(0, **kw)(x[..., 0])[0], want)


def test_chunked_calls_and_the_step_equal_one_call() -> None:
    x = _signal(T=120, n=1)
    op = _op(1, 2, x=x)
    with torch.no_grad():
        whole, last = op(x)
        parts, state = [], None
        for chunk in x.split([1, 1, 2, 27, 89], dim=1):
            f, state = op(chunk, state)
            parts.append(f)
        assert torch.equal(torch.cat(parts, 1), whole) and torch.equal(state, last)
        row, row_last = op(x[1])
        assert torch.equal(row, whole[1]) and torch.equal(row_last, last[1])
        step = op.streaming_step(DT)
        assert (step.n_inputs, step.n_outputs) == (2, 1)
        assert torch.equal(step.run(x)[..., 0], whole)


def test_gradcheck_in_x_raw_and_theta() -> None:
    t = torch.arange(16, dtype=DT)
    x = torch.stack([0.8 * torch.sin(0.61 * t + 0.3) + 0.05 * t ** 0.5,
                     0.3 * torch.cos(0.2 * t)], -1)[None]
    op = ConditionedJilesAtherton(1, degree=2)
    op.calibrate(x)
    theta = torch.tensor([[0.1, -0.05]] * 5, dtype=DT) * torch.arange(1, 6, dtype=DT)[:, None]

    def field(v: Tensor, raw: Tensor, th: Tensor) -> Tensor:
        return torch.func.functional_call(op, {"raw": raw, "theta": th}, (v,))[0]

    args = (x.clone().requires_grad_(), op.raw.detach().clone().requires_grad_(),
            theta.requires_grad_())
    assert torch.autograd.gradcheck(field, args)  # eps 1e-6: errors about 3e-6 of entries ~1e3


def test_a_temperature_schedule_is_learned() -> None:
    """Rows at three temperatures, ms and k falling with it: gradient descent on theta from
    0 recovers their log-slopes."""
    x = _signal(B=3, T=120, n=1)
    x[..., 1] = torch.tensor([20.0, 60.0, 100.0], dtype=DT).view(3, 1)
    x[..., 0] *= 0.5  # below saturation (at 1 T the hot row's field runs away: a poor fit)
    true = ConditionedJilesAtherton(1, degree=1, substeps=1)
    true.calibrate(x)
    with torch.no_grad():
        true.theta[0, 0], true.theta[2, 0] = -0.2, -0.3  # ms and k at 100 C: 0.82x, 0.74x
    y = true(x)[0].detach()
    op = ConditionedJilesAtherton(1, degree=1, substeps=1)
    op.calibrate(x)
    op.raw.requires_grad_(False)
    opt = torch.optim.LBFGS([op.theta], max_iter=200, line_search_fn="strong_wolfe",
                            tolerance_grad=1e-12, tolerance_change=1e-14)

    def closure() -> Tensor:
        opt.zero_grad()
        loss = ((op(x)[0] - y) / y.std()).square().mean()
        loss.backward()
        return loss

    opt.step(closure)
    assert float(closure()) < 1e-10
    torch.testing.assert_close(op.theta.detach(), true.theta.detach(), rtol=0, atol=1e-5)


@pytest.mark.slow
def test_the_conformance_suite_passes_without_conditions() -> None:
    """Every default check but vmap_params (below; 9 s: the Python loop under vmap and
    gradgradcheck)."""
    example = Example(lambda: ConditionedJilesAtherton(0), bad_values={"raw": float("nan")})
    checks = [c for c in torchhys.testing.DEFAULT_CHECKS if c != "vmap_params"]
    got = check_conformance(ConditionedJilesAtherton, example, checks=checks)
    assert got == dict.fromkeys(checks)


@pytest.mark.slow
@pytest.mark.xfail(strict=True, raises=AssertionError, reason=(
    "as JilesAtherton's (tests/test_conformance.py): mu0 and substeps are read from their "
    "saved buffers into Python numbers when loaded (after_load), so functional_call with "
    "other buffers, and vmap over stacked ones, runs with the loaded values"))
def test_vmap_over_stacked_buffers_is_jiles_athertons_known_defect() -> None:
    example = Example(lambda: ConditionedJilesAtherton(0), bad_values={"raw": float("nan")})
    check_conformance(ConditionedJilesAtherton, example, checks=["vmap_params"])


def test_bad_arguments_and_input_are_one_line_errors() -> None:
    x = _signal(T=10, n=1)
    cases = [
        (lambda: ConditionedJilesAtherton(1, c=1.0), r"^c must be in \(0, 1\)"),
        (lambda: ConditionedJilesAtherton(1, k=-1.0), r"^k must be"),
        (lambda: ConditionedJilesAtherton(-1), r"^n_conditions must be an int >= 0"),
        (lambda: ConditionedJilesAtherton(1, degree=0), r"^degree must be an int >= 1"),
        (lambda: ConditionedJilesAtherton(1, substeps=0), r"^substeps must be an int >= 1"),
        (lambda: ConditionedJilesAtherton(1)(x), r"^ConditionedJilesAtherton is not calibrated"),
        (lambda: _op()(x[..., :1]), r"^x must have shape \(time, 2\) or \(batch, time, 2\)"),
        (lambda: _op()(x, torch.zeros(3, 2, dtype=DT)), r"^state must have shape \(2, 2\)"),
        (lambda: ConditionedJilesAtherton(1).calibrate(x * torch.tensor([1.0, 0.0])),
         r"^x: condition column 0 is constant .* cannot scale the parameters"),
    ]
    for call, message in cases:
        with pytest.raises(ValueError, match=message) as info:
            call()
        assert "\n" not in str(info.value)


@pytest.mark.skipif(CC is None, reason=NO_CC)
def test_a_model_streams_and_its_c_step_equals_the_torch_compensator(tmp_path: Path) -> None:
    from torchhys.deploy.c import to_c
    x = _signal(B=3, T=200, n=2)
    m = PlayModel(_op(2, 2, x=x))
    comp = StreamingCompensator(m, limits=LIMITS, direction="none")
    u = torch.stack([comp.step(x[:, k, 0], x[:, k, 1:]) for k in range(x.shape[1])], 1)
    want = m(x[..., 0], x[..., 1:])
    assert float((u - want).abs().max()) <= 1e-12 * float(want.abs().max())
    xs, cs = x[1, :, 0].clone(), x[1, :, 1:].clone()
    xs[50], cs[80, 0] = float("nan"), float("nan")
    comp = StreamingCompensator(m, limits=LIMITS, direction="none")
    u = torch.cat([comp.step(xs[k:k + 1], cs[k:k + 1]) for k in range(len(xs))])
    h, src = to_c(m, tmp_path, direction="none", limits=LIMITS)
    out = run_driver(tmp_path, DRIVER, src, ((a, *b) for a, b in zip(xs, cs, strict=True)))
    u_c = torch.tensor([float(v) for v in out[:len(xs)]], dtype=DT)
    assert float((u_c - u).abs().max()) <= 1e-12 * float(u.abs().max())
    assert [int(v) for v in out[len(xs)].split()] == [2, 0]


def test_the_onnx_step_equals_the_torch_compensator(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from torchhys.deploy.export_onnx import load_onnx, to_onnx
    x = _signal(B=3, T=200, n=2)
    m = PlayModel(_op(2, 2, x=x))
    xs, cs = x[1, :, 0].clone(), x[1, :, 1:].clone()
    xs[50] = float("nan")
    comp = StreamingCompensator(m, limits=LIMITS, direction="none")
    u = torch.cat([comp.step(xs[k:k + 1], cs[k:k + 1]) for k in range(len(xs))])
    stepper = load_onnx(to_onnx(m, tmp_path / "comp.onnx", direction="none", limits=LIMITS,
                                batch=1))
    got = torch.cat([stepper.step(xs[k:k + 1], cs[k:k + 1]) for k in range(len(xs))])
    assert float((got - u).abs().max()) <= 1e-12 * float(u.abs().max())
    assert stepper.nonfinite_count().tolist() == comp.nonfinite_count().tolist() == [1]


def test_mu0_and_substeps_travel_in_the_state_dict() -> None:
    saved = ConditionedJilesAtherton(1, mu0=2e-6, substeps=5)
    fresh = ConditionedJilesAtherton(1)
    fresh.load_state_dict(saved.state_dict())
    assert (fresh.mu0, fresh.substeps) == (2e-6, 5)
    bad = {**saved.state_dict(), "saved_substeps": torch.tensor(0)}
    with pytest.raises(ValueError, match="saved_substeps"):
        ConditionedJilesAtherton(1).load_state_dict(bad)
