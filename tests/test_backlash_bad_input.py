"""Clear errors naming the argument for bad input."""

from __future__ import annotations

import math

import pytest
import torch

from torchhys import Backlash, BacklashCell, PrandtlIshlinskii
from torchhys.functional import backlash
from torchhys.plants import paper_simulation

W = torch.tensor([0.5, 1.0])


@pytest.mark.parametrize(
    "x, widths, y0, err, match",
    [
        # NaN, 3-D, integer x: tests/test_conformance.py
        (torch.tensor([0.0, float("inf")]), W, None, ValueError, "x must be finite"),
        (torch.zeros(()), W, None, ValueError, "x must have shape"),
        (torch.zeros(2, 0), W, None, ValueError, "at least one sample"),
        ([0.0, 1.0], W, None, TypeError, "x must be a torch.Tensor"),
        (torch.zeros(5), torch.tensor([0.5, -1.0]), None, ValueError, "widths must be non-neg"),
        (torch.zeros(5), torch.tensor([[0.5]]), None, ValueError, r"widths must have shape"),
        (torch.zeros(5), torch.tensor([1, 2]), None, TypeError, "widths must have a floating"),
        (torch.zeros(5), torch.tensor([math.nan]), None, ValueError, "widths must be finite"),
        (torch.zeros(5), torch.empty(0), None, ValueError, "at least one width"),
        (torch.zeros(2, 5), W, torch.zeros(3, 2), ValueError, r"state must have shape"),
        (torch.zeros(2, 5), W, torch.zeros(3), ValueError, r"state must have shape"),
        (torch.zeros(5), W, torch.tensor([0.0, math.nan]), ValueError, "state must be finite"),
        (torch.zeros(5), W, torch.tensor([0, 1]), TypeError, "state must have a floating"),
    ],
)
def test_functional_errors(x, widths, y0, err, match):
    with pytest.raises(err, match=match):
        backlash(x, widths, state=y0)


def test_module_errors():
    with pytest.raises(ValueError, match="widths must be non-negative"):
        Backlash(torch.tensor([-0.1]))
    cell = BacklashCell(W)
    with pytest.raises(ValueError, match=r"x_t must have shape \(batch,\)"):
        cell(torch.zeros(2, 3))
    with pytest.raises(ValueError, match=r"state must have shape \(batch, N\) = \(2, 2\)"):
        cell(torch.zeros(2), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="x_t must be finite"):
        cell(torch.tensor([math.inf]))
    with pytest.raises(ValueError, match=r"weights must have shape \(2,\)"):
        PrandtlIshlinskii(W, torch.ones(3))
    with pytest.raises(ValueError, match="linear_weight must be finite"):
        PrandtlIshlinskii(W, linear_weight=math.nan)


def test_bad_input_does_not_corrupt_state():
    seq = Backlash(W)
    x = torch.randn(2, 30).cumsum(1)
    _, state = seq(x)
    before = state.clone()
    with pytest.raises(ValueError):
        seq(torch.full((2, 5), math.nan), state)
    torch.testing.assert_close(state, before, rtol=0, atol=0)


@pytest.mark.parametrize("kwargs", [{"dt": 0.0}, {"dt": -1.0}, {"t_end": 0.0}, {"dt": math.nan}])
def test_simulation_arguments(kwargs):
    with pytest.raises(ValueError, match="dt|t_end"):
        paper_simulation(**kwargs)
