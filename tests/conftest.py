"""Shared test fixtures and independent reference implementations."""

from __future__ import annotations

import numpy as np
import pytest

from torchhys.functional._kernel import kernel_enabled


def play_reference(x: np.ndarray, widths: np.ndarray, y0: np.ndarray | None = None) -> np.ndarray:
    """Plain float64 loop of the play operator: x (B, T), widths (N,) -> (B, T, N)."""
    x = np.asarray(x, dtype=np.float64)
    widths = np.asarray(widths, dtype=np.float64)
    B, T = x.shape
    N = widths.shape[0]
    state = np.zeros((B, N)) if y0 is None else np.broadcast_to(y0, (B, N)).astype(np.float64)
    y = np.empty((B, T, N))
    for b in range(B):
        s = state[b].copy()
        for t in range(T):
            for n in range(N):
                r = widths[n] / 2.0
                s[n] = min(x[b, t] + r, max(x[b, t] - r, s[n]))
            y[b, t] = s
    return y


@pytest.fixture(params=["kernel", "scan"])
def backend(request):
    """Run a test with the compiled kernel and with the pure-torch scan."""
    with kernel_enabled(request.param == "kernel"):
        yield request.param
