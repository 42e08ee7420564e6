"""Shared test fixtures (shared helpers and references are in _helpers.py)."""

from __future__ import annotations

import pytest

from torchhys.functional._kernel import kernel_enabled, kernel_unavailable_reason


@pytest.fixture(params=["kernel", "scan"])
def backend(request):
    """Run a test with the compiled kernel and with the pure-torch scan.

    The "kernel" case is skipped, with the reason, where the kernel cannot run (no C
    compiler, a failed build, ``TORCHHYS_DISABLE_KERNEL``): it would test the scan twice.
    """
    if request.param == "kernel":
        reason = kernel_unavailable_reason()
        if reason is not None:
            pytest.skip(f"compiled play kernel unavailable: {reason}")
    with kernel_enabled(request.param == "kernel"):
        yield request.param
