"""Preisach identification: NNLS against scipy.optimize.nnls on the same design matrix,
exact recovery, penalty selection on a time-ordered hold-out."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from scipy.optimize import nnls

from torchhys.functional.preisach import relay_states
from torchhys.identification.preisach import fit_preisach, fit_preisach_signs, select_penalty
from torchhys.operators.preisach import Preisach

F64 = torch.float64


def excitation(B: int, T: int, seed: int = 0) -> torch.Tensor:
    """Sines of decaying and growing amplitude with a random walk: every relay switches."""
    g = torch.Generator().manual_seed(seed)
    t = torch.arange(T, dtype=F64)
    env = 0.6 + 0.5 * torch.sin(2 * math.pi * t / T * torch.tensor([[1.0], [1.7]])[:B])
    walk = (0.08 * torch.randn(B, T, generator=g, dtype=F64)).cumsum(1)
    x = env * torch.sin(0.07 * t + 0.3 * torch.sin(walk)) + 0.2 * torch.sin(0.31 * t + walk)
    return 0.9 * x  # within [-1.2, 1.2]


def plant(n: int, seed: int = 1) -> Preisach:
    m = Preisach(-1.2, 1.2, n).double()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        w = torch.rand(m.n_relays, generator=g, dtype=F64)
        m.weights.copy_(torch.where(w < 0.3, torch.zeros_like(w), w))  # some exact zeros
        m.linear.fill_(0.4)
        m.offset.fill_(-0.1)
    return m


def differences(n: int) -> np.ndarray:
    """Finite differences between grid neighbours (alpha or beta one level apart)."""
    index = {(i, j): k for k, (i, j) in enumerate(zip(*np.tril_indices(n), strict=True))}
    rows = []
    for (i, j), k in index.items():
        for nb in ((i + 1, j), (i, j + 1)):
            if nb in index:
                row = np.zeros(len(index))
                row[k], row[index[nb]] = -1.0, 1.0
                rows.append(row)
    return np.array(rows).reshape(-1, len(index))


def scipy_fit(x, y, model, ridge, smoothness, linear, warmup):
    """The same problem through scipy: free columns projected out, NNLS on the rest."""
    R = relay_states(x, model.alpha, model.beta, state=model.initial_relays)[:, warmup:]
    K = R.shape[-1]
    xs, ys = x[:, warmup:].reshape(-1).numpy(), y[:, warmup:].reshape(-1).numpy()
    N = ys.size
    free = np.column_stack([xs, np.ones(N)] if linear else [np.ones(N)])
    D = differences(model.n)
    A = np.vstack([np.hstack([R.reshape(-1, K).numpy(), free]) / math.sqrt(N),
                   np.hstack([math.sqrt(ridge) * np.eye(K), np.zeros((K, free.shape[1]))]),
                   np.hstack([math.sqrt(smoothness) * D, np.zeros((len(D), free.shape[1]))])])
    b = np.concatenate([ys / math.sqrt(N), np.zeros(K + len(D))])
    Q, _ = np.linalg.qr(A[:, K:])
    w, _ = nnls(A[:, :K] - Q @ (Q.T @ A[:, :K]), b - Q @ (Q.T @ b), maxiter=50 * K)
    coef = np.linalg.lstsq(A[:, K:], b - A[:, :K] @ w, rcond=None)[0]
    return w, coef


@pytest.mark.parametrize(
    "B, n, ridge, smoothness, linear, warmup",
    [
        (1, 6, 0.0, 0.0, True, 0),
        (2, 7, 0.0, 0.0, False, 40),
        (1, 8, 1e-3, 0.0, True, 0),
        (2, 8, 0.0, 1e-2, True, 10),
        (1, 9, 1e-4, 1e-3, False, 0),
    ],
)
def test_fit_matches_scipy_nnls(B, n, ridge, smoothness, linear, warmup):
    x = excitation(B, 1500)
    with torch.no_grad():
        y = plant(n, seed=n)(x)[0] + 0.05 * torch.randn(B, 1500, dtype=F64,
                                                       generator=torch.Generator().manual_seed(2))
    fit = fit_preisach(x, y, lo=-1.2, hi=1.2, n=n, ridge=ridge, smoothness=smoothness,
                       linear=linear, warmup=warmup)
    w, coef = scipy_fit(x, y, fit, ridge, smoothness, linear, warmup)
    assert fit.weights.dtype == F64 and bool((fit.weights >= 0).all())
    np.testing.assert_allclose(fit.weights.detach().numpy(), w, rtol=0, atol=1e-8)
    np.testing.assert_allclose(fit.offset.item(), coef[-1], rtol=0, atol=1e-8)
    if linear:
        np.testing.assert_allclose(fit.linear.item(), coef[0], rtol=0, atol=1e-8)
    else:
        assert fit.linear.item() == 0.0 and "linear" not in dict(fit.named_parameters())
    if smoothness == 0.0:
        assert int((fit.weights == 0).sum()) > 0  # the constraints are active somewhere


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_noise_free_data_is_recovered(dtype):
    x = excitation(2, 2000, seed=3)
    true = plant(7, seed=4)
    with torch.no_grad():
        y = true(x)[0]
    fit = fit_preisach(x.to(dtype), y.to(dtype), lo=-1.2, hi=1.2, n=7)
    assert fit.weights.dtype == dtype
    tol = 1e-9 if dtype == torch.float64 else 1e-4
    torch.testing.assert_close(fit.weights.detach().to(F64), true.weights.detach(),
                               rtol=0, atol=tol * 10)
    with torch.no_grad():
        torch.testing.assert_close(fit(x.to(dtype))[0].to(F64), y, rtol=0, atol=tol)


def test_select_penalty_scores_the_hold_out():
    x = excitation(1, 1600, seed=5)
    with torch.no_grad():
        y = plant(8, seed=6)(x)[0] + 0.2 * torch.randn(1, 1600, dtype=F64,
                                                       generator=torch.Generator().manual_seed(7))
    penalties = [0.0, 1e-4, 1e-2, 1.0]
    best, scores = select_penalty(x, y, penalties, kind="smoothness", validation=0.25,
                                  lo=-1.2, hi=1.2, n=8, warmup=20)
    assert list(scores) == penalties and best == min(scores, key=scores.__getitem__)
    cut = 1600 - 400
    for p in penalties:
        fit = fit_preisach(x[:, :cut], y[:, :cut], lo=-1.2, hi=1.2, n=8, smoothness=p,
                           warmup=20)
        with torch.no_grad():
            rms = (fit(x)[0] - y)[:, cut:].square().mean().sqrt().item()
        assert scores[p] == pytest.approx(rms, rel=1e-9)
    assert scores[1.0] > scores[best]  # an excessive penalty loses on the hold-out
    best_r, scores_r = select_penalty(x, y, [0.0, 10.0], kind="ridge", lo=-1.2, hi=1.2, n=8)
    assert best_r == 0.0 and scores_r[10.0] > scores_r[0.0]


def test_fit_default_range_and_deployment():
    x = excitation(1, 800, seed=8)
    with torch.no_grad():
        y = plant(5)(x)[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the range of x: no sample outside, no warning
        fit = fit_preisach(x, y, n=5)
    assert fit.lo == float(x.min()) and fit.hi == float(x.max())
    step = fit.streaming_step(F64)
    with torch.no_grad():
        torch.testing.assert_close(step.run(x)[..., 0], fit(x)[0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("penalties", [[0.0, 1e-4, 1e-2], 1e-3])
def test_fit_signs_equals_select_then_fit(penalties):
    """One pass of the relays for both signs of y and for the penalty's choice gives what
    select_penalty then fit_preisach give for each sign, up to rounding."""
    x = excitation(2, 400)
    with torch.no_grad():
        y = plant(6)(x)[0] + 0.01 * torch.randn(x.shape, generator=torch.Generator()
                                                 .manual_seed(3), dtype=F64)
    mask = torch.ones_like(x, dtype=torch.bool)
    mask[:, 150:200] = False
    kw = dict(lo=-1.2, hi=1.2, n=6, mask=mask, validation=0.25)
    fits = fit_preisach_signs(x, y, penalties, signs=(1.0, -1.0), **kw)
    for (penalty, m, rmse), sign in zip(fits, (1.0, -1.0), strict=True):
        if isinstance(penalties, list):
            best, _ = select_penalty(x, sign * y, penalties, **kw)
        else:
            best = penalties
        assert penalty == best
        kw_fit = {k: v for k, v in kw.items() if k != "validation"}
        ref = fit_preisach(x, sign * y, smoothness=best, **kw_fit)
        for a, b in zip(m.parameters(), ref.parameters(), strict=True):
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)
        with torch.no_grad():
            out = m(x)[0]
        assert math.isclose(rmse, float((out - sign * y)[mask].square().mean().sqrt()),
                            rel_tol=1e-9)
