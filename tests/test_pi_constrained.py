"""Non-negative Prandtl-Ishlinskii identification (against scipy.optimize.nnls on the same
ridge-augmented design; monotone and invertible) and the choice of its ridge on a
time-ordered hold-out."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import nnls

from torchhys import PrandtlIshlinskii
from torchhys.functional import backlash, prandtl_ishlinskii
from torchhys.identification.fitting import (
    LINEAR_FLOOR,
    fit_prandtl_ishlinskii,
    play_width_grid,
    select_pi_ridge,
)
from torchhys.plants import paper_simulation

F64 = torch.float64
WIDTHS = torch.linspace(0.2, 3.0, 8, dtype=F64)
MIXED = torch.tensor([0.8, -0.3, 0.5, 0.0, -0.2, 0.6, 0.1, -0.4], dtype=F64)


def walk(B: int, T: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (0.3 * torch.randn(B, T, generator=g, dtype=F64)).cumsum(1)


def noise(shape: tuple[int, ...], sigma: float, seed: int) -> torch.Tensor:
    return sigma * torch.randn(*shape, dtype=F64, generator=torch.Generator().manual_seed(seed))


def modulated(T: int = 400) -> torch.Tensor:
    """An input that revisits its range (so a hold-out at the end is not an extrapolation)."""
    t = torch.arange(T, dtype=F64)
    x = torch.sin(0.05 * t) * (1 + 0.5 * torch.sin(0.011 * t)) + 0.4 * torch.sin(0.23 * t)
    return x[None]


def scipy_fit(u, y, widths, ridge, warmup):
    """The documented problem through scipy: floor from the static gain, NNLS on the
    augmented design with ``w0 - floor`` as the variable."""
    N = widths.shape[0]
    P = backlash(u, widths)[:, warmup:].reshape(-1, N).numpy()
    us, ys = u[:, warmup:].reshape(-1).numpy(), y[:, warmup:].reshape(-1).numpy()
    n = ys.size
    du = us - us.mean()
    floor = LINEAR_FLOOR * max(du @ (ys - ys.mean()) / (du @ du), 0.0)
    A = np.vstack([np.column_stack([us, P]) / math.sqrt(n),
                   np.hstack([np.zeros((N, 1)), math.sqrt(ridge) * np.eye(N)])])
    b = np.concatenate([(ys - floor * us) / math.sqrt(n), np.zeros(N)])
    w, _ = nnls(A, b)
    w[0] += floor
    return w, floor


@pytest.mark.parametrize("B, ridge, warmup", [(2, 0.0, 0), (2, 1e-3, 20), (1, 0.1, 0),
                                              (3, 1e-5, 5)])
def test_nonnegative_fit_matches_scipy_nnls(B, ridge, warmup):
    u = walk(B, 600, seed=B)
    y = prandtl_ishlinskii(u, WIDTHS, MIXED, linear_weight=0.3) + noise(u.shape, 0.05, 1)
    model = fit_prandtl_ishlinskii(u, y, WIDTHS, ridge=ridge, warmup=warmup, nonnegative=True)
    w, floor = scipy_fit(u, y, WIDTHS, ridge, warmup)
    ours = np.concatenate([[model.linear_weight.item()], model.weights.numpy()])
    np.testing.assert_allclose(ours, w, rtol=0, atol=1e-8)
    assert bool((model.weights >= 0).all()) and model.linear_weight.item() >= floor > 0
    assert int((model.weights == 0).sum()) > 0  # the constraints are active
    free = fit_prandtl_ishlinskii(u, y, WIDTHS, ridge=ridge, warmup=warmup)
    assert float(free.weights.min()) < 0  # ... where the unconstrained fit goes negative


def test_nonnegative_fit_is_monotone_and_invertible():
    u = walk(2, 800, seed=3)
    y = prandtl_ishlinskii(u, WIDTHS, MIXED, linear_weight=0.3) + noise(u.shape, 0.05, 4)
    model = fit_prandtl_ishlinskii(u, y, play_width_grid(u, 20), nonnegative=True)
    ramp = torch.linspace(0.0, float(u.abs().max()), 500, dtype=F64)
    for sign in (1.0, -1.0):  # initial loading curves, up and down
        h, _ = model(sign * ramp)
        assert bool((sign * h.diff() > 0).all())
    x = torch.sin(torch.linspace(0, 30, 900, dtype=F64)) * torch.linspace(0.5, 2.0, 900,
                                                                             dtype=F64)
    h, _ = model(x)  # every branch rises: the output moves with the input
    moving = x.diff() != 0
    assert bool((torch.sign(h.diff()) == torch.sign(x.diff()))[moving].all())
    desired = 0.8 * torch.sin(torch.linspace(0, 20, 700, dtype=F64)) + 0.1
    command, _ = model.inverse()(desired)
    torch.testing.assert_close(model(command)[0], desired, rtol=0, atol=1e-10)


def test_nonnegative_recovers_a_monotone_plant():
    weights = MIXED.abs()
    u = walk(2, 500, seed=5)
    y = prandtl_ishlinskii(u, WIDTHS, weights, linear_weight=0.3)
    model = fit_prandtl_ishlinskii(u, y, WIDTHS, nonnegative=True)
    torch.testing.assert_close(model.weights, weights, rtol=0, atol=1e-9)
    assert abs(model.linear_weight.item() - 0.3) < 1e-9


def test_linear_floor_makes_the_paper_plant_invertible():
    """The paper's plant has no linear term: the fit keeps w0 at the documented floor."""
    t, x, h = paper_simulation(dtype=F64)
    widths = torch.linspace(1 / 6, 15 / 6, 15, dtype=F64)
    model = fit_prandtl_ishlinskii(x, h, widths, nonnegative=True)
    du, dh = x - x.mean(), h - h.mean()
    floor = LINEAR_FLOOR * float((du * dh).sum() / (du * du).sum())
    assert model.linear_weight.item() == pytest.approx(floor, rel=1e-6)
    torch.testing.assert_close(model.weights, torch.ones(15, dtype=F64), rtol=0, atol=0.05)
    assert float((model(x)[0] - h).square().mean().sqrt()) < 2e-5 * float(h.std())
    with pytest.raises(ValueError, match="no inverse"):
        PrandtlIshlinskii(widths, torch.ones(15, dtype=F64)).inverse()
    command, _ = model.inverse()(h)
    torch.testing.assert_close(model(command)[0], h, rtol=0, atol=1e-9)


@pytest.mark.parametrize("nonnegative", [False, True])
def test_select_pi_ridge_scores_the_hold_out(nonnegative):
    u = modulated()
    y = prandtl_ishlinskii(u, WIDTHS[:6], MIXED[:6].abs(), linear_weight=0.3)
    y = y + noise(u.shape, 0.2, 6)
    widths = play_width_grid(u, 25, power=1.0)
    ridges = [1e-4, 1e-2, 1.0] if not nonnegative else [0.0, 1e-4, 1e-2, 1.0]
    best, scores = select_pi_ridge(u, y, widths, ridges, nonnegative=nonnegative,
                                   validation=0.25, warmup=10)
    assert list(scores) == ridges and best == min(scores, key=scores.__getitem__)
    cut = 400 - 100
    for r in ridges:  # a fit on the first 75 % only, scored on the last 25 %
        fit = fit_prandtl_ishlinskii(u[:, :cut], y[:, :cut], widths, ridge=r, warmup=10,
                                     nonnegative=nonnegative)
        rms = (fit(u)[0] - y)[:, cut:].square().mean().sqrt().item()
        assert scores[r] == pytest.approx(rms, rel=1e-7)
    changed = y.clone()
    changed[:, :cut] += noise((1, cut), 0.5, 7)  # the scores see the training part ...
    assert select_pi_ridge(u, changed, widths, ridges, nonnegative=nonnegative,
                           warmup=10)[1] != scores
    changed = y.clone()
    changed[:, cut:] += 1.0  # ... and the hold-out only through the score
    _, shifted = select_pi_ridge(u, changed, widths, ridges, nonnegative=nonnegative,
                                 warmup=10)
    for r in ridges:
        fit = fit_prandtl_ishlinskii(u[:, :cut], y[:, :cut], widths, ridge=r, warmup=10,
                                     nonnegative=nonnegative)
        rms = (fit(u)[0] - changed)[:, cut:].square().mean().sqrt().item()
        assert shifted[r] == pytest.approx(rms, rel=1e-7)


@pytest.mark.parametrize("nonnegative", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_heavy_noise_selects_a_larger_ridge(nonnegative, seed):
    """Known answer: 40 plays on 300 training samples; with little noise the ridge only
    costs (the least ridge wins), with heavy noise the fit overfits without it."""
    u = modulated()
    clean = prandtl_ishlinskii(u, WIDTHS[:6], MIXED[:6].abs(), linear_weight=0.3)
    widths = play_width_grid(u, 40, power=1.0)
    ridges = [0.0, 1e-6, 1e-4, 1e-2, 1.0]
    light, scores_light = select_pi_ridge(u, clean + noise(u.shape, 1e-3, seed), widths, ridges,
                                          nonnegative=nonnegative)
    heavy, scores_heavy = select_pi_ridge(u, clean + noise(u.shape, 1.0, seed), widths, ridges,
                                          nonnegative=nonnegative)
    assert light <= 1e-6 and heavy >= 1e-2
    assert scores_heavy[0.0] > scores_heavy[heavy]  # training error alone would pick 0


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"ridges": []}, ValueError, "ridges must hold at least one value"),
        ({"ridges": [0.1, -1.0]}, ValueError, "ridges must be >= 0"),
        ({"ridges": [math.nan]}, ValueError, "ridges must be finite"),
        ({"ridges": ["a"]}, TypeError, "ridges must be a real number"),
        ({"validation": 1.0}, ValueError, r"validation must be in \(0, 1\)"),
        ({"validation": 0}, ValueError, r"validation must be in \(0, 1\)"),
        ({"warmup": 16}, ValueError, "leaves no training samples"),
        ({"warmup": 20}, ValueError, "warmup must leave samples to fit"),
        ({"y": torch.zeros(5, dtype=F64)}, ValueError, "y must have the shape of u"),
        ({"widths": -WIDTHS}, ValueError, "widths must be non-negative"),
    ],
)
def test_bad_selection_input(kwargs, error, match):
    args = {"u": torch.sin(torch.linspace(0, 12, 20, dtype=F64)), "ridges": [0.0, 1.0],
            "widths": WIDTHS, **kwargs}
    u = args.pop("u")
    y = args.pop("y", u)
    with pytest.raises(error, match=match):
        select_pi_ridge(u, y, args.pop("widths"), args.pop("ridges"), **args)


def test_bad_nonnegative_fit_input():
    u = walk(1, 50, seed=8)
    for bad in (-1.0, math.inf, True, "0"):
        with pytest.raises(ValueError, match="ridge must be a finite number >= 0"):
            fit_prandtl_ishlinskii(u, u, WIDTHS, ridge=bad, nonnegative=True)
    decreasing = fit_prandtl_ishlinskii(u, -u, WIDTHS, nonnegative=True)  # floor 0
    assert decreasing.linear_weight.item() == 0.0 and bool((decreasing.weights == 0).all())
    with pytest.raises(ValueError, match="no inverse"):
        decreasing.inverse()


def test_nonnegative_model_refuses_negative_weights():
    """A ``nonnegative`` model (what ``fit_prandtl_ishlinskii(nonnegative=True)`` returns)
    refuses negative weights at construction and from a state dict, inside a composite too,
    and leaves its weights as they were; an unconstrained model loads them."""
    u = walk(1, 300, 3)
    fitted = fit_prandtl_ishlinskii(u, prandtl_ishlinskii(u, WIDTHS, MIXED.abs()), WIDTHS,
                                    nonnegative=True)
    assert fitted.nonnegative and "nonnegative=True" in repr(fitted)
    bad = {k: v.clone() for k, v in fitted.state_dict().items()}
    bad["weights"][2] = -1e-3
    before = fitted.weights.clone()
    with pytest.raises(ValueError, match=r"^weights must be finite and >= 0 .*-0\.001"):
        fitted.load_state_dict(bad)
    torch.testing.assert_close(fitted.weights, before, rtol=0, atol=0)
    net = torch.nn.Sequential(fitted)
    with pytest.raises(ValueError, match=r"^0\.linear_weight must be finite and >= 0"):
        net.load_state_dict({"0." + k: v for k, v in fitted.state_dict().items()}
                            | {"0.linear_weight": torch.tensor(-0.5, dtype=F64)})
    for key in ("weights", "linear_weight"):  # a partial state dict is checked too
        with pytest.raises(ValueError, match=f"^{key} must be finite and >= 0"):
            fitted.load_state_dict({key: -torch.ones_like(getattr(fitted, key))}, strict=False)
    torch.testing.assert_close(fitted.weights, before, rtol=0, atol=0)
    free = PrandtlIshlinskii(WIDTHS)
    free.load_state_dict(bad)  # unconstrained: negative weights are a model
    assert float(free.weights[2]) == -1e-3
    with pytest.raises(ValueError, match="weights must be finite and >= 0"):
        PrandtlIshlinskii(WIDTHS, MIXED, nonnegative=True)
    with pytest.raises(ValueError, match="linear_weight must be finite and >= 0"):
        PrandtlIshlinskii(WIDTHS, MIXED.abs(), linear_weight=-1.0, nonnegative=True)
    learnable = PrandtlIshlinskii(WIDTHS, MIXED.abs(), nonnegative=True, learnable=True)
    with torch.no_grad():
        learnable.weights[0] = -2.0
    assert float(learnable.project_().weights.min()) == 0.0
    assert not fit_prandtl_ishlinskii(u, u, WIDTHS).nonnegative
