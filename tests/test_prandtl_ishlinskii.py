"""Prandtl-Ishlinskii model and its analytic inverse."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _helpers import play_reference

from torchhys import PrandtlIshlinskii
from torchhys.functional import prandtl_ishlinskii, prandtl_ishlinskii_inverse_parameters


def _model(linear_weight: float = 0.4, seed: int = 0) -> PrandtlIshlinskii:
    g = torch.Generator().manual_seed(seed)
    widths = torch.rand(8, generator=g, dtype=torch.float64) * 3
    weights = torch.rand(8, generator=g, dtype=torch.float64) * 0.8 + 0.1
    return PrandtlIshlinskii(widths, weights, linear_weight=linear_weight)


def _desired(T: int = 3000) -> torch.Tensor:
    t = torch.linspace(0, 20, T, dtype=torch.float64)
    return 3 * torch.sin(t) * torch.exp(-0.1 * t) + 0.5 + 0.3 * torch.sin(7 * t)


def test_matches_loop_reference():
    pi = _model()
    x = torch.randn(2, 300, dtype=torch.float64).cumsum(1)
    h, state = pi(x)
    y = play_reference(x.numpy(), pi.get_widths().numpy())
    ref = 0.4 * x.numpy() + y @ pi.weights.numpy()
    np.testing.assert_allclose(h.numpy(), ref, atol=1e-12)
    np.testing.assert_allclose(state.numpy(), y[:, -1])
    h2 = prandtl_ishlinskii(x, pi.get_widths(), pi.weights, linear_weight=0.4)
    torch.testing.assert_close(h, h2)


def test_paper_plant_definition():
    pi = PrandtlIshlinskii(torch.linspace(1 / 6, 15 / 6, 15))
    assert torch.equal(pi.weights, torch.ones(15)) and pi.linear_weight.item() == 0.0
    h, state = pi(torch.tensor([0.0, 1.0, 3.0]))
    assert state.shape == (15,)
    # H[x] = sum_i clamp(0, x - r_i, x + r_i) at the first samples
    r = torch.linspace(1 / 6, 15 / 6, 15) / 2
    torch.testing.assert_close(h[1], (1.0 - r).clamp_min(0).sum())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_inverse_tracks_desired_output(backend, seed):
    pi = _model(seed=seed)
    inv = pi.inverse()
    yd = _desired()
    u, _ = inv(yd)
    y, _ = pi(u)
    torch.testing.assert_close(y, yd, rtol=0, atol=1e-10)


def test_inverse_with_negative_weights_and_zero_width():
    widths = torch.tensor([0.0, 0.4, 1.0, 1.7, 2.5], dtype=torch.float64)
    weights = torch.tensor([0.3, 1.0, -0.2, 0.5, -0.1], dtype=torch.float64)
    pi = PrandtlIshlinskii(widths, weights, linear_weight=0.2)
    u, _ = pi.inverse()(_desired())
    torch.testing.assert_close(pi(u)[0], _desired(), rtol=0, atol=1e-10)


def test_inverse_from_reachable_state():
    pi = _model()
    prefix = torch.randn(200, dtype=torch.float64).cumsum(0) * 0.3
    h_prefix, z = pi(prefix)
    yd = _desired() + h_prefix[-1]
    u, _ = pi.inverse()(yd, pi.inverse_state(z))
    torch.testing.assert_close(pi(u, z)[0], yd, rtol=0, atol=1e-10)


def test_inverse_state_and_a_linear_inverse_check_their_input():
    pi = _model()
    n = pi.n_operators
    with pytest.raises(ValueError, match=rf"state must have shape \({n},\) or \(batch, {n}\)"):
        pi.inverse_state(torch.zeros(n + 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="state must be finite"):
        pi.inverse_state(torch.full((n,), math.nan, dtype=torch.float64))
    with pytest.raises(TypeError, match="state must have a floating-point dtype"):
        pi.inverse_state(torch.zeros(n, dtype=torch.long))
    linear = PrandtlIshlinskii(torch.tensor([0.0]), torch.tensor([0.5]),
                               linear_weight=0.5).inverse()
    assert linear.widths.numel() == 0
    with pytest.raises(ValueError, match="x must be finite"):
        linear(torch.tensor([0.0, math.nan]))
    with pytest.raises(ValueError, match=r"x must have shape \(time,\)"):
        linear(torch.zeros(2, 3, 4))


def test_inverse_parameters_analytic_two_operators():
    # w0 = 1, one play of half-width 1 with weight 1: slopes 1 then 2;
    # inverse: linear 1, threshold r' = w0 * r = 1, weight -1 / (2 * 1)
    p = prandtl_ishlinskii_inverse_parameters(
        torch.tensor([2.0]), torch.tensor([1.0]), 1.0
    )
    torch.testing.assert_close(p.linear_weight, torch.tensor(1.0))
    torch.testing.assert_close(p.widths, torch.tensor([2.0]))
    torch.testing.assert_close(p.weights, torch.tensor([-0.5]))


def test_no_inverse_for_the_paper_plant():
    pi = PrandtlIshlinskii(torch.linspace(1 / 6, 15 / 6, 15))
    with pytest.raises(ValueError, match="no inverse.*strictly increasing"):
        pi.inverse()
    with pytest.raises(ValueError, match="no inverse"):
        PrandtlIshlinskii(torch.tensor([1.0, 2.0]), torch.tensor([1.0, -2.0]),
                          linear_weight=0.5).inverse()


def test_learnable_parameters_receive_gradients():
    pi = PrandtlIshlinskii(torch.tensor([0.5, 1.0]), learnable=True, linear_weight=0.1)
    x = torch.randn(50).cumsum(0)
    pi(x)[0].pow(2).sum().backward()
    for p in pi.parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all()
