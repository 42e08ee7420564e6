"""Bad input to the operators and the network: clear errors naming the argument."""

from __future__ import annotations

import warnings

import pytest
import torch

from torchhys import EIHO, InverseHysteresisNet, SegmentEIHO, ZhaoTanOperator
from torchhys.functional import NonCausalWarning, eiho, segment_coefficients, zhao_tan

X = torch.linspace(0, 1, 10)


@pytest.mark.parametrize(
    "call, error, match",
    [
        # NaN, 3-D, integer x: tests/test_conformance.py
        (lambda: eiho(torch.tensor([float("inf")])), ValueError, "x must be finite"),
        (lambda: eiho(X, -1.0), ValueError, "a must be positive"),
        (lambda: eiho(X, torch.ones(3)), ValueError, r"a must be a scalar .* \(3,\)"),
        (lambda: eiho(X, torch.tensor(float("nan"))), ValueError, "a must be finite"),
        (lambda: eiho(X, rule="newest"), ValueError, "rule must be one of .*'newest'"),
        (lambda: eiho(X, threshold=-0.1), ValueError, "threshold must be .* -0.1"),
        (lambda: eiho(X, max_depth=2), ValueError, "max_depth must be an int >= 3, got 2"),
        (lambda: zhao_tan(torch.zeros(0)), ValueError, "at least one sample"),
        (lambda: eiho(X, torch.ones(2, 3), per_segment=True), ValueError, "per-segment a"),
        (lambda: EIHO(a=0.0), ValueError, "a must be positive"),
        (lambda: EIHO(a="big"), ValueError, "a must be .*'big'"),
        (lambda: SegmentEIHO(a_formula="square"), ValueError, "a_formula must be .*'square'"),
        (lambda: EIHO(rule="x"), ValueError, "rule must be .*'x'"),
        (lambda: EIHO(threshold=-1.0), ValueError, "threshold must be .*-1.0"),
        (lambda: ZhaoTanOperator(scale=0.0), ValueError, "scale must be a positive number"),
        (lambda: InverseHysteresisNet("no_such_operator"), ValueError,
         "operator: no operator is registered as 'no_such_operator'"),
        (lambda: InverseHysteresisNet(hidden=0), ValueError, "hidden must be .* 0"),
        (lambda: InverseHysteresisNet(activation="swish"), ValueError, "activation .*'swish'"),
    ],
)
def test_errors_name_the_argument(call, error: type, match: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonCausalWarning)
        with pytest.raises(error, match=match):
            call()


def test_per_segment_needs_targets_and_warns() -> None:
    with pytest.warns(NonCausalWarning, match="not causal"):
        op = SegmentEIHO()
    with pytest.raises(ValueError, match="needs target= .* or segment_a="):
        op(X)
    with pytest.warns(NonCausalWarning):
        segment_coefficients(X, X)
    with pytest.raises(ValueError, match="y must have the shape of x"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NonCausalWarning)
            segment_coefficients(X, X[:5])
    with pytest.warns(NonCausalWarning):
        net = InverseHysteresisNet("eiho_segment", 4)
    with pytest.raises(ValueError, match="needs target="):
        net(X)


def test_uncalibrated_auto_threshold() -> None:
    op = EIHO(threshold="auto")
    with pytest.raises(ValueError, match="calibrate_threshold"):
        op(X)
    x = torch.sin(torch.linspace(0, 20, 500)) + 0.01 * torch.randn(500)
    op.calibrate_threshold(x)
    assert float(op.threshold) > 0
    op(x)


def test_normalization_needs_enough_data() -> None:
    net = InverseHysteresisNet("eiho", 4)
    with pytest.raises(ValueError, match="x must hold at least 2 samples"):
        net.fit_normalization(torch.ones(1), torch.ones(1))
    with pytest.raises(ValueError, match="y is constant"):
        net.fit_normalization(X, torch.ones(10))
    with pytest.raises(ValueError, match="y must have the shape of x"):
        net.fit_normalization(X, X[:4])
    with pytest.raises(ValueError, match="y must be finite"):
        net.fit_normalization(X, X * float("nan"))
    with pytest.raises(ValueError, match="state must hold 1 states"):
        net(X, [None, None])
