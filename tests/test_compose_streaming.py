"""A Composed through the StreamingCompensator and TorchScript: commands equal the module's
output inside the range (float64, 1e-12), and saturation, NaN held and counted, the input
clamp, the direction guard, reset() and the explicit state behave as for the
InverseHysteresisNet (tests/test_streaming_safety.py, tests/test_streaming_direction.py)."""

from __future__ import annotations

import math

import pytest
import torch
from _compose_models import MODELS, make, signal

from torchhys.compose import compose
from torchhys.deploy.export import to_torchscript
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


@pytest.mark.parametrize("name", MODELS)
def test_float32_commands_within_a_bound_of_float64(name):
    """A float32 model's compensator against the float64 module: within 1e-4 of the
    command's scale (docs/composing.md)."""
    model = make(name)
    x = signal(time=400)
    with torch.no_grad():
        y = model(x)
    c32 = compose(make(name, dtype=torch.float32), x=x.float(), y=y.float())
    u32 = StreamingCompensator(c32, **RAW)(x.float())
    assert u32.dtype == torch.float32
    assert float((u32.double() - y).abs().max()) < 1e-4 * float(y.abs().max())


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


def test_reset_and_explicit_state_save_and_restore():
    composed, _, x, y = _composed("parallel_gru")
    comp = StreamingCompensator(composed, **RAW, limits=(-1e3, 1e3))
    with torch.no_grad():
        first = torch.stack([comp.step(xt) for xt in x[:, :40].unbind(1)], 1)
        saved = [t.clone() for t in comp.state]
        rest = torch.stack([comp.step(xt) for xt in x[:, 40:].unbind(1)], 1)
        comp.state = saved
        again = torch.stack([comp.step(xt) for xt in x[:, 40:].unbind(1)], 1)
        comp.reset()
        fresh = torch.stack([comp.step(xt) for xt in x[:, :40].unbind(1)], 1)
        # explicit state, continued across two calls
        state = comp.initial_state(x.shape[0])
        explicit = []
        for xt in x.unbind(1):
            u, state = comp.step_explicit(xt, state)
            explicit.append(u)
    torch.testing.assert_close(rest, again, rtol=0, atol=0)
    torch.testing.assert_close(fresh, first, rtol=0, atol=0)
    torch.testing.assert_close(torch.cat([first, rest], 1), y, rtol=0, atol=1e-12)
    torch.testing.assert_close(torch.stack(explicit, 1), y, rtol=0, atol=1e-12)


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


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
@pytest.mark.parametrize("name", MODELS)
def test_torchscript_equals_eager(name, tmp_path):
    composed, _, x, y = _composed(name)
    scripted = to_torchscript(composed, tmp_path / "model.pt", direction="none")
    loaded = torch.jit.load(str(tmp_path / "model.pt"))
    eager = StreamingCompensator(composed, direction="none")
    torch.testing.assert_close(loaded(x), y, rtol=0, atol=1e-12)
    torch.testing.assert_close(scripted(x), eager(x), rtol=0, atol=1e-12)
    steps = torch.stack([loaded.step(xt) for xt in x.unbind(1)], 1)
    torch.testing.assert_close(steps, y, rtol=0, atol=1e-12)
    xn = x.clone()
    xn[:, 7] = math.nan
    torch.testing.assert_close(loaded(xn), eager(xn), rtol=0, atol=1e-12)
