"""The compensator's input clamp and direction guard (StreamingCompensator, the exports).

A compensator clamps its input to the training input range widened by a margin, counts the
samples it clamped, and never moves its command against the training data's direction.
"""

import math

import pytest
import torch
from _helpers import RAW

from torchhys import InverseHysteresisNet
from torchhys.deploy.export import load_torchscript, metadata, to_torchscript
from torchhys.deploy.ranges import MIN_TREND, default_direction, default_input_range
from torchhys.deploy.streaming import StreamingCompensator


def loop(sign: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A growing loop: x (600,) and a target that rises (sign 1) or falls (-1) with it."""
    t = torch.linspace(0, 12, 600, dtype=torch.float64)
    x = torch.sin(t) * (1 + 0.1 * t)
    return x, sign * (x + 0.2 * torch.cos(t))


def untrained(sign: float = 1.0, hidden: int = 8) -> InverseHysteresisNet:
    """A seeded, untrained EIHO network (not monotone in its input) with its normalization
    and ranges fitted to :func:`loop`."""
    torch.manual_seed(0)
    net = InverseHysteresisNet("eiho", hidden).double()
    net.fit_normalization(*loop(sign))
    return net


def sweep(lo: float, hi: float, scale: float = 100.0) -> torch.Tensor:
    """From 0 up to ``scale`` times the top of the range, down to ``scale`` times the bottom
    and back up: turning points, and 99 ranges beyond the training data on each side."""
    top, bottom = scale * max(abs(hi), abs(lo)), -scale * max(abs(hi), abs(lo))
    f64 = {"dtype": torch.float64}
    return torch.cat([torch.linspace(0, top, 800, **f64), torch.linspace(top, bottom, 1600, **f64),
                      torch.linspace(bottom, top, 1600, **f64)])


def against(u: torch.Tensor, x: torch.Tensor, d: int) -> int:
    """Steps where the command moved against direction ``d`` of the input."""
    du, dx = u.diff(), x.diff()
    return int(((d * du * dx) < 0).sum() + ((dx == 0) & (du != 0)).sum())


def test_fit_normalization_records_the_input_range_and_direction() -> None:
    x, y = loop()
    assert default_input_range(untrained()) == (float(x.min()), float(x.max()))
    assert default_direction(untrained(1.0)) == 1
    assert default_direction(untrained(-1.0)) == -1
    fresh = InverseHysteresisNet("eiho", 3)
    assert default_input_range(fresh) is None and default_direction(fresh) == 0


def test_no_direction_where_the_training_data_have_no_clear_trend() -> None:
    # a friction force against position: +F while the position rises, -F while it falls,
    # uncorrelated with the position (r = 0): no direction to keep, no guard
    t = torch.linspace(0, 12 * math.pi, 1200, dtype=torch.float64)
    x = torch.sin(t)
    y = torch.tanh(20 * torch.cos(t))
    net = InverseHysteresisNet("eiho", 4).double()
    net.fit_normalization(x, y)
    r = float(net.trend)
    assert abs(r - float(torch.corrcoef(torch.stack([x, y]))[0, 1])) < 1e-12
    assert abs(r) < MIN_TREND and default_direction(net) == 0
    assert not StreamingCompensator(net).guard
    assert StreamingCompensator(net, direction="increasing").guard
    # the same record with a clear trend added: a direction
    net.fit_normalization(x, y + 3 * x)
    assert float(net.trend) >= MIN_TREND and default_direction(net) == 1


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_guard_keeps_the_direction_far_beyond_the_training_range(sign: float) -> None:
    net = untrained(sign)
    lo, hi = default_input_range(net)
    x = sweep(lo, hi)
    with torch.no_grad():
        u = StreamingCompensator(net)(x)
        free = StreamingCompensator(net, **RAW)(x)
    d = int(sign)
    assert against(free, x, d) > 100  # the model alone turns the wrong way, often
    assert against(u, x, d) == 0
    low, high = float(net.out_min), float(net.out_max)
    assert bool(((u >= low) & (u <= high)).all())
    # the ramp up ends on the side of the direction: at the top of what it commanded
    top = u[: 800 + 1600 + 1600]
    end = top[-1]
    assert float(end) == pytest.approx(float(top.max() if d > 0 else top.min()), abs=0.0)


def test_guard_and_clamp_change_nothing_inside_the_range_of_a_monotone_model() -> None:
    # an affine readout of x alone with a positive slope: monotone, so guard and clamp are
    # identities on inputs inside the training range
    x, y = loop()
    net = InverseHysteresisNet(None, 1, activation="identity").double()
    net.fit_normalization(x, y)
    with torch.no_grad():
        net.hidden.weight.fill_(1.0)
        net.output.weight.fill_(0.5)
        guarded = StreamingCompensator(net, limits=(-1e6, 1e6))(x)
        free = StreamingCompensator(net, limits=(-1e6, 1e6), **RAW)(x)
    assert torch.equal(guarded, free)


def test_clamp_holds_the_command_beyond_the_widened_range_and_counts() -> None:
    net = untrained()
    lo, hi = default_input_range(net)
    comp = StreamingCompensator(net, input_margin=0.1, direction="none")
    assert float(comp.in_low) == pytest.approx(lo - 0.1 * (hi - lo))
    assert float(comp.in_high) == pytest.approx(hi + 0.1 * (hi - lo))
    edge = float(comp.in_high)
    x = torch.cat([torch.linspace(0, edge, 50, dtype=torch.float64),
                   torch.tensor([edge * 2, 1e300, edge * 10, math.nan, math.inf],
                                dtype=torch.float64)])
    with torch.no_grad():
        u = torch.stack([comp.step(v.reshape(1))[0] for v in x])
    # beyond the bound the model sees the bound: the command stays where it was at the edge
    assert torch.equal(u[50:53], u[49].expand(3))
    assert int(comp.out_of_range_count()) == 3
    assert int(comp.nonfinite_count()) == 2
    comp.reset()
    assert int(comp.out_of_range_count()) == 0
    none = StreamingCompensator(net, input_margin=None)
    assert not none.clamp_input and int(none.out_of_range_count()) == 0


def test_torchscript_keeps_guard_clamp_and_metadata(tmp_path) -> None:
    net = untrained()
    comp = StreamingCompensator(net)
    x = sweep(*default_input_range(net), scale=10.0)
    m = to_torchscript(net, tmp_path / "c.pt")
    with torch.no_grad():
        torch.testing.assert_close(m(x), comp(x), rtol=0, atol=1e-12)
        for v in x[:900]:
            m.step(v.reshape(1))
    assert int(m.out_of_range_count()) == int(((x[:900] < comp.in_low)
                                               | (x[:900] > comp.in_high)).sum())
    meta = load_torchscript(tmp_path / "c.pt").torchhys_metadata
    assert meta == metadata(comp)
    assert float(meta["input_high"]) == float(comp.in_high) and meta["direction"] == "1"


def test_a_state_dict_without_the_ranges_is_refused_naming_them() -> None:
    net = untrained()
    state = {k: v for k, v in net.state_dict().items()
             if k not in ("in_min", "in_max", "trend")}
    with pytest.raises(RuntimeError, match="in_min.*in_max.*trend|Missing key"):
        InverseHysteresisNet("eiho", 8).double().load_state_dict(state)


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"direction": "sideways"}, "direction must be one of"),
    ({"input_margin": -0.1}, "input_margin must be >= 0"),
    ({"input_margin": math.nan}, "input_margin"),
    ({"input_range": (1.0, 0.0)}, "input_range must be finite with low < high"),
    ({"input_range": (0.0,)}, "input_range must be a pair"),
])
def test_bad_options_name_the_argument(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        StreamingCompensator(untrained(), **kwargs)


def test_explicit_direction_and_range_override_the_recorded_ones() -> None:
    net = untrained(1.0)
    comp = StreamingCompensator(net, direction="decreasing", input_range=(-1.0, 1.0),
                                input_margin=0.0)
    assert int(comp.direction) == -1
    assert (float(comp.in_low), float(comp.in_high)) == (-1.0, 1.0)
    x = sweep(-1.0, 1.0, scale=3.0)
    with torch.no_grad():
        assert against(comp(x), x, -1) == 0


@pytest.mark.slow
def test_aoti_keeps_guard_and_clamp(tmp_path) -> None:
    from torchhys.deploy.export import load_aoti, to_aoti

    net = untrained()
    comp = StreamingCompensator(net)
    x = sweep(*default_input_range(net), scale=10.0)[::8]
    stepper = load_aoti(to_aoti(net, tmp_path / "c.pt2"))
    with torch.no_grad():
        u = torch.stack([stepper.step(v.reshape(1))[0] for v in x])
        torch.testing.assert_close(u, comp(x), rtol=0, atol=1e-12)
    assert against(u, x, 1) == 0
    outside = int(((x < comp.in_low) | (x > comp.in_high)).sum())
    assert outside > 0 and int(stepper.out_of_range_count()) == outside
    assert stepper.metadata["direction"] == "1"
