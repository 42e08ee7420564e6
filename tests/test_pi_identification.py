"""Least-squares Prandtl-Ishlinskii identification: reference, analytic inverse, causal use."""

from __future__ import annotations

import pytest
import torch
from _helpers import random_walk, run_chunked

from torchhys import InverseHysteresisNet, PrandtlIshlinskii
from torchhys.functional import prandtl_ishlinskii, prandtl_ishlinskii_inverse_parameters
from torchhys.identification.fitting import (
    fit_full_batch,
    fit_prandtl_ishlinskii,
    play_width_grid,
    select_pi_ridge,
)
from torchhys.plants import paper_plant_widths, paper_simulation
from torchhys.signals import exponential_decay, multisine, to_range


def walk_batch() -> torch.Tensor:
    return torch.stack([random_walk(s, T=400, quantize=False) for s in range(2)])


def test_recovers_known_weights() -> None:
    widths = torch.tensor([0.3, 1.0, 2.0, 4.0], dtype=torch.float64)
    weights = torch.tensor([0.7, -0.2, 1.3, 0.4], dtype=torch.float64)
    u = walk_batch()
    y = prandtl_ishlinskii(u, widths, weights, linear_weight=0.25)
    model = fit_prandtl_ishlinskii(u, y, widths)
    torch.testing.assert_close(model.weights, weights, rtol=1e-9, atol=1e-9)
    assert abs(float(model.linear_weight) - 0.25) < 1e-9
    torch.testing.assert_close(model(u)[0], y, rtol=1e-9, atol=1e-9)


def test_matches_the_analytic_inverse() -> None:
    """From (h, x) of an invertible plant, least squares finds the classical inversion rule."""
    widths = torch.tensor([0.5, 1.0, 1.5, 3.0], dtype=torch.float64)
    weights = torch.tensor([1.0, 0.5, 0.8, 0.3], dtype=torch.float64)
    plant = PrandtlIshlinskii(widths, weights, linear_weight=0.4)
    x = walk_batch()
    h, _ = plant(x)
    p = prandtl_ishlinskii_inverse_parameters(widths, weights, 0.4)
    model = fit_prandtl_ishlinskii(h, x, p.widths)
    torch.testing.assert_close(model.weights, p.weights, rtol=1e-7, atol=1e-9)
    assert abs(float(model.linear_weight) - float(p.linear_weight)) < 1e-8
    torch.testing.assert_close(model(h)[0], x, rtol=1e-8, atol=1e-8)


def test_ridge_shrinks_weights() -> None:
    u = walk_batch()
    widths = play_width_grid(u, 6)
    y = torch.sin(u)
    free = fit_prandtl_ishlinskii(u, y, widths)
    shrunk = fit_prandtl_ishlinskii(u, y, widths, ridge=1.0)
    assert float(shrunk.weights.norm()) < float(free.weights.norm())


def test_width_grid() -> None:
    u = torch.tensor([[-1.0, 3.0], [0.0, 2.0]], dtype=torch.float64)
    w = play_width_grid(u, 4, power=2.0)
    assert w.shape == (4,) and w.dtype == torch.float64
    torch.testing.assert_close(w, 4.0 * torch.tensor([1, 4, 9, 16], dtype=torch.float64) / 16)
    with pytest.raises(ValueError, match="constant"):
        play_width_grid(torch.ones(5), 3)
    with pytest.raises(ValueError, match="n must"):
        play_width_grid(u, 0)
    for bad in (-1.0, float("inf"), True):
        with pytest.raises(ValueError, match=f"power must be a finite number > 0, got {bad!r}"):
            play_width_grid(u, 3, power=bad)


def test_bad_input() -> None:
    u = walk_batch()
    widths = torch.tensor([0.5, 1.0], dtype=torch.float64)
    with pytest.raises(ValueError, match="y must have the shape"):
        fit_prandtl_ishlinskii(u, u[:, :-1], widths)
    with pytest.raises(ValueError, match="ridge"):
        fit_prandtl_ishlinskii(u, u, widths, ridge=-1.0)
    with pytest.raises(TypeError, match="nonnegative must be True or False, got str 'no'"):
        fit_prandtl_ishlinskii(u, u, widths, nonnegative="no")
    with pytest.raises(TypeError, match="learnable must be True or False, got int 1"):
        fit_prandtl_ishlinskii(u, u, widths, learnable=1)
    with pytest.raises(TypeError, match="ridges must be a sequence of candidate values"):
        select_pi_ridge(u, u, widths, 0.1)
    with pytest.raises(ValueError, match="non-negative"):
        fit_prandtl_ishlinskii(u, u, -widths)
    with pytest.raises(TypeError, match="floating"):
        fit_prandtl_ishlinskii(u.long(), u, widths)
    for bad in (-1, 1.5, True, None):
        with pytest.raises(ValueError, match=f"warmup must be an int >= 0, got {bad!r}"):
            fit_prandtl_ishlinskii(u, u, widths, warmup=bad)
    with pytest.raises(ValueError, match="warmup=400 of 400 samples"):
        fit_prandtl_ishlinskii(u, u, widths, warmup=400)
    fit_prandtl_ishlinskii(u, u, widths, warmup=399)  # one sample per row left: still a fit


def _decaying_test_signal(t: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    raw = multisine(t, band=(0.2, 3.0), n_tones=8, seed=1)
    xs = to_range(exponential_decay(raw, t, time_constant=float(t[-1]) / 2), x.min(), x.max())
    widths = paper_plant_widths(torch.float64)
    return xs, prandtl_ishlinskii(xs, widths, torch.ones_like(widths))


def test_paper_plant_causal_inverse_generalizes() -> None:
    """Fitted on the paper's signal, the least-squares inverse tracks a new signal."""
    t, x, h = paper_simulation(dtype=torch.float64)
    model = fit_prandtl_ishlinskii(h, x, play_width_grid(h, 30))
    xs, hs = _decaying_test_signal(t, x)
    with torch.no_grad():
        train = float(torch.mean((model(h)[0] - x) ** 2))
        test = float(torch.mean((model(hs)[0] - xs) ** 2))
    assert train < 7e-4  # the set-valued plateaus put a floor near 3.5e-4
    assert test < 1.2e-3


@pytest.mark.parametrize("learnable", [False, True])
@pytest.mark.parametrize("sizes", [[1], [7, 1, 30]])
def test_network_with_pi_operator_streams(learnable: bool, sizes: list[int]) -> None:
    u = walk_batch()[:, :120]
    pi = fit_prandtl_ishlinskii(u, torch.tanh(u), play_width_grid(u, 5), learnable=learnable)
    torch.manual_seed(0)
    net = InverseHysteresisNet([pi], hidden=4).double()
    assert net.hidden.in_features == 2
    net.fit_normalization(u, torch.tanh(u))
    whole, _ = net(u)
    torch.testing.assert_close(run_chunked(net, u, sizes), whole, rtol=1e-12, atol=1e-12)


def test_network_with_pi_operator_is_causal_with_finite_gradients() -> None:
    u = walk_batch()[:, :150].clone().requires_grad_(True)
    pi = fit_prandtl_ishlinskii(u, torch.tanh(u), play_width_grid(u, 5), learnable=True)
    net = InverseHysteresisNet([pi], hidden=4).double()
    y, _ = net(u)
    changed = u.detach().clone()
    changed[:, 100:] += 3.0
    torch.testing.assert_close(net(changed)[0][:, :100], y[:, :100].detach())
    y.sum().backward()
    grads = [u.grad] + [p.grad for p in net.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert float(pi.raw_widths.grad.abs().sum()) > 0


def test_paper_plant_network_on_the_pi_operator_generalizes() -> None:
    """The recommended causal compensator: a network whose operator is the least-squares PI."""
    n_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        t, x, h = paper_simulation(dtype=torch.float64)
        xs, hs = _decaying_test_signal(t, x)
        torch.manual_seed(0)
        net = InverseHysteresisNet([fit_prandtl_ishlinskii(h, x, play_width_grid(h, 30))], 32)
        result = fit_full_batch(net.double(), h, x, adam_epochs=300, lbfgs_epochs=300)
        with torch.no_grad():
            test = float(torch.mean((net(hs)[0] - xs) ** 2))
    finally:
        torch.set_num_threads(n_threads)
    assert result.mse < 7e-4
    assert test < 1.5e-3


def test_a_fit_no_better_than_a_line_warns_how_to_fix_it() -> None:
    """Data far from zero (a PI model has no intercept): one warning naming the fix; the
    same data centred: none."""
    import warnings

    from torchhys.identification.fitting import fit_prandtl_ishlinskii, play_width_grid

    t = torch.linspace(0.0, 20.0, 800, dtype=torch.float64)
    u = 2.0 * torch.sin(t) * (1.0 - 0.04 * t)
    y = -100.0 + 0.8 * u + 0.05 * torch.sin(3.0 * t)
    widths = play_width_grid(u, 6, power=2.0)
    with pytest.warns(UserWarning, match="no better than a straight line with an intercept") as rec:
        fit_prandtl_ishlinskii(u, y, widths, nonnegative=True)
    assert "centre u and y" in str(rec[0].message) and "\n" not in str(rec[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_prandtl_ishlinskii(u - u.mean(), y - y.mean(), widths, nonnegative=True)
