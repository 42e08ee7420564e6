"""Streaming: chunked calls with the carried state equal one call on the whole sequence."""

from __future__ import annotations

import warnings

import pytest
import torch
from _helpers import batch, run_chunked

from torchhys import EIHO, InverseHysteresisNet, SegmentEIHO, ZhaoTanOperator
from torchhys.functional import NonCausalWarning

A_MODES = [1.5, (1.5, 0.5), "learnable"]


@pytest.mark.parametrize("rule", ["recent", "dominant"])
@pytest.mark.parametrize("a", A_MODES)
@pytest.mark.parametrize("threshold", [0.0, 0.75])
@pytest.mark.parametrize("sizes", [[1], [7, 1, 30]])
def test_eiho_chunked_equals_whole(rule: str, a: object, threshold: float, sizes: list[int]):
    op = EIHO(a=a, rule=rule, threshold=threshold, max_depth=6).double()
    x = batch()
    whole, _ = op(x)
    torch.testing.assert_close(run_chunked(op, x, sizes), whole, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("rule", ["recent", "dominant"])
@pytest.mark.parametrize("a_formula", ["sqrt", "paper"])
def test_per_segment_chunked_equals_whole(rule: str, a_formula: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonCausalWarning)
        op = SegmentEIHO(rule=rule, a_formula=a_formula, threshold=0.5).double()
    x = batch()
    y = torch.sin(x)
    whole, _ = op(x, target=y)
    seg_a = op.segment_coefficients(x, y)
    chunked = run_chunked(op, x, [1, 13], segment_a=seg_a)
    torch.testing.assert_close(chunked, whole, rtol=1e-12, atol=1e-12)


def test_zhao_tan_dominant_chunked_equals_whole() -> None:  # recent: test_conformance.py
    op = ZhaoTanOperator(rule="dominant", threshold=0.5, scale=3.0)
    x = batch()
    whole, _ = op(x)
    torch.testing.assert_close(run_chunked(op, x, [1, 5, 11]), whole, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("operator", ["eiho", "zhao_tan", None])
def test_network_chunked_equals_whole(operator: str | None) -> None:
    torch.manual_seed(0)
    net = InverseHysteresisNet(operator, hidden=8, operator_kwargs={}).double()
    x = batch()
    net.fit_normalization(x, torch.tanh(x))
    whole, _ = net(x)
    torch.testing.assert_close(run_chunked(net, x, [1, 9]), whole, rtol=1e-12, atol=1e-12)


def test_expanded_network_chunked_equals_whole() -> None:
    torch.manual_seed(0)
    ops = [EIHO(a=0.5), EIHO(a=2.0, rule="dominant", threshold=0.3), ZhaoTanOperator()]
    net = InverseHysteresisNet(ops, hidden=8, activation="tanh").double()
    x = batch()
    net.fit_normalization(x, torch.tanh(x))
    whole, _ = net(x)
    torch.testing.assert_close(run_chunked(net, x, [3, 1]), whole, rtol=1e-12, atol=1e-12)
