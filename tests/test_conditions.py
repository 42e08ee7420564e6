"""Operating conditions: the scheduled readout (torchhys.conditions.ScheduledReadout) against
float64 numpy least squares, and the compensator's conditions (step(x_t, conditions)):
streaming equal to the model, TorchScript, the clamp and its counter, NaN held, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchhys
from torchhys.conditions import ScheduledReadout, legendre_basis
from torchhys.deploy.streaming import StreamingCompensator

DT = torch.float64


def _record(T: int = 400) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Three rows at conditions 0, 1, 2: a backlash whose width and gain grow with it."""
    t = torch.linspace(0, 12, T, dtype=DT)
    x = (torch.sin(t) * torch.linspace(0.3, 1, T, dtype=DT)).unsqueeze(0).repeat(3, 1)
    v = torch.tensor([0.0, 1.0, 2.0], dtype=DT)
    y = torch.stack([
        torchhys.Backlash(torch.tensor([0.1 + 0.1 * float(vi)], dtype=DT))(x[i:i + 1])[0][0, :, 0]
        * (1 + 0.3 * float(vi)) for i, vi in enumerate(v)])
    return x, v.view(3, 1, 1).expand(3, T, 1).contiguous(), y


def _model(degree: int = 2) -> ScheduledReadout:
    ops = [torchhys.Backlash(torch.linspace(0.0, 0.4, 6, dtype=DT))]
    return ScheduledReadout(ops, 1, degree=degree, ridge=0.0).to(DT)


def test_legendre_basis_is_the_legendre_polynomials() -> None:
    c = torch.linspace(-1, 1, 11, dtype=DT).unsqueeze(-1)
    b = legendre_basis(c, [[0], [1], [2], [3]], 3)
    want = np.polynomial.legendre.legvander(c[:, 0].numpy(), 3)
    np.testing.assert_allclose(b.numpy(), want, rtol=0, atol=1e-14)


def test_fit_is_numpy_least_squares_and_schedules_the_loop() -> None:
    x, c, y = _record()
    m = _model().fit(x, c, y)
    feats = m.features(x).numpy().reshape(-1, 7)
    phi = np.concatenate([np.ones((feats.shape[0], 1)), feats], 1)
    cs = c.numpy().reshape(-1)
    b = np.polynomial.legendre.legvander(2 * (cs - 0) / 2 - 1, 2)
    design = (phi[:, :, None] * b[:, None, :]).reshape(phi.shape[0], -1)
    w, *_ = np.linalg.lstsq(design, y.numpy().reshape(-1), rcond=None)
    pred = m(x, c)
    np.testing.assert_allclose(pred.numpy().reshape(-1), design @ w, rtol=0, atol=1e-9)
    rel = float((pred - y).square().mean().sqrt() / y.std())
    flat = _model(degree=0).fit(x, c, y)
    rel0 = float((flat(x, c) - y).square().mean().sqrt() / y.std())
    assert rel < 0.01 and rel < rel0 / 5  # the condition pays on this plant


def test_the_compensator_streams_the_model_with_its_conditions() -> None:
    x, c, y = _record()
    m = _model().fit(x, c, y)
    comp = StreamingCompensator(m, direction="none")
    u = torch.stack([comp.step(x[:, k], c[:, k]) for k in range(x.shape[1])], 1)
    want = m(x, c).clamp(float(comp.low), float(comp.high))
    assert float((u - want).abs().max()) <= 1e-12
    assert torch.equal(comp(x, c), u)
    scripted = torch.jit.script(comp)
    assert torch.equal(scripted(x, c), u)
    assert torch.equal(comp(x[0], c[0]), u[0])  # one row: (time,) and (time, n)
    assert comp.nonfinite_count().tolist() == [0, 0, 0]


def test_a_condition_out_of_range_is_clamped_and_counted_a_nan_one_held() -> None:
    x, c, y = _record()
    m = _model().fit(x, c, y)
    comp = StreamingCompensator(m, direction="none")
    far = torch.full((3, 1), 10.0, dtype=DT)
    edge = torch.full((3, 1), 2.0 + 0.05 * 2.0, dtype=DT)  # the range widened by 5 %
    u_far = comp.step(x[:, 0], far)
    assert comp.out_of_range_count().tolist() == [1, 1, 1]
    comp.reset()
    assert torch.equal(u_far, comp.step(x[:, 0], edge))
    assert comp.out_of_range_count().tolist() == [0, 0, 0]
    comp.reset()
    first = comp.step(x[:, 0], c[:, 0])
    bad = c[:, 1].clone()
    bad[1] = float("nan")
    second = comp.step(x[:, 1], bad)
    assert comp.nonfinite_count().tolist() == [0, 1, 0]
    assert float(second[1]) == float(first[1])  # held
    wide = StreamingCompensator(m, direction="none", condition_ranges=[(-5.0, 20.0)])
    wide.step(x[:, 0], far)
    assert wide.out_of_range_count().tolist() == [0, 0, 0]


def test_bad_conditions_are_refused_in_one_line() -> None:
    x, c, y = _record()
    m = _model().fit(x, c, y)
    comp = StreamingCompensator(m, direction="none")
    with pytest.raises(ValueError, match=r"step: this compensator takes 1 condition"):
        comp.step(x[:, 0])
    with pytest.raises(ValueError, match=r"conditions must have shape \[3, 1\]"):
        comp.step(x[:, 0], c[:, 0, 0])
    with pytest.raises(ValueError, match=r"forward: conditions must have shape \[3, 400, 1\]"):
        comp(x, c[:, :10])
    pi = torchhys.PrandtlIshlinskiiInverse(torchhys.PrandtlIshlinskii(
        torch.tensor([0.0, 0.2], dtype=DT), torch.tensor([1.0, 0.5], dtype=DT)))
    plain = StreamingCompensator(pi, limits=(-3, 3))
    with pytest.raises(ValueError, match=r"conditions given, but the model takes none"):
        plain.step(x[:, 0], c[:, 0])
    with pytest.raises(ValueError, match=r"condition_ranges must be 1 pair"):
        StreamingCompensator(m, condition_ranges=[(0, 1), (0, 1)])
    with pytest.raises(ValueError, match=r"condition_ranges given, but the model takes no"):
        StreamingCompensator(pi, limits=(-3, 3), condition_ranges=[(0, 1)])


def test_fit_refuses_a_constant_condition_and_bad_shapes() -> None:
    x, c, y = _record()
    with pytest.raises(ValueError, match=r"condition column 0 is constant"):
        _model().fit(x, torch.ones_like(c), y)
    with pytest.raises(ValueError, match=r"conditions must have shape \(3, 400, 1\)"):
        _model().fit(x, c[..., 0], y)
    nan = c.clone()
    nan[0, 5, 0] = float("nan")
    with pytest.raises(ValueError, match=r"conditions must be finite"):
        _model().fit(x, nan, y)
    with pytest.raises(ValueError, match=r"not fitted"):
        StreamingCompensator(_model(), limits=(-1, 1))
    with pytest.raises(TypeError, match=r"operators\[0\] must be a causal"):
        ScheduledReadout([torch.nn.Linear(1, 1)])
