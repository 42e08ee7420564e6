"""fit_stop_pi_signs: one formation of the stops' design for both signs of the target and
the ridge's choice, against select_stop_pi_ridge and fit_stop_pi called for each sign."""

from __future__ import annotations

import math

import pytest
import torch

from torchhys.identification.fitting import play_width_grid
from torchhys.identification.stop_pi import (
    fit_stop_pi,
    fit_stop_pi_signs,
    select_stop_pi_ridge,
)

F64 = torch.float64


@pytest.mark.parametrize("ridges", [[0.0, 1e-4, 1e-2], 1e-3])
@pytest.mark.parametrize("nonnegative", [True, False])
def test_fit_signs_equals_select_then_fit(ridges, nonnegative):
    g = torch.Generator().manual_seed(4)
    t = torch.arange(700, dtype=F64)
    x = torch.stack([torch.sin(0.05 * t) * (1 + 0.3 * torch.sin(0.011 * t)),
                     0.8 * torch.sin(0.07 * t + 1.0)])
    x = x + 0.02 * torch.randn(x.shape, generator=g, dtype=F64)
    y = torch.tanh(1.5 * x) + 0.3 * torch.roll(x, 5, 1) + 0.01 * torch.randn(
        x.shape, generator=g, dtype=F64)
    mask = torch.ones_like(x, dtype=torch.bool)
    mask[:, :30] = False
    mask[0, 300:380] = False
    thresholds = play_width_grid(x[mask], 8, power=2.0)
    fits = fit_stop_pi_signs(x, y, thresholds, ridges, signs=(1.0, -1.0), segments=3,
                             nonnegative=nonnegative, validation=0.25, mask=mask)
    for (ridge, m, rmse), sign in zip(fits, (1.0, -1.0), strict=True):
        if isinstance(ridges, list):
            best, _ = select_stop_pi_ridge(x, sign * y, thresholds, ridges, segments=3,
                                           nonnegative=nonnegative, validation=0.25,
                                           mask=mask)
        else:
            best = ridges
        assert ridge == best
        ref = fit_stop_pi(x, sign * y, thresholds, segments=3, ridge=best,
                          nonnegative=nonnegative, mask=mask)
        for a, b in zip(m.parameters(), ref.parameters(), strict=True):
            torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)
        for a, b in zip(m.buffers(), ref.buffers(), strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
        with torch.no_grad():
            out = m(x)[0]
        assert math.isclose(rmse, float((out - sign * y)[mask].square().mean().sqrt()),
                            rel_tol=1e-9)
