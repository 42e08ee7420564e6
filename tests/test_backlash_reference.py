"""Play operators against a plain float64 loop."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from _helpers import play_reference

from torchhys.functional import backlash
from torchhys.functional._kernel import kernel_enabled, kernel_unavailable_reason


def _awkward_input(rng: np.random.Generator, B: int, T: int) -> np.ndarray:
    """Random walk with flat stretches, repeated samples and exact ties."""
    x = np.cumsum(rng.normal(size=(B, T)), axis=1)
    x = np.round(x * 4) / 4  # a coarse grid makes ties with the half-widths likely
    flat = rng.random((B, T)) < 0.2
    for b in range(B):
        for t in range(1, T):
            if flat[b, t]:
                x[b, t] = x[b, t - 1]
    return x


@pytest.mark.parametrize("T", [1, 2, 7, 64, 65, 333, 1500])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_float64_loop(backend, T, dtype):
    rng = np.random.default_rng(T)
    B = 3
    x = _awkward_input(rng, B, T)
    widths = np.array([0.0, 0.5, 0.5, 1.0, 2.5, 0.25])  # zero, repeated, tie-prone widths
    y0 = np.round(rng.normal(size=(B, widths.size)) * 4) / 4
    ref = play_reference(x, widths, y0)
    y = backlash(
        torch.tensor(x, dtype=dtype), torch.tensor(widths, dtype=dtype),
        state=torch.tensor(y0, dtype=dtype),
    )
    assert y.shape == (B, T, widths.size)
    assert y.dtype == dtype
    # the grid values are exact in float32 too, so agreement is exact
    np.testing.assert_array_equal(y.double().numpy(), ref)


def test_random_float_inputs(backend):
    rng = np.random.default_rng(0)
    x = rng.normal(size=(4, 777)).cumsum(1)
    widths = rng.uniform(0, 3, size=9)
    y0 = rng.normal(size=9)
    ref = play_reference(x, widths, y0)
    y = backlash(torch.tensor(x), torch.tensor(widths), state=torch.tensor(y0))
    np.testing.assert_allclose(y.numpy(), ref, rtol=0, atol=1e-12)


def test_unbatched_shapes_and_default_state(backend):
    x = torch.linspace(0, 3, 50, dtype=torch.float64)
    widths = torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64)
    y = backlash(x, widths)
    assert y.shape == (50, 3)
    ref = play_reference(x.numpy()[None], widths.numpy())[0]
    np.testing.assert_allclose(y.numpy(), ref)
    # a zero width is the identity; the operator output lags x by the half-width on loading
    np.testing.assert_allclose(y[:, 0].numpy(), x.numpy())
    assert torch.allclose(y[-1, 2], x[-1] - 1.0)


def test_batch_consistency(backend):
    torch.manual_seed(1)
    x = torch.randn(5, 200, dtype=torch.float64).cumsum(1)
    widths = torch.rand(4, dtype=torch.float64) * 2
    y0 = torch.randn(5, 4, dtype=torch.float64)
    whole = backlash(x, widths, state=y0)
    for b in range(5):
        single = backlash(x[b], widths, state=y0[b])
        torch.testing.assert_close(whole[b], single, rtol=0, atol=0)


def test_kernel_and_scan_agree():
    reason = kernel_unavailable_reason()
    if reason is not None:
        pytest.skip(f"compiled play kernel unavailable: {reason}")
    x = torch.randn(2, 3001).cumsum(1)
    widths = torch.rand(6) * 3
    with kernel_enabled(True):
        a = backlash(x, widths)
    with kernel_enabled(False):
        b = backlash(x, widths)
    torch.testing.assert_close(a, b, rtol=0, atol=0)
