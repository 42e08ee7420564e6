"""EIHO and Zhao-Tan operators against the per-sample float64 loop in _branch_reference."""

from __future__ import annotations

import math

import pytest
import torch
from _branch_reference import ref_branch
from _helpers import random_walk

from torchhys.functional import eiho, zhao_tan


def f64(values: list[float]) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("threshold", [0.0, 1.0])
@pytest.mark.parametrize("rule", ["recent", "dominant"])
@pytest.mark.parametrize("depth", [32, 5])
def test_eiho_matches_loop(seed: int, threshold: float, rule: str, depth: int) -> None:
    x = random_walk(seed, quantize=seed % 2 == 0)
    a = torch.tensor([1.3, 0.7], dtype=torch.float64)
    f, _ = eiho(x, a, rule=rule, threshold=threshold, max_depth=depth)
    ref = ref_branch(x.tolist(), a_up=1.3, a_down=0.7, threshold=threshold, rule=rule, depth=depth)
    torch.testing.assert_close(f, f64(ref), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("threshold", [0.0, 1.0])
@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_zhao_tan_matches_loop(seed: int, threshold: float, rule: str) -> None:
    x = random_walk(seed, quantize=seed % 2 == 0)
    f, _ = zhao_tan(x, rule=rule, threshold=threshold, max_depth=6)
    ref = ref_branch(x.tolist(), kind="zhao_tan", threshold=threshold, rule=rule, depth=6)
    torch.testing.assert_close(f, f64(ref), rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
def test_per_segment_matches_loop(rule: str) -> None:
    x = random_walk(5)
    a_seg = torch.rand(1, 80, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    a_seg = a_seg + 0.1
    f, _ = eiho(x, a_seg, rule=rule, threshold=0.5, per_segment=True)
    ref = ref_branch(x.tolist(), a_seg=a_seg[0].tolist(), threshold=0.5, rule=rule)
    torch.testing.assert_close(f, f64(ref), rtol=1e-10, atol=1e-10)


def test_eq2_on_a_hand_example() -> None:
    x = f64([0.0, 1.0, 4.0, 3.0, 0.0, 2.0])
    f, _ = eiho(x, 2.0)
    # up from 0: 2 sqrt(x); turning point 4 (f = 4); down: 4 - 2 sqrt(4 - x);
    # turning point 0 (f = 0); up again: 0 + 2 sqrt(x - 0).
    expected = f64([0, 2, 4, 2, 0, 2 * math.sqrt(2)])
    torch.testing.assert_close(f, expected)


def test_dominant_rule_is_bounded_and_recent_drifts() -> None:
    period = 1000  # samples per period 4 pi of the paper's input
    t = torch.arange(4 * period, dtype=torch.float64) * (4 * math.pi / period)
    x = 4 * torch.sin(0.5 * t) + 2 * torch.sin(3 * t)
    f_dom, _ = eiho(x, 1.0, rule="dominant")
    f_rec, _ = eiho(x, 1.0, rule="recent")
    p2, p3 = slice(period, 2 * period), slice(2 * period, 3 * period)
    torch.testing.assert_close(f_dom[p3], f_dom[p2], atol=1e-9, rtol=0)
    assert (f_rec[p3] - f_rec[p2]).abs().max() > 1e-5  # slow drift: sqrt is not additive


def test_dominant_wipes_out_a_minor_loop() -> None:
    # Major branch 0 -> 10, minor loop 6 -> 9; going below 6 closes it.
    x = f64([0.0, 10.0, 6.0, 9.0, 5.0])
    f, _ = eiho(x, 1.0, rule="dominant")
    # after passing 6 (the minimum that opened the loop 6 -> 9) the branch is the one from 10
    assert math.isclose(float(f[4]), math.sqrt(10.0) - math.sqrt(5.0), rel_tol=1e-12)
    g, _ = eiho(x, 1.0, rule="recent")
    f9 = math.sqrt(10) - 2 + math.sqrt(3)
    assert math.isclose(float(g[4]), f9 - 2.0, rel_tol=1e-12)


def test_threshold_small_excursions_leave_no_memory() -> None:
    x = f64([0.0, 2.0, 1.8, 2.0, 3.0])
    f, _ = eiho(x, 1.0, threshold=0.5)
    assert math.isclose(float(f[4]), math.sqrt(3.0), rel_tol=1e-12)
    assert math.isclose(float(f[2]), math.sqrt(2.0) - math.sqrt(0.2), rel_tol=1e-12)
