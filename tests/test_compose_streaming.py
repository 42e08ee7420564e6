"""A Composed through the StreamingCompensator with its recorded ranges: commands equal the
module's output inside the range (float64, 1e-12), and saturation, NaN and inf held and
counted, the input clamp, the direction guard and the layout behave as for the
InverseHysteresisNet (tests/test_streaming_safety.py, tests/test_streaming_direction.py).
TorchScript, float32, reset() and the explicit state: torchhys.testing.check_composed's
checks (tests/test_conformance.py)."""

from __future__ import annotations

import math

import pytest
import torch
from _compose_models import MODELS, make, signal

from torchhys.compose import compose
from torchhys.deploy.streaming import StreamingCompensator

RAW = {"input_margin": None, "direction": "none"}


def _composed(name: str = "backlash_lstm", dtype: torch.dtype = torch.float64):
    model = make(name, dtype=dtype)
    x = signal(dtype=dtype)
    with torch.no_grad():
        y = model(x)
    return compose(model, x=x, y=y), model, x, y


@pytest.mark.parametrize("name", MODELS)
def test_commands_equal_the_module_inside_the_range(name):
    composed, model, x, y = _composed(name)
    comp = StreamingCompensator(composed, direction="none")  # default limits and clamp
    assert comp.clamp_input
    torch.testing.assert_close(comp(x), y, rtol=0, atol=1e-12)
    with torch.no_grad():
        steps = torch.stack([comp.step(xt) for xt in x.unbind(1)], 1)
    torch.testing.assert_close(steps, y, rtol=0, atol=1e-12)


def test_saturation_to_limits():
    composed, _, x, y = _composed()
    lo, hi = float(y.quantile(0.2)), float(y.quantile(0.8))
    u = StreamingCompensator(composed, limits=(lo, hi), **RAW)(x)
    torch.testing.assert_close(u, y.clamp(lo, hi), rtol=0, atol=1e-12)
    assert float(u.min()) >= lo and float(u.max()) <= hi


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_nonfinite_input_holds_command_state_and_counts(bad):
    composed, _, x, _ = _composed("filter_eiho_gru")
    comp = StreamingCompensator(composed, limits=(-1e3, 1e3), **RAW)
    xs = x[:1]
    clean = comp(xs)
    out = []
    with torch.no_grad():
        for t, xt in enumerate(xs.unbind(1)):
            if t in (0, 30, 31):  # bad samples before these clean ones (one before the first)
                out.append(comp.step(torch.tensor([bad], dtype=x.dtype)))
                assert torch.isfinite(out[-1]).all()
            out.append(comp.step(xt))
    assert int(comp.nonfinite_count()) == 3
    assert out[0].item() == 0.0  # the initial command before the first finite sample
    assert torch.equal(out[31], out[30]) and torch.equal(out[33], out[32])  # held
    valid = torch.cat([o for i, o in enumerate(out) if i not in (0, 31, 33)])
    torch.testing.assert_close(valid, clean[0], rtol=0, atol=0)


def test_input_clamp_and_count():
    composed, model, x, _ = _composed()
    comp = StreamingCompensator(composed, input_margin=0.1, direction="none")
    lo, hi = float(comp.in_low), float(comp.in_high)
    wide = x * 3.0
    u = comp(wide)
    with torch.no_grad():
        want = model(wide.clamp(lo, hi)).clamp(float(comp.low), float(comp.high))
    torch.testing.assert_close(u, want, rtol=0, atol=1e-12)
    with torch.no_grad():
        for xt in wide.unbind(1):
            comp.step(xt)
    outside = ((wide < lo) | (wide > hi)).sum(1)
    assert outside.sum() > 0
    assert torch.equal(comp.out_of_range_count(), outside)


def test_direction_guard():
    composed, _, x, _ = _composed()
    assert composed.trend < -0.5  # the recorded direction is decreasing
    free = StreamingCompensator(composed, limits=(-1e3, 1e3), **RAW)(x)
    u = StreamingCompensator(composed, limits=(-1e3, 1e3), input_margin=None)(x)
    du, dx = u.diff(dim=1), x.diff(dim=1)
    assert bool((du * dx <= 0).all())  # the command never moves with the input
    assert bool((du[dx == 0] == 0).all())
    fdu = free.diff(dim=1)
    assert bool((fdu * dx > 0).any())  # the model alone does, at times: the guard acts
    assert not torch.equal(u, free)


def test_layout_names_the_leaves_blocks():
    composed, _, _, _ = _composed()
    rows = StreamingCompensator(composed, **RAW, limits=(-1.0, 1.0)).layout()
    names = [r[2] for r in rows]
    for block, size in (("bl.plays", 1), ("lstm.h", 8), ("lstm.c", 8)):
        row = next(r for r in rows if r[2] == f"step 0 (ComposedStep): {block}")
        assert row[4] == size
    assert names[:3] == ["held command", "held-sample counter", "started"]


def test_no_ranges_no_clamp_no_guard_and_limits_needed():
    composed = compose(make("backlash_lstm"))
    with pytest.raises(ValueError, match=r"records no training output range.*limits="):
        StreamingCompensator(composed)
    comp = StreamingCompensator(composed, limits=(-1.0, 1.0))
    assert not comp.clamp_input and not comp.guard
