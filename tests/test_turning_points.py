"""turning_points: reference loop, noise threshold, flat stretches, batches, bad input."""

from __future__ import annotations

import math

import pytest
import torch
from _branch_reference import ref_turning_points
from _helpers import random_walk

from torchhys.functional import estimate_threshold, turning_points


@pytest.mark.parametrize("seed", range(8))
@pytest.mark.parametrize("threshold", [0.0, 0.5, 1.0, 2.5])
def test_matches_reference_loop(seed: int, threshold: float) -> None:
    x = random_walk(seed, quantize=seed % 2 == 0)
    mask = turning_points(x, threshold=threshold)
    assert mask.dtype == torch.bool and mask.shape == x.shape
    assert mask.tolist() == ref_turning_points(x.tolist(), threshold)


def test_sine_marks_the_extrema() -> None:
    t = torch.arange(2000, dtype=torch.float64) * (20 * math.pi / 2000)
    mask = turning_points(torch.sin(t))
    idx = mask.nonzero().flatten()
    assert len(idx) == 20
    assert torch.allclose(torch.sin(t[idx]).abs(), torch.ones(20, dtype=torch.float64), atol=1e-4)


def noisy_sine(seed: int = 0) -> torch.Tensor:
    t = torch.linspace(0, 10 * 2 * math.pi, 4000, dtype=torch.float64)
    g = torch.Generator().manual_seed(seed)
    return torch.sin(t) + 0.005 * 2.0 * torch.randn(t.shape, generator=g, dtype=torch.float64)


def test_noise_needs_a_threshold() -> None:
    x = noisy_sine()
    assert int(turning_points(x).sum()) > 500  # every wiggle counts without a threshold
    assert int(turning_points(x, threshold=0.1).sum()) == 20
    assert int(turning_points(x, threshold="auto").sum()) == 20


def test_auto_threshold_estimates_noise_level() -> None:
    th = float(estimate_threshold(noisy_sine(1)))
    assert 0.5 * 10 * 0.01 < th < 2 * 10 * 0.01  # factor 10 times sigma = 0.01


def test_flat_stretches_are_not_turning_points() -> None:
    x = torch.tensor([0.0, 0, 0, 1, 1, 1, 2, 2, 2, 2, 1, 1, 0, 0, 1], dtype=torch.float64)
    mask = turning_points(x)
    assert mask.nonzero().flatten().tolist() == [6, 12]  # first sample of each flat extremum
    assert not turning_points(torch.zeros(10)).any()


def test_threshold_is_strict() -> None:
    x = torch.tensor([0.0, 2.0, 1.0, 3.0, 1.0], dtype=torch.float64)
    assert turning_points(x, threshold=1.0).nonzero().flatten().tolist() == [3]
    assert turning_points(x, threshold=0.99).nonzero().flatten().tolist() == [1, 2, 3]


def test_batch_consistency() -> None:
    xs = torch.stack([random_walk(s) for s in range(4)])
    batched = turning_points(xs, threshold=0.5)
    for row, x in zip(batched, xs, strict=True):
        assert torch.equal(row, turning_points(x, threshold=0.5))
    per_row = torch.tensor([0.0, 0.5, 1.0, 2.0], dtype=torch.float64)
    batched = turning_points(xs, threshold=per_row)
    for row, x, th in zip(batched, xs, per_row.tolist(), strict=True):
        assert torch.equal(row, turning_points(x, threshold=th))


def test_single_sample_and_float32() -> None:
    assert turning_points(torch.tensor([1.0])).tolist() == [False]
    x = random_walk(3).float()
    assert turning_points(x, threshold=0.5).tolist() == ref_turning_points(x.tolist(), 0.5)


@pytest.mark.parametrize(
    "x, kwargs, error, match",
    [
        (torch.tensor([0.0, float("nan")]), {}, ValueError, "x must be finite"),
        (torch.tensor([0.0, float("inf")]), {}, ValueError, "x must be finite"),
        (torch.zeros(2, 3, 4), {}, ValueError, r"x must have shape .* got shape \(2, 3, 4\)"),
        (torch.zeros(0), {}, ValueError, "at least one sample"),
        (torch.arange(5), {}, TypeError, "x must have a floating-point dtype"),
        ([0.0, 1.0], {}, TypeError, "x must be a torch.Tensor"),
        (torch.zeros(5), {"threshold": -1.0}, ValueError, "threshold must be .* got -1.0"),
        (torch.zeros(5), {"threshold": "median"}, ValueError, "threshold must be .*'median'"),
        (torch.zeros(5), {"threshold": float("nan")}, ValueError, "threshold"),
        (torch.zeros(2), {"threshold": "auto"}, ValueError, "at least 3 samples"),
    ],
)
def test_bad_input(x: object, kwargs: dict, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        turning_points(x, **kwargs)  # type: ignore[arg-type]


def test_the_prefix_clamp_of_a_symbolic_length_equals_the_eager_loop() -> None:
    """The detector's prefix clamp exported with a dynamic time dimension (its shifted-in
    form, torch.export) equals, bit for bit, the eager loop over slices at lengths below,
    at and above the traced one, ties and 2 included, and a plain loop of clamps."""
    from torchhys.functional.turning_points import _prefix_clamp

    class Clamp(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            return _prefix_clamp(x - 0.3, x + 0.3)

    time = torch.export.Dim("time", min=2, max=1 << 12)
    x = torch.stack([random_walk(3, 24), random_walk(4, 24)])
    program = torch.export.export(Clamp(), (x,), dynamic_shapes={"x": {1: time}}).module()
    for n in (2, 3, 24, 37, 100):
        v = torch.stack([random_walk(n, n), -random_walk(n + 1, n)])  # quantized: ties
        got, ref = program(v), Clamp()(v)
        assert all(torch.equal(a, b) for a, b in zip(got, ref, strict=True)), n
        lo, hi = v - 0.3, v + 0.3  # y -> clamp(y, lo_t, hi_t) composed from the first sample
        a, b = lo[:, 0], hi[:, 0]
        for t in range(1, n):
            a, b = (torch.minimum(torch.maximum(a, lo[:, t]), hi[:, t]),
                    torch.minimum(torch.maximum(b, lo[:, t]), hi[:, t]))
        assert torch.equal(ref[0][:, -1], a) and torch.equal(ref[1][:, -1], b), n
