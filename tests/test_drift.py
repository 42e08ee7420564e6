"""The drift of the accumulated input variation: against a plain float64 loop, chunked calls,
the per-sample step (eager, TorchScript, torch.export), gradients, its least-squares fit
against scipy's NNLS, bad input (inside an exported network: tests/test_conformance.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _helpers import run_split, scripted_run, step_loop
from scipy.optimize import nnls

from torchhys import Drift, fit_drift
from torchhys.functional.drift import accumulated_variation, drift
from torchhys.registry import OPERATORS, make_operator

F64 = torch.float64
SCALES = [0.5, 2.0, 8.0]


def signal(rows: int = 3, T: int = 300, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(rows, T, generator=g, dtype=F64).cumsum(1) * 0.1


def reference(x: np.ndarray, scales, weights, offset, prev=None, v0=0.0, floor=0.0) -> tuple:
    """A plain loop in float64: the drift and the final (previous input, variation)."""
    out, v = np.empty(len(x)), v0
    p = x[0] if prev is None else prev
    for t, xt in enumerate(x):
        v += abs(xt - p)
        p = xt
        out[t] = offset + sum(w * (1.0 - math.exp(-max(v, floor) / c))
                              for w, c in zip(weights, scales, strict=True))
    return out, (p, v)


def test_equals_a_plain_loop():
    x = signal()
    w = torch.tensor([0.7, -0.3, 1.5], dtype=F64)
    d, state = drift(x, torch.tensor(SCALES, dtype=F64), w, 0.25)
    assert d.shape == x.shape and state.shape == (3, 2) and state.dtype == F64
    for row in range(3):
        ref, (p, v) = reference(x[row].numpy(), SCALES, w.tolist(), 0.25)
        np.testing.assert_allclose(d[row].numpy(), ref, rtol=0, atol=1e-13)
        assert state[row, 0].item() == p
        assert state[row, 1].item() == pytest.approx(v, rel=1e-14)
    # a given state: the variation before the first sample and the jump to it count
    s0 = torch.tensor([0.4, 3.0], dtype=F64)
    d1, _ = drift(x[0], torch.tensor(SCALES, dtype=F64), w, 0.25, s0)
    ref1, _ = reference(x[0].numpy(), SCALES, w.tolist(), 0.25, prev=0.4, v0=3.0)
    np.testing.assert_allclose(d1.numpy(), ref1, rtol=0, atol=1e-13)
    v, _ = accumulated_variation(torch.tensor([1.0, 3.0, 2.0, 2.0, -1.0], dtype=F64))
    assert v.tolist() == [0.0, 2.0, 3.0, 3.0, 6.0]  # total variation, from the first sample


def test_the_floor_holds_the_drift_below_it():
    x = signal()
    w = [0.7, -0.3, 1.5]
    c64, w64 = torch.tensor(SCALES, dtype=F64), torch.tensor(w, dtype=F64)
    m = Drift(c64, w64, offset=0.25, min_variation=1.5)
    d, state = m(x)
    v, _ = accumulated_variation(x)
    assert bool((v[:, 0] < 1.5).all()) and bool((v[:, -1] > 1.5).all())  # both sides
    for row in range(3):
        ref, (_, vend) = reference(x[row].numpy(), SCALES, w, 0.25, floor=1.5)
        np.testing.assert_allclose(d[row].numpy(), ref, rtol=0, atol=1e-13)
        assert state[row, 1].item() == pytest.approx(vend, rel=1e-14)  # v itself runs on
    held = v < 1.5
    assert torch.equal(d[held], torch.full_like(d[held], float(d[held][0])))
    plain, _ = Drift(c64, w64, offset=0.25)(x)
    assert torch.equal(d[~held], plain[~held])


@pytest.mark.parametrize("splits", [[1] * 40, [7, 100, 193], [299, 1]])
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_chunked_calls_equal_one_call(splits, dtype):
    m = Drift(SCALES, [0.7, -0.3, 1.5], offset=0.25, min_variation=1.0).to(dtype)
    x = signal(T=sum(splits)).to(dtype)
    whole, final = m(x)
    chunked, state = run_split(m, x, splits)
    assert torch.equal(chunked, whole) and torch.equal(state, final)


@pytest.mark.parametrize("floor", [0.0, 1.0])
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_step_eager_and_scripted_equal_the_sequence_path(dtype, floor):
    m = Drift(SCALES, [0.7, -0.3, 1.5], offset=0.25, min_variation=floor).to(dtype)
    x = signal(2, 150, seed=3).to(dtype)
    y, final = m(x)
    step = m.streaming_step(dtype)
    assert step.n_outputs == 1 and [b.kind for b in step.state_spec] == ["float64"] * 2
    for got, state in (step_loop(step, x, step.initial_state(x[:, :1])),
                       scripted_run(step, x)):
        assert got.dtype == dtype and torch.equal(got[..., 0], y)
        assert torch.equal(torch.cat(state, 1), final)


def test_step_through_torch_export_equals_the_sequence_path():
    m = Drift(SCALES, [0.7, -0.3, 1.5], offset=0.25, min_variation=1.0).double()
    x = signal(2, 120, seed=7)
    seq, last = m(x)
    step = m.streaming_step(F64)
    state = step.initial_state(x[:, :1])
    exported = torch.export.export(step, (x[:, :1], state)).module()
    with torch.no_grad():
        got, state = step_loop(exported, x, state)
    assert torch.equal(got[..., 0], seq) and torch.equal(torch.cat(state, 1), last)


def test_gradients():
    x = signal(2, 40, seed=5).requires_grad_(True)
    w = torch.tensor([0.7, -0.3, 1.5], dtype=F64, requires_grad=True)
    off = torch.tensor(0.25, dtype=F64, requires_grad=True)
    c = torch.tensor(SCALES, dtype=F64)
    assert torch.autograd.gradcheck(lambda a, b, o: drift(a, c, b, o)[0], (x, w, off))
    m = Drift(SCALES, learnable=True)
    assert {n for n, _ in m.named_parameters()} == {"weights", "offset"}


def test_registered():
    assert OPERATORS["drift"] is Drift
    assert isinstance(make_operator("drift", scales=SCALES), Drift)


def test_fit_recovers_a_drift_and_equals_scipy_nnls():
    x = signal(2, 400, seed=6)
    true = Drift(SCALES, [-0.4, 0.0, -2.0], offset=1.5).double()
    with torch.no_grad():
        y, _ = true(x)
    fitted = fit_drift(x, y, SCALES)
    torch.testing.assert_close(fitted.weights, true.weights, rtol=0, atol=1e-8)
    assert float(fitted.offset) == pytest.approx(1.5, abs=1e-8)
    # noisy, with a warm-up: the same solution as scipy's NNLS on the design, both signs
    noisy = y + 0.05 * torch.randn(y.shape, generator=torch.Generator().manual_seed(1),
                                   dtype=F64)
    v, _ = accumulated_variation(x)
    g = 1.0 - np.exp(-v[:, 30:].reshape(-1, 1).numpy() / np.array(SCALES))
    t = noisy[:, 30:].reshape(-1).numpy()
    xs = x[:, 30:].reshape(-1, 1).numpy()
    for linear in (False, True):
        fitted = fit_drift(x, noisy, SCALES, warmup=30, linear=linear)
        # the free offset (and slope) as differences of two non-negative columns
        free = np.hstack([np.ones_like(xs)] + ([xs] if linear else []))
        best = None
        for sign in (1.0, -1.0):
            coef, res = nnls(np.hstack([g, free, -free]), sign * t)
            if best is None or res < best[0] - 1e-12:
                best = (res, sign, coef)
        _, sign, coef = best
        np.testing.assert_allclose(fitted.weights.numpy(), sign * coef[:3], rtol=0, atol=1e-7)
        assert float(fitted.offset) == pytest.approx(
            sign * (coef[3] - coef[3 + free.shape[1]]), abs=1e-7)
        # the floor: the least variation of the fitted samples
        assert float(fitted.min_variation) == float(v[:, 30:].min())


def test_a_drift_fitted_after_a_held_out_start_is_not_extrapolated_back():
    """Fitted on a record without its first stretch (a held-out block), the drift holds at
    the variation it starts from: before it, its error stays that of its first fitted
    samples, where the exponentials it fits on their flat tails would run away."""
    x = signal(1, 600, seed=2)
    v, _ = accumulated_variation(x)
    y = Drift([0.5, 8.0], [-3.0, -1.0], offset=1.0).double()(x)[0]
    y = y + 0.02 * torch.randn(y.shape, generator=torch.Generator().manual_seed(3),
                               dtype=F64)
    mask = torch.ones_like(x, dtype=torch.bool)
    mask[:, :150] = False
    fitted = fit_drift(x, y, [0.25, 0.5, 1.0, 2.0, 4.0, 8.0], mask=mask, linear=False)
    assert float(fitted.min_variation) == float(v[0, 150])
    with torch.no_grad():
        d = fitted(x)[0]
        free = Drift(fitted.scales, fitted.weights, offset=float(fitted.offset))(x)[0]
    start = float((d - y)[:, :150].abs().max())
    assert start <= float(y[:, :150].max() - y[:, :150].min()) + 0.1
    assert torch.equal(d[:, 150:], free[:, 150:])


def test_bad_input():
    with pytest.raises(ValueError, match="scales must be finite and positive"):
        Drift([1.0, 0.0])
    with pytest.raises(ValueError, match="scales must be finite and positive"):
        Drift([1.0, float("nan")])
    with pytest.raises(ValueError, match=r"scales must have shape \(K,\)"):
        Drift([])
    with pytest.raises(ValueError, match="weights must have the shape of scales"):
        Drift([1.0, 2.0], [1.0])
    m = Drift(SCALES)
    x = signal(2, 10)
    with pytest.raises(ValueError, match="accumulated variation .* must be >= 0"):
        m(x, torch.tensor([0.0, -1.0], dtype=F64))
    with pytest.raises(ValueError, match="x and y must have the same shape"):
        fit_drift(x, x[:1], SCALES)
    with pytest.raises(ValueError, match="warmup"):
        fit_drift(x, x, SCALES, warmup=10)
    saved = {k: v.clone() for k, v in m.state_dict().items()}
    bad = dict(saved, scales=torch.tensor([1.0, -2.0, 3.0], dtype=F64))
    with pytest.raises(ValueError, match="scales must be finite and > 0"):
        m.load_state_dict(bad)
    assert all(torch.equal(m.state_dict()[k], v) for k, v in saved.items())
    with pytest.raises(ValueError, match="min_variation must be a finite number >= 0"):
        Drift(SCALES, min_variation=-1.0)
    with pytest.raises(ValueError, match="min_variation must be finite and >= 0"):
        m.load_state_dict(dict(saved, min_variation=torch.tensor(float("nan"), dtype=F64)))
    assert all(torch.equal(m.state_dict()[k], v) for k, v in saved.items())
    m.load_state_dict(dict(saved, min_variation=torch.tensor(2.0, dtype=F64)))
    assert float(m.min_variation) == 2.0
    with pytest.raises(RuntimeError, match="min_variation"):  # a state dict without it
        m.load_state_dict({k: v for k, v in saved.items() if k != "min_variation"})
