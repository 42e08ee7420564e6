"""Shared test fixtures (shared helpers and references are in _helpers.py)."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import pytest

from torchhys.functional._kernel import kernel_enabled, kernel_unavailable_reason
from torchhys.registry import EXAMPLES, OPERATORS


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


ERFINV_OPERATOR = '''
import torch
from torchhys.operator import HysteresisOperator
from torchhys.registry import register_operator
from torchhys.step import OperatorStep


class ErfinvStep(OperatorStep):
    def __init__(self):
        super().__init__()
        self.n_outputs = 1
        self.state_spec = []

    def forward(self, x, state):
        return torch.erfinv(torch.tanh(x)), state


class ErfinvZone(HysteresisOperator):
    """A memoryless toy whose step uses an operation (erfinv) that neither the C
    generator nor the ONNX exporter translates."""

    def forward(self, x, state=None):
        return torch.erfinv(torch.tanh(x)), None

    def streaming_step(self, dtype):
        return ErfinvStep()


register_operator("erfinv_zone", ErfinvZone)
'''


@pytest.fixture
def erfinv_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """A module in a temporary folder that registers ``erfinv_zone`` (removed afterwards)."""
    folder = tmp_path / "plugin"
    folder.mkdir()
    (folder / "erfinv_plugin.py").write_text(ERFINV_OPERATOR)
    monkeypatch.syspath_prepend(str(folder))
    yield importlib.import_module("erfinv_plugin")
    OPERATORS.pop("erfinv_zone", None)
    EXAMPLES.pop("erfinv_zone", None)
    sys.modules.pop("erfinv_plugin", None)
