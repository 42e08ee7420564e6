"""A float64 composition exported to a float32 C step: ``to_c`` converts a copy. The
compositions' C99, ONNX, TorchScript and AOTI steps (the three compositions of
tests/_compose_models.py and every recurrent layer kind) are checked by the conformance
suite (tests/test_conformance.py: ``test_composed_conformance``, and the C and ONNX steps
against the TorchScript file over tests/_export_helpers.record, with turning points, ties,
signed zeros, NaN and inf held and counted, excursions 30 % beyond the training range
clamped and counted; float64 within 1e-12 of the command's scale (FLOAT64_RTOL), float32
within FLOAT32_RTOL = 1e-4)."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import torch
from _compose_models import make, signal
from _export_helpers import (
    CC,
    FLOAT32_RTOL,
    NO_CC,
    assert_equal_runs,
    compile_harness,
    record,
    run_c,
    stepped,
)

from torchhys.compose import compose
from torchhys.deploy.c import to_c
from torchhys.deploy.streaming import StreamingCompensator


@pytest.mark.skipif(CC is None, reason=NO_CC)
def test_a_float64_composition_converts_to_a_float32_c_step(tmp_path: Path) -> None:
    """``to_c(model, dtype=float32)`` copies and converts a float64 Composed (as
    ``model.to(float32)``): its C step runs as the eager float32 compensator of that copy."""
    module = make("parallel_gru")
    x = signal()
    with torch.no_grad():
        y = module(x)
    model = compose(module, x=x, y=y)
    samples = record(float(model.in_min), float(model.in_max), n=1000, seed=5)
    to_c(model, tmp_path, dtype=torch.float32)
    got = run_c(compile_harness(tmp_path), samples)
    ref = stepped(StreamingCompensator(copy.deepcopy(model).to(torch.float32)), samples,
                  torch.float32)
    assert_equal_runs(got, ref, FLOAT32_RTOL)
    assert model.in_min.dtype == torch.float64  # the model itself is left as it was
