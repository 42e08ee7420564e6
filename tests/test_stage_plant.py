"""The piezo-stage plant (hysteresis, then a lightly damped second-order stage): against
scipy's zero-order hold and dlsim, the analytic step response and its overshoot, unit DC gain
(slow inputs give the hysteresis output), autograd, batches, time grid or rate, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import signal

from torchhys import Backlash, PrandtlIshlinskii
from torchhys.functional.linear_filter import state_space
from torchhys.plants import (
    BoucWen,
    PiezoStage,
    bouc_wen,
    default_stage_hysteresis,
    second_order_zoh,
)


def _scipy_zoh(fn: float, zeta: float, fs: float) -> tuple:
    wn = 2 * math.pi * fn
    A = np.array([[0.0, 1.0], [-wn**2, -2 * zeta * wn]])
    B = np.array([[0.0], [wn**2]])
    C, D = np.array([[1.0, 0.0]]), np.zeros((1, 1))
    return signal.cont2discrete((A, B, C, D), 1 / fs, method="zoh")


def _walk(shape: tuple[int, ...], seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return 0.4 * torch.randn(shape, generator=g, dtype=torch.float64).cumsum(-1)


@pytest.mark.parametrize("fn, zeta, fs", [(8.0, 0.07, 160.0), (1000.0, 0.05, 20_000.0),
                                          (3.0, 0.1, 25.0), (2.0, 1.5, 100.0)])
def test_matches_scipy_cont2discrete_and_dlsim(fn, zeta, fs):
    stage = PiezoStage(fn, zeta)
    u = _walk((3, 400))
    y = stage(u, fs=fs)
    h = stage.hysteresis_output(u)
    Ad, Bd, Cd, Dd, dt = _scipy_zoh(fn, zeta, fs)
    for row in range(3):
        _, ref, _ = signal.dlsim((Ad, Bd, Cd, Dd, dt), h[row].numpy())
        np.testing.assert_allclose(y[row].numpy(), ref[:, 0], rtol=0, atol=1e-12)
    num, den = signal.ss2tf(Ad, Bd, Cd, Dd)
    b, a = stage.coefficients(fs)
    np.testing.assert_allclose(b.numpy(), num[0], rtol=0, atol=1e-13)
    np.testing.assert_allclose(a.numpy(), den, rtol=0, atol=1e-13)
    assert float(b.sum() / a.sum()) == pytest.approx(1.0, abs=1e-12)  # unit DC gain


@pytest.mark.parametrize("zeta", [0.05, 0.07, 0.1])
def test_step_response_is_exact_and_overshoot_matches_zeta(zeta):
    fn, fs = 5.0, 5000.0
    stage = PiezoStage(fn, zeta)
    n = 4000
    y = stage.dynamics(torch.ones(n, dtype=torch.float64), fs=fs)
    t = torch.arange(n, dtype=torch.float64) / fs
    wn, root = 2 * math.pi * fn, math.sqrt(1 - zeta**2)
    wd = wn * root
    exact = 1 - torch.exp(-zeta * wn * t) * (torch.cos(wd * t) + zeta / root * torch.sin(wd * t))
    # a held step is what the zero-order hold assumes: the samples are the continuous response
    # (to the rounding of the matrix exponential, compounded over 4000 steps)
    torch.testing.assert_close(y, exact, rtol=0, atol=1e-10)
    overshoot = float(y.max()) - 1.0
    assert overshoot == pytest.approx(math.exp(-math.pi * zeta / root), abs=1e-5)
    assert float(t[y.argmax()]) == pytest.approx(math.pi / wd, abs=1 / fs)


def test_dc_gain_is_one_slow_inputs_give_the_hysteresis_output():
    fn, fs = 10.0, 200.0
    stage = PiezoStage(fn, 0.07)
    # a held level: after the ringing has decayed (100 time constants 1/(zeta w_n)) y = h
    u = torch.cat([torch.linspace(0, 4.0, 50), torch.full((5000,), 4.0)]).double()
    y, h = stage(u, fs=fs), stage.hysteresis_output(u)
    assert abs(float(y[-1] - h[-1])) < 1e-10
    # a sine at f_n / 1000 (two periods): y = h up to the lag 2 zeta / w_n + dt / 2
    t = torch.arange(int(200 * fs), dtype=torch.float64) / fs
    u = 6 * torch.sin(2 * math.pi * fn / 1000 * t)
    y, h = stage(u, fs=fs), stage.hysteresis_output(u)
    lag = 2 * 0.07 / (2 * math.pi * fn) + 0.5 / fs
    slope = float(torch.diff(h).abs().max()) * fs
    assert float((y - h).abs().max()) < 1.25 * slope * lag
    assert float((y - h).abs().max()) < 3e-4 * float(h.max() - h.min())


def test_default_hysteresis_is_the_documented_prandtl_ishlinskii():
    op = default_stage_hysteresis()
    assert isinstance(op, PrandtlIshlinskii)
    u = 6 * torch.sin(torch.linspace(0, 6 * math.pi, 3000, dtype=torch.float64))
    h, _ = op(u)
    assert float(h.max()) == pytest.approx(10.0) and float(h.min()) == pytest.approx(-10.0)
    # the loop at u = 0 (the sample after each crossing, where the branch slope is 2)
    crossings = h[1001:][torch.diff(torch.sign(u[1000:])) != 0]
    assert crossings.numel() >= 3
    torch.testing.assert_close(crossings.abs(), torch.full_like(crossings, 2.0), atol=0.1,
                               rtol=0)


def test_time_grid_equals_rate_and_batch_rows_equal_single_calls():
    stage = PiezoStage(8.0, 0.07)
    u = _walk((2, 300), seed=1)
    t = 0.25 + torch.arange(300, dtype=torch.float64) / 160.0
    y = stage(u, t)
    torch.testing.assert_close(y, stage(u, fs=160.0), rtol=0, atol=1e-12)
    for row in range(2):
        torch.testing.assert_close(stage(u[row], fs=160.0), y[row], rtol=0, atol=0)
    assert stage(u.float(), fs=160.0).dtype == torch.float32


def test_bouc_wen_hysteresis():
    bw = BoucWen(learnable=False)
    stage = PiezoStage(8.0, 0.07, hysteresis=bw)
    u = 5 * torch.sin(torch.linspace(0, 12, 500, dtype=torch.float64))
    h = bouc_wen(u, torch.arange(500, dtype=torch.float64))
    torch.testing.assert_close(stage.hysteresis_output(u), h)
    torch.testing.assert_close(stage(u, fs=160.0), stage.dynamics(h, fs=160.0))


def test_gradients_in_the_input_and_the_stage_parameters():
    dt = 1 / 50.0
    h = _walk((2, 40), seed=2).requires_grad_(True)
    fn = torch.tensor(4.0, dtype=torch.float64, requires_grad=True)
    zeta = torch.tensor(0.08, dtype=torch.float64, requires_grad=True)

    def sampled(h: torch.Tensor, fn: torch.Tensor, zeta: torch.Tensor) -> torch.Tensor:
        A, B = second_order_zoh(fn, zeta, dt)
        y, _ = state_space(h, A, B, A.new_tensor([[1.0, 0.0]]), A.new_zeros(1))
        return y.squeeze(-1)

    def loop(h: torch.Tensor, fn: torch.Tensor, zeta: torch.Tensor) -> torch.Tensor:
        A, B = second_order_zoh(fn, zeta, dt)
        s, out = h.new_zeros(2, 2), []
        for hk in h.unbind(1):
            out.append(s[:, 0])
            s = s @ A.mT + hk[:, None] * B
        return torch.stack(out, 1)

    stage = PiezoStage(4.0, 0.08, learnable=True)
    torch.testing.assert_close(stage.dynamics(h, fs=50.0), loop(h, fn, zeta), rtol=0,
                               atol=1e-12)
    torch.autograd.gradcheck(sampled, (h, fn, zeta))
    torch.autograd.gradcheck(loop, (h, fn, zeta))
    # the module's parameters get the same gradients as central differences
    u = _walk((2, 60), seed=3)
    stage(u, fs=50.0).square().sum().backward()
    eps = 1e-6
    for p in (stage.natural_frequency, stage.damping):
        with torch.no_grad():
            p += eps
            up = float(stage(u, fs=50.0).square().sum())
            p -= 2 * eps
            down = float(stage(u, fs=50.0).square().sum())
            p += eps
        assert float(p.grad) == pytest.approx((up - down) / (2 * eps), rel=1e-6)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"natural_frequency": 0.0}, ValueError, "natural_frequency"),
    ({"natural_frequency": float("nan")}, ValueError, "natural_frequency"),
    ({"natural_frequency": 5.0, "damping": -0.1}, ValueError, "damping"),
    ({"natural_frequency": 5.0, "hysteresis": torch.nn.Linear(1, 1)}, TypeError, "hysteresis"),
    ({"natural_frequency": 5.0, "hysteresis": Backlash([0.1, 0.2])}, TypeError, "one output"),
])
def test_bad_construction(kwargs, error, match):
    with pytest.raises(error, match=match):
        PiezoStage(**kwargs)


def test_bad_calls():
    stage = PiezoStage(5.0)
    u = torch.zeros(2, 10, dtype=torch.float64)
    with pytest.raises(ValueError, match="exactly one of t or fs"):
        stage(u)
    with pytest.raises(ValueError, match="exactly one of t or fs"):
        stage(u, torch.arange(10.0), fs=10.0)
    with pytest.raises(ValueError, match="fs"):
        stage(u, fs=0.0)
    with pytest.raises(ValueError, match="evenly spaced"):
        stage(u, torch.tensor([0.0, 1, 2, 3, 4, 5, 6, 7, 8, 10]))
    with pytest.raises(ValueError, match=r"t must have shape \(time,\) with time = 10"):
        stage(u, torch.arange(9.0))
    with pytest.raises(TypeError, match="floating"):
        stage(torch.zeros(2, 10, dtype=torch.long), fs=10.0)
    with pytest.raises(ValueError, match="shape"):
        stage(torch.zeros(2, 2, 10), fs=10.0)
    with pytest.raises(ValueError, match="scalar"):
        second_order_zoh(torch.ones(2), 0.1, 0.01)
