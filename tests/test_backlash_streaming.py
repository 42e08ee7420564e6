"""Cell loop == sequence module; unbatched shapes; learnable widths (chunked calls of Backlash
and PrandtlIshlinskii: tests/test_conformance.py)."""

from __future__ import annotations

import pytest
import torch

from torchhys import Backlash, BacklashCell

WIDTHS = torch.tensor([0.0, 0.3, 1.0, 2.2], dtype=torch.float64)


def _signal(B: int = 3, T: int = 257) -> torch.Tensor:
    torch.manual_seed(0)
    return torch.randn(B, T, dtype=torch.float64).cumsum(1) * 0.4


@pytest.mark.parametrize("learnable", [False, True])
def test_cell_loop_equals_sequence(backend, learnable):
    x = _signal()
    cell = BacklashCell(WIDTHS, learnable=learnable).double()
    seq = Backlash(WIDTHS, learnable=learnable).double()
    state = torch.randn(3, 4, dtype=torch.float64)
    outs, s = [], state
    for x_t in x.unbind(1):
        y_t, s = cell(x_t, s)
        outs.append(y_t)
    y_seq, final = seq(x, state)
    torch.testing.assert_close(torch.stack(outs, 1), y_seq, rtol=0, atol=0)
    torch.testing.assert_close(final, s, rtol=0, atol=0)


def test_learnable_widths_stay_nonnegative_and_train():
    torch.manual_seed(0)
    seq = Backlash(torch.tensor([0.0, 0.5, 1.5]), learnable=True)
    assert torch.allclose(seq.get_widths(), torch.tensor([0.0, 0.5, 1.5]), atol=1e-6)
    x = torch.randn(2, 100).cumsum(1)
    target = Backlash(torch.tensor([0.2, 0.8, 1.0]))(x)[0]
    opt = torch.optim.SGD(seq.parameters(), lr=50.0)
    for _ in range(30):
        opt.zero_grad()
        loss = (seq(x)[0] - target).pow(2).mean()
        loss.backward()
        opt.step()
    assert (seq.get_widths() >= 0).all()
    assert loss.item() < 0.05
