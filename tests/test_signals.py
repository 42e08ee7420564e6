"""Tests of torchhys.signals: determinism, analytic values, nesting, ranges, bad input."""

import math

import numpy as np
import pytest
import torch

from torchhys import signals


@pytest.fixture
def t() -> torch.Tensor:
    return signals.time_grid(dt=0.01, t_end=8 * math.pi, dtype=torch.float64)


def _extrema(x: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """Values of strict interior local maxima and minima."""
    a = x.numpy()
    mid, left, right = a[1:-1], a[:-2], a[2:]
    return mid[(mid > left) & (mid >= right)], mid[(mid < left) & (mid <= right)]


# --- time grid and the paper's sum of sines ---------------------------------------------

def test_time_grid_paper_length_and_dtype() -> None:
    t = signals.time_grid(dt=0.01, t_end=8 * math.pi)
    assert t.shape == (2514,) and t.dtype == torch.float32
    assert t[0] == 0 and t[-1] < 8 * math.pi
    t2 = signals.time_grid(dt=0.1, t_end=1.0, t_start=0.5, dtype=torch.float64)
    assert torch.allclose(t2, torch.tensor([0.5, 0.6, 0.7, 0.8, 0.9], dtype=torch.float64))


def test_time_grid_follows_the_default_dtype() -> None:
    old = torch.get_default_dtype()
    try:
        torch.set_default_dtype(torch.float64)
        t = signals.time_grid(dt=0.01, t_end=60.0)
        assert t.dtype == torch.float64
        assert float(t[-1]) == 59.99  # 0.01 * 5999 in float64, not a float32 rounding
    finally:
        torch.set_default_dtype(old)
    assert signals.time_grid(dt=0.01, t_end=1.0).dtype == old
    with pytest.raises(TypeError, match="floating torch.dtype"):
        signals.time_grid(dt=0.01, t_end=1.0, dtype=torch.int64)


def test_sum_of_sines_analytic(t: torch.Tensor) -> None:
    x = signals.sum_of_sines(t)
    expected = 4 * np.sin(0.5 * t.numpy()) + 2 * np.sin(3 * t.numpy())
    np.testing.assert_allclose(x.numpy(), expected, rtol=0, atol=1e-12)
    y = signals.sum_of_sines(t, amplitudes=(3.0, 2.0), frequencies=(0.5, 3.0),
                             phases=(0.0, math.pi / 2))
    np.testing.assert_allclose(y.numpy(), 3 * np.sin(0.5 * t.numpy()) + 2 * np.cos(3 * t.numpy()),
                               atol=1e-12)


def test_output_follows_t_dtype() -> None:
    t32 = signals.time_grid(dt=0.05, t_end=5.0)
    for x in (signals.sum_of_sines(t32), signals.multisine(t32, band=(0.5, 2.0)),
              signals.chirp(t32, omega0=1, omega1=2), signals.decaying_sine(t32),
              signals.nested_reversals(t32)):
        assert x.dtype == torch.float32 and x.shape == t32.shape


# --- multisines ----------------------------------------------------------------------------

def test_multisine_seeded_and_global_rng_untouched(t: torch.Tensor) -> None:
    state = torch.get_rng_state()
    a = signals.multisine(t, band=(0.2, 3.0), n_tones=8, seed=3)
    b = signals.multisine(t, band=(0.2, 3.0), n_tones=8, seed=3)
    c = signals.multisine(t, band=(0.2, 3.0), n_tones=8, seed=4)
    assert torch.equal(a, b)
    assert (a - c).abs().max() > 0.1
    assert torch.equal(state, torch.get_rng_state())


def test_multisine_rms_and_schroeder(t: torch.Tensor) -> None:
    x = signals.multisine(t, frequencies=(0.5, 1.0, 1.5), rms=2.0, seed=1)
    assert torch.isclose(x.square().mean().sqrt(), torch.tensor(2.0, dtype=x.dtype))
    s = signals.multisine(t, band=(1.0, 4.0), n_tones=16, phases="schroeder")
    r = signals.multisine(t, band=(1.0, 4.0), n_tones=16, phases="schroeder", seed=99)
    assert torch.equal(s, r)  # deterministic phases ignore the seed
    crest = s.abs().max() / s.square().mean().sqrt()
    assert crest < 2.5  # Schroeder phases keep the crest factor low (all-zero phases: ~5.7)


def test_multisine_single_tone_amplitude(t: torch.Tensor) -> None:
    x = signals.multisine(t, frequencies=(2.0,), amplitude=1.5, phases="schroeder")
    np.testing.assert_allclose(x.numpy(), 1.5 * np.sin(2.0 * t.numpy()), atol=1e-12)


# --- chirps ---------------------------------------------------------------------------------

def _zero_crossings(t: torch.Tensor, x: torch.Tensor) -> np.ndarray:
    a, tt = x.numpy(), t.numpy()
    i = np.nonzero(np.sign(a[:-1]) * np.sign(a[1:]) < 0)[0]
    return tt[i] - a[i] * (tt[i + 1] - tt[i]) / (a[i + 1] - a[i])


@pytest.mark.parametrize("sweep", ["linear", "logarithmic"])
def test_chirp_instantaneous_frequency(sweep: str) -> None:
    t = signals.time_grid(dt=1e-3, t_end=20.0, dtype=torch.float64)
    w0, w1 = 2.0, 20.0
    x = signals.chirp(t, omega0=w0, omega1=w1, t1=20.0, sweep=sweep, phase=0.3)
    z = _zero_crossings(t, x)
    mid, omega = 0.5 * (z[1:] + z[:-1]), math.pi / np.diff(z)
    if sweep == "linear":
        expected = w0 + (w1 - w0) * mid / 20.0
    else:
        expected = w0 * (w1 / w0) ** (mid / 20.0)
    np.testing.assert_allclose(omega, expected, rtol=2e-3)


def test_chirp_start_value_and_default_t1() -> None:
    t = signals.time_grid(dt=0.01, t_end=10.0, dtype=torch.float64)
    x = signals.chirp(t, omega0=1.0, omega1=5.0, amplitude=2.0, phase=math.pi / 2)
    assert x[0].item() == pytest.approx(2.0)
    y = signals.chirp(t, omega0=1.0, omega1=5.0, t1=float(t[-1]))
    assert torch.equal(signals.chirp(t, omega0=1.0, omega1=5.0), y)


# --- decaying signals: nested extrema -------------------------------------------------------

def test_decaying_sine_extrema_nest(t: torch.Tensor) -> None:
    x = signals.decaying_sine(t, amplitude=5.0, omega=3.0)
    maxima, minima = _extrema(x)
    assert len(maxima) >= 10 and len(minima) >= 10
    assert np.all(np.diff(maxima) < 0) and np.all(np.diff(minima) > 0)
    assert np.all(maxima > 0) and np.all(minima < 0)


def test_decayed_multisine_envelope(t: torch.Tensor) -> None:
    x = signals.multisine(t, band=(1.0, 2.0), n_tones=3, seed=0)
    y = signals.exponential_decay(x, t, time_constant=2.0)
    np.testing.assert_allclose(y.numpy(), x.numpy() * np.exp(-t.numpy() / 2.0), atol=1e-12)


@pytest.mark.parametrize("n_reversals,ratio,center", [(10, 0.8, 0.0), (7, 0.5, 2.0)])
def test_nested_reversals(t: torch.Tensor, n_reversals: int, ratio: float, center: float) -> None:
    x = signals.nested_reversals(t, amplitude=3.0, n_reversals=n_reversals, ratio=ratio,
                                 center=center)
    assert x[0].item() == pytest.approx(center)
    maxima, minima = _extrema(x)
    # the last extremum falls on the end of t, so it is not an interior one
    assert len(maxima) + len(minima) == n_reversals - 1
    assert np.all(np.diff(maxima) < 0) and np.all(np.diff(minima) > 0)
    assert maxima.max() == pytest.approx(center + 3.0, abs=1e-3)
    assert minima.min() == pytest.approx(center - 3.0 * ratio, abs=1e-3)
    # strictly monotone between turning points: no flat samples
    assert torch.all(torch.diff(x) != 0)


# --- rescaling ---------------------------------------------------------------------------

def test_to_range(t: torch.Tensor) -> None:
    x = signals.sum_of_sines(t)
    other = signals.to_range(signals.multisine(t, band=(0.3, 3.0), seed=1), x.min(), x.max())
    assert torch.isclose(other.min(), x.min()) and torch.isclose(other.max(), x.max())
    batch = signals.to_range(torch.stack([x, 2 * x + 1]), -1.0, 1.0)
    assert torch.allclose(batch.amin(-1), -torch.ones(2, dtype=x.dtype))
    assert torch.allclose(batch.amax(-1), torch.ones(2, dtype=x.dtype))
    assert torch.allclose(batch[0], batch[1])
    xg = x.clone().requires_grad_()
    signals.to_range(xg, 0.0, 1.0).sum().backward()
    assert torch.isfinite(xg.grad).all()


# --- bad input -------------------------------------------------------------------------------

@pytest.mark.parametrize(
    "call,match",
    [
        (lambda t: signals.time_grid(dt=0.0, t_end=1.0), "dt"),
        (lambda t: signals.time_grid(dt=-0.1, t_end=1.0), "dt"),
        (lambda t: signals.time_grid(dt=0.1, t_end=0.0), "t_end"),
        (lambda t: signals.time_grid(dt=float("nan"), t_end=1.0), "dt"),
        (lambda t: signals.sum_of_sines(t.reshape(1, -1)), "shape"),
        (lambda t: signals.sum_of_sines(torch.full((3,), float("nan"))), "finite"),
        (lambda t: signals.sum_of_sines(t, amplitudes=(-1.0, 2.0)), "non-negative"),
        (lambda t: signals.sum_of_sines(t, amplitudes=(1.0,)), "equal lengths"),
        (lambda t: signals.multisine(t), "exactly one"),
        (lambda t: signals.multisine(t, band=(2.0, 1.0)), "band"),
        (lambda t: signals.multisine(t, band=(1.0, 2.0), amplitude=1.0, rms=1.0), "not both"),
        (lambda t: signals.multisine(t, band=(1.0, 2.0), phases="zero"), "phases"),
        (lambda t: signals.multisine(t, band=(1.0, 2.0), n_tones=0), "n_tones"),
        (lambda t: signals.chirp(t, omega0=0.0, omega1=1.0, sweep="logarithmic"), "omega0"),
        (lambda t: signals.chirp(t, omega0=1.0, omega1=2.0, sweep="cubic"), "sweep"),
        (lambda t: signals.chirp(t, omega0=1.0, omega1=2.0, t1=-1.0), "t1"),
        (lambda t: signals.decaying_sine(t, time_constant=0.0), "time_constant"),
        (lambda t: signals.nested_reversals(t, ratio=1.0), "ratio"),
        (lambda t: signals.nested_reversals(t, amplitude=-1.0), "amplitude"),
        (lambda t: signals.to_range(t, 1.0, 1.0), "low"),
        (lambda t: signals.to_range(torch.ones(5), 0.0, 1.0), "constant"),
    ],
)
def test_bad_input_value_error(t: torch.Tensor, call, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        call(t)


@pytest.mark.parametrize(
    "call,match",
    [
        (lambda t: signals.sum_of_sines(t.numpy()), "torch.Tensor"),
        (lambda t: signals.sum_of_sines(torch.arange(5)), "floating"),
        (lambda t: signals.multisine(t, band=(1.0, 2.0), seed=1.5), "seed"),
        (lambda t: signals.to_range(torch.arange(5), 0.0, 1.0), "floating"),
        (lambda t: signals.time_grid(dt=0.1, t_end=1.0, dtype=torch.int64), "dtype"),
    ],
)
def test_bad_input_type_error(t: torch.Tensor, call, match: str) -> None:
    with pytest.raises(TypeError, match=match):
        call(t)
