"""Shared inputs, references and the backend switch of the linear-dynamics tests."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import pytest
import torch

from torchhys.functional._filter_kernel import (
    filter_kernel_enabled,
    filter_kernel_unavailable_reason,
)

BACKENDS = ["kernel", "scan"]


@contextlib.contextmanager
def use_backend(name: str) -> Iterator[None]:
    """Run with the compiled kernel ("kernel", skipped where it cannot run) or the scan."""
    if name == "kernel" and filter_kernel_unavailable_reason() is not None:
        pytest.skip(f"compiled filter kernel unavailable: {filter_kernel_unavailable_reason()}")
    with filter_kernel_enabled(name == "kernel"):
        yield


def signal(shape: tuple[int, ...], seed: int = 0) -> torch.Tensor:
    """A float64 random walk plus noise along the last axis."""
    g = torch.Generator().manual_seed(seed)
    steps = torch.randn(shape, generator=g, dtype=torch.float64)
    return 0.3 * steps.cumsum(-1) + steps


def stable_denominator(poles: list[complex]) -> np.ndarray:
    """``a`` (len(poles) + 1,) with these poles (conjugates of complex ones added)."""
    full = [p for p in poles] + [np.conj(p) for p in poles if np.imag(p) != 0]
    return np.poly(full).real

