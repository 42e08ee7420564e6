"""The ``mask`` of the identification functions: the samples a fit uses, the states running
through the others (a held-out block of a cross-validation, a shorter row's padding).

Each fitter is checked three ways: a mask of the samples after the warm-up fits as
``warmup`` does; targets outside the mask do not change the fit; and (for the linear fits)
the fit equals least squares on the masked rows of a design computed by a plain loop over
the whole sequence, the states running through the left-out samples."""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
import pytest
import torch
from _helpers import play_reference, random_walk, sine_loops
from scipy.optimize import nnls

from torchhys import (
    InverseHysteresisNet,
    JilesAtherton,
    fit_drift,
    fit_generalized_pi,
    fit_jiles_atherton,
    fit_preisach,
    fit_stop_pi,
    select_penalty,
)
from torchhys.functional.drift import accumulated_variation, drift_features
from torchhys.identification._nnls import fit_segments, holdout_cuts
from torchhys.identification.fitting import (
    fit_full_batch,
    fit_prandtl_ishlinskii,
    play_width_grid,
    select_pi_ridge,
)
from torchhys.identification.stop_pi import select_stop_pi_ridge
from torchhys.operators.backlash import Backlash

F64 = torch.float64
T = 240
WIDTHS = torch.tensor([0.2, 0.6, 1.2], dtype=F64)


def data() -> tuple[torch.Tensor, torch.Tensor]:
    """Two rows of a random walk and a hysteretic target of them (plays, a bend, noise)."""
    x = torch.stack([random_walk(s, T, quantize=False) for s in (1, 2)]).to(F64)
    x = x / x.abs().max()
    plays = torch.from_numpy(play_reference(x.numpy(), WIDTHS.numpy()))
    g = torch.Generator().manual_seed(3)
    y = 0.8 * x + plays @ torch.tensor([0.5, 0.3, 0.2], dtype=F64) + 0.3 * torch.tanh(2 * x)
    return x, y + 0.01 * torch.randn(x.shape, generator=g, dtype=F64)


def block_mask() -> torch.Tensor:
    """Row 0 without a block in its middle, row 1 without its tail (a shorter recording's
    padding); both without their first 20 samples."""
    m = torch.ones(2, T, dtype=torch.bool)
    m[:, :20] = False
    m[0, 90:150] = False
    m[1, 200:] = False
    return m


def spoiled(y: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``y`` with large errors on the samples outside ``mask``."""
    g = torch.Generator().manual_seed(7)
    return torch.where(mask, y, y + 50.0 * torch.randn(y.shape, generator=g, dtype=F64))


def output(model: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        return model(x)[0]


Fit = Callable[..., torch.nn.Module]
FITTERS: dict[str, Fit] = {
    "pi": lambda x, y, **kw: fit_prandtl_ishlinskii(x, y, WIDTHS, ridge=1e-6, **kw),
    "pi_nonneg": lambda x, y, **kw: fit_prandtl_ishlinskii(x, y, WIDTHS, nonnegative=True,
                                                           **kw),
    "stop_pi": lambda x, y, **kw: fit_stop_pi(x, y, play_width_grid(x, 6, power=2.0),
                                              segments=3, ridge=1e-8, **kw),
    "preisach": lambda x, y, **kw: fit_preisach(x, y, n=8, smoothness=1e-4, **kw),
    "drift": lambda x, y, **kw: fit_drift(x, y, [0.5, 2.0, 8.0], **kw),
    "generalized_pi": lambda x, y, **kw: fit_generalized_pi(x, y, WIDTHS, units=2,
                                                            lbfgs_epochs=40, **kw),
}


@pytest.mark.parametrize("name", list(FITTERS))
def test_a_mask_of_the_samples_after_the_warm_up_fits_as_the_warm_up(name):
    x, y = data()
    mask = torch.ones_like(x, dtype=torch.bool)
    mask[:, :30] = False
    by_warmup = FITTERS[name](x, y, warmup=30)
    by_mask = FITTERS[name](x, y, mask=mask)
    both = FITTERS[name](x, y, warmup=30, mask=torch.ones_like(mask))
    ref = output(by_warmup, x)
    scale = float(ref.abs().max())
    for other in (by_mask, both):
        assert torch.allclose(output(other, x), ref, rtol=0, atol=1e-9 * scale)


@pytest.mark.parametrize("name", list(FITTERS))
def test_targets_outside_the_mask_do_not_enter_the_fit(name):
    x, y = data()
    mask = block_mask()
    clean = output(FITTERS[name](x, y, mask=mask), x)
    other = output(FITTERS[name](x, spoiled(y, mask), mask=mask), x)
    assert torch.allclose(other, clean, rtol=0, atol=1e-9 * float(clean.abs().max()))
    # and they would: the same fit without the mask moves
    moved = output(FITTERS[name](x, spoiled(y, mask), warmup=20), x)
    assert float((moved - clean).abs().max()) > 1e-3 * float(clean.abs().max())


def test_jiles_atherton_leaves_the_samples_outside_its_mask_out():
    true = JilesAtherton(ms=3.0e5, a=20.0, k=15.0, alpha=1e-4, c=0.8)
    b = sine_loops([0.12, 0.36], periods=2, n=64)
    h = output(true, b)
    mask = torch.ones_like(b, dtype=torch.bool)
    mask[0, 70:100] = False
    mask[1, 120:] = False
    kw = dict(warmup=32, starts=2, iterations=6)
    clean = fit_jiles_atherton(b, h, mask=mask, **kw)
    other = fit_jiles_atherton(b, spoiled(h, mask), mask=mask, **kw)
    for p, q in zip(clean.parameters_effective(), other.parameters_effective(), strict=True):
        assert float(p.detach()) == pytest.approx(float(q.detach()), rel=1e-12)
    full = torch.ones_like(mask)
    by_mask = fit_jiles_atherton(b, h, mask=full, **kw)
    by_warmup = fit_jiles_atherton(b, h, **kw)
    for p, q in zip(by_mask.parameters_effective(), by_warmup.parameters_effective(),
                    strict=True):
        assert float(p.detach()) == pytest.approx(float(q.detach()), rel=1e-12)


def test_the_plays_run_through_the_samples_left_out():
    """The masked PI fit is least squares on the masked rows of a plain-loop design over
    the whole rows; fitting the rows cut at the block and joined would not be."""
    x, y = data()
    mask = block_mask()
    fit = fit_prandtl_ishlinskii(x, y, WIDTHS, mask=mask)
    plays = play_reference(x.numpy(), WIDTHS.numpy())
    A = np.concatenate([x.numpy()[..., None], plays], -1)[mask.numpy()]
    w, *_ = np.linalg.lstsq(A, y.numpy()[mask.numpy()], rcond=None)
    assert float(fit.linear_weight) == pytest.approx(w[0], rel=1e-9)
    np.testing.assert_allclose(fit.weights.detach().numpy(), w[1:], rtol=1e-9, atol=1e-12)
    keep = mask[0].clone()
    keep[:20] = True
    joined = fit_prandtl_ishlinskii(x[0, keep], y[0, keep], WIDTHS, warmup=20)
    assert not np.allclose(joined.weights.detach().numpy(),
                           fit_prandtl_ishlinskii(x[:1], y[:1], WIDTHS,
                                                  mask=mask[:1]).weights.detach().numpy(),
                           rtol=1e-6)


def test_the_drift_counts_the_variation_of_the_samples_left_out():
    """The masked drift fit against scipy's NNLS on the masked rows of features of the
    whole rows' accumulated variation."""
    x, y = data()
    y = y + 0.5 * (1 - torch.exp(-accumulated_variation(x)[0] / 4.0))
    mask = block_mask()
    scales = [0.5, 2.0, 8.0]
    fit = fit_drift(x, y, scales, mask=mask, linear=False)
    v = accumulated_variation(x)[0][mask]
    g = drift_features(v, torch.tensor(scales, dtype=F64)).numpy()
    t = y[mask].numpy()
    # weights of one sign (the better of the two), the offset free: two non-negative columns
    A = np.concatenate([g, np.ones((len(t), 1)), -np.ones((len(t), 1))], 1)
    fits = [(nnls(A, s * t), s) for s in (1.0, -1.0)]
    (sol, _), sign = min(fits, key=lambda f: f[0][1])
    np.testing.assert_allclose(fit.weights.detach().numpy(), sign * sol[:3], rtol=1e-6,
                               atol=1e-9)
    assert float(fit.offset) == pytest.approx(sign * (sol[3] - sol[4]), rel=1e-6, abs=1e-9)


def test_the_hold_out_of_a_mask_is_the_last_share_of_each_rows_masked_samples():
    mask = torch.zeros(3, 20, dtype=torch.bool)
    mask[0] = True
    mask[1, :10] = True
    mask[2, 4:8] = True
    mask[2, 12:16] = True
    train, held = fit_segments((3, 20), 2, mask, 0.25)
    assert held[0].nonzero().flatten().tolist() == list(range(16, 20))  # round(4.5) = 4
    assert held[1].nonzero().flatten().tolist() == [8, 9]  # round(2.0)
    assert held[2].nonzero().flatten().tolist() == [14, 15]
    assert not bool((train & held).any())
    expect = mask.clone()
    expect[:, :2] = False
    assert torch.equal(train | held, expect)
    # without a mask: the time-ordered cut of holdout_cuts
    a, split, b = holdout_cuts(20, 2, 0.25)
    train, held = fit_segments((3, 20), 2, None, 0.25)
    assert torch.equal(held, torch.arange(20).expand(3, 20) >= split)
    assert torch.equal(train, (torch.arange(20) >= a).expand(3, 20) & ~held)


def test_the_penalty_selections_leave_the_samples_outside_the_mask_out():
    x, y = data()
    mask = block_mask()
    bad = spoiled(y, mask)
    ridges = [0.0, 1e-4, 1e-2]
    stops = play_width_grid(x, 6, power=2.0)
    for select, extra in ((select_pi_ridge, (WIDTHS, ridges)),
                          (select_stop_pi_ridge, (stops, ridges)),
                          (select_penalty, (ridges,))):
        best, scores = select(x, y, *extra, mask=mask)
        best_bad, scores_bad = select(x, bad, *extra, mask=mask)
        assert best == best_bad
        for p in scores:
            assert scores_bad[p] == pytest.approx(scores[p], rel=1e-9)
        moved = select(x, bad, *extra, warmup=20)[1]
        assert max(abs(moved[p] - scores[p]) for p in scores) > 1e-3


def test_the_full_batch_loss_and_the_normalization_use_the_mask():
    x, y = data()
    mask = block_mask()
    bad = spoiled(y, mask)
    nets = []
    for target in (y, bad):
        torch.manual_seed(0)
        net = InverseHysteresisNet([Backlash(WIDTHS)], 4).double()
        fit_full_batch(net, x, target, adam_epochs=5, lbfgs_epochs=20, mask=mask)
        nets.append(net)
    for (name, a), b in zip(nets[0].state_dict().items(), nets[1].state_dict().values(),
                            strict=True):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12), name
    assert float(nets[0].out_mean) == pytest.approx(float(y[mask].mean()), rel=1e-12)
    assert float(nets[0].out_max) == pytest.approx(float(y[mask].max()), rel=1e-12)


def test_bad_masks_are_named():
    x, y = data()
    with pytest.raises(TypeError, match="mask must be a bool tensor"):
        fit_prandtl_ishlinskii(x, y, WIDTHS, mask=torch.ones_like(x))
    with pytest.raises(ValueError, match=r"mask must have the data's shape \(2, 240\)"):
        fit_stop_pi(x, y, WIDTHS, mask=torch.ones(2, 10, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask .* leaves no sample to fit"):
        fit_drift(x, y, [1.0], mask=torch.zeros_like(x, dtype=torch.bool))
    late = torch.zeros_like(x, dtype=torch.bool)
    late[:, 100:] = True
    with pytest.raises(ValueError, match="leaves no sample to fit"):
        fit_preisach(x, y, warmup=150, mask=late & (torch.arange(T) < 120))
    one = torch.zeros_like(x, dtype=torch.bool)
    one[0, 5] = True
    with pytest.raises(ValueError, match="no training sample before the validation"):
        select_pi_ridge(x, y, WIDTHS, [0.0], mask=one)
    with pytest.raises(ValueError, match="mask"):
        InverseHysteresisNet([Backlash(WIDTHS)], 4).double().fit_normalization(
            x, y, mask=torch.ones(3, dtype=torch.bool))


def test_the_grid_warning_counts_the_masked_samples_only():
    """Samples outside the Preisach grid that the mask leaves out (a held-out block beyond
    the training range) saturate their relays silently; masked ones still warn."""
    x, y = data()
    mask = block_mask()
    lo, hi = float(x[mask].min()), float(x[mask].max())
    assert float(x.min()) < lo or float(x.max()) > hi
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_preisach(x, y, lo=lo, hi=hi, n=6, mask=mask)
    with pytest.warns(RuntimeWarning, match="of the samples of x lie outside"):
        fit_preisach(x, y, lo=lo, hi=hi, n=6)
    inner = 0.5 * (lo + hi)
    with pytest.warns(RuntimeWarning, match="of the masked samples of x lie outside"):
        fit_preisach(x, y, lo=inner, hi=hi, n=6, mask=mask)
