"""The inverse generalized Prandtl-Ishlinskii operator: exact inverse of the forward model,
the bisection against a float64 numpy reference, bounds, the per-sample step (eager,
TorchScript, float32), the implicit-function gradient, bad input (chunked calls, streaming and
export inside a network: tests/test_conformance.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _gpi_helpers import F64, WIDTHS, model, walks

from torchhys import GeneralizedPIInverse
from torchhys.functional.generalized_pi import monotone_inverse, monotone_output
from torchhys.registry import OPERATORS


def test_inverts_the_forward_model_exactly():
    m = model()
    x = walks(300)
    y, _ = m(x)
    x_back, _ = m.inverse()(y)
    torch.testing.assert_close(x_back, x, rtol=0, atol=1e-12)


def test_g_inverse_matches_a_numpy_bisection():
    a, c, b, s, off = 0.3, np.array([0.5, 0.3, 0.9]), np.array([-1.0, 0.2, 1.5]), \
        np.array([0.7, 2.0, 1.2]), -0.2

    def g(v):
        return a * v + np.tanh(s * (v[:, None] - b)) @ c + off

    y = np.linspace(-6.0, 6.0, 41)
    lo, hi = np.full_like(y, -1e3), np.full_like(y, 1e3)
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        below = g(mid) < y
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    t = [torch.tensor(v, dtype=F64) for v in (a, c, b, s, off)]
    v = monotone_inverse(torch.from_numpy(y), *t, torch.tensor(-np.inf, dtype=F64),
                         torch.tensor(np.inf, dtype=F64))
    np.testing.assert_allclose(v.numpy(), 0.5 * (lo + hi), rtol=0, atol=1e-12)


def test_bounds_hold_g_inverse_at_the_bound():
    m = model(gain=1e-9)  # a saturating g: its exact inverse is steep beyond the saturation
    inv = m.inverse(lower=-2.0, upper=3.0)
    big = torch.tensor([50.0, -50.0], dtype=F64)  # far beyond g(3), below g(-2)
    exact_pi = m.prandtl_ishlinskii().inverse()
    out, _ = inv(big)
    ref, _ = exact_pi(torch.tensor([3.0, -2.0], dtype=F64))  # p^-1 of the clamped v, fresh
    # the first sample starts from zero state in both; the second continues differently,
    # so compare sample by sample from zero state
    torch.testing.assert_close(inv(big[:1])[0], ref[:1], rtol=0, atol=1e-12)
    torch.testing.assert_close(inv(big[1:])[0], exact_pi(torch.tensor([-2.0], dtype=F64))[0],
                               rtol=0, atol=1e-12)
    assert out.isfinite().all()
    m, x = model(), walks(300)  # within the bounds the bounded inverse is exact
    p = m.prandtl_ishlinskii()(x)[0]
    inside = m.inverse(lower=float(p.min()) - 1e-9, upper=float(p.max()) + 1e-9)
    torch.testing.assert_close(inside(m(x)[0])[0], x, rtol=0, atol=1e-12)


def test_bounded_inverse_widens_the_training_range_of_the_pi_part():
    m, x = model(), walks(300)
    p = m.prandtl_ishlinskii()(x)[0].numpy()
    span = p.max() - p.min()
    for margin in (0.0, 0.5):
        inv = m.bounded_inverse(x, margin=margin)
        assert float(inv.lower) == pytest.approx(p.min() - margin * span, rel=0, abs=1e-12)
        assert float(inv.upper) == pytest.approx(p.max() + margin * span, rel=0, abs=1e-12)
        torch.testing.assert_close(inv(m(x)[0])[0], x, rtol=0, atol=1e-9)
        given = m.bounded_inverse(x, margin=margin, pi_output=torch.as_tensor(p))
        assert (float(given.lower), float(given.upper)) == (float(inv.lower), float(inv.upper))


def test_bounded_inverse_checks_the_given_pi_output():
    m, x = model(), walks(300)
    with pytest.raises(ValueError, match=r"pi_output must have the shape of x"):
        m.bounded_inverse(x, pi_output=torch.zeros(x.shape[-1] - 1, dtype=x.dtype))
    with pytest.raises(ValueError, match=r"the PI part is constant \(1\) on x"):
        m.bounded_inverse(x, pi_output=torch.ones_like(x))
    with pytest.raises(TypeError, match="pi_output must be a torch.Tensor, got list"):
        m.bounded_inverse(x, pi_output=[0.0, 1.0])
    with pytest.raises(ValueError, match="pi_output must be finite"):
        m.bounded_inverse(x, pi_output=torch.full_like(x, math.inf))
    with pytest.raises(ValueError, match="the PI part is constant"):
        m.bounded_inverse(torch.zeros_like(x))


@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_step_eager_and_scripted_equal_sequence(dtype):
    inv = model(dtype).inverse()
    y = walks(300)[:, :80].to(dtype)
    seq, final = inv(y)
    for step in (inv.streaming_step(dtype), torch.jit.script(inv.streaming_step(dtype))):
        state = [torch.zeros(3, len(WIDTHS), dtype=dtype)]
        outs = []
        for yt in y.unbind(1):
            f, state = step(yt.unsqueeze(1), state)
            outs.append(f)
        torch.testing.assert_close(torch.cat(outs, 1), seq, rtol=0, atol=0)
        torch.testing.assert_close(state[0], final, rtol=0, atol=0)


def test_gradient_is_the_implicit_function_one():
    inv = model().inverse()
    # a random walk without repeated samples (a repeat sits on a play's bound)
    y = torch.randn(25, dtype=F64, generator=torch.Generator().manual_seed(3)).cumsum(0)
    y = y.requires_grad_()
    assert torch.autograd.gradcheck(lambda v: inv(v)[0], (y,))
    # d g^-1(y) / dy = 1 / g'(g^-1(y)), against finite differences of g
    v = monotone_inverse(y, *(getattr(inv, n) for n in (
        "gain", "unit_weights", "centers", "slopes", "offset", "lower", "upper")))
    (grad,) = torch.autograd.grad(v.sum(), y)
    p = [getattr(inv, n) for n in ("gain", "unit_weights", "centers", "slopes", "offset")]
    h = 1e-6
    slope = (monotone_output(v.detach() + h, *p) - monotone_output(v.detach() - h, *p)) / (2 * h)
    torch.testing.assert_close(grad, 1 / slope, rtol=1e-7, atol=0)


def test_placeholder_loads_a_fitted_state_and_is_registered():
    inv = model().inverse(lower=-4.0, upper=4.0)
    placeholder = GeneralizedPIInverse(len(WIDTHS), 3).double()
    placeholder.load_state_dict(inv.state_dict())
    y = walks(300)
    torch.testing.assert_close(placeholder(y)[0], inv(y)[0], rtol=0, atol=0)
    assert OPERATORS["generalized_pi_inverse"] is GeneralizedPIInverse
    assert "lower=-4" in repr(placeholder)


def test_bad_input():
    with pytest.raises(ValueError, match="n_plays must be an int >= 1"):
        GeneralizedPIInverse(0)
    with pytest.raises(ValueError, match="n_units must be an int >= 0"):
        GeneralizedPIInverse(2, -1)
    with pytest.raises(ValueError, match="lower must be below upper"):
        model().inverse(lower=1.0, upper=1.0)
    with pytest.raises(ValueError, match="margin must be >= 0"):
        model().bounded_inverse(walks(50), margin=-0.1)


def test_bounds_must_be_real_numbers():
    m = model()
    with pytest.raises(ValueError, match=r"lower must be a real number \(or \+-inf\)"):
        m.inverse(lower=torch.tensor([0.0, 1.0]))
    with pytest.raises(ValueError, match="upper must be a real number"):
        m.inverse(upper=math.nan)
    inv = m.inverse(lower=torch.tensor(-2.0), upper=np.float64(3.0))
    assert (float(inv.lower), float(inv.upper)) == (-2.0, 3.0)


@pytest.mark.parametrize(("key", "value", "match"), [
    ("gain", -0.5, r"gain must be finite and > 0"),
    ("gain", math.nan, r"gain must be finite and > 0"),
    ("unit_weights", -0.1, r"unit_weights must be finite and >= 0"),
    ("slopes", -1e-3, r"slopes must be finite and >= 0"),
    ("widths", -1.0, r"widths must be finite and >= 0"),
    ("weights", math.inf, r"weights must be finite"),
    ("lower", math.nan, r"lower must be a number or \+-inf \(not NaN\)"),
    ("upper", -10.0, r"lower must be below .*upper"),
])
def test_loading_a_state_dict_that_breaks_g_is_refused(key, value, match) -> None:
    """``g^-1`` needs an increasing ``g``: a loaded buffer that breaks it names its key, and
    the module keeps its buffers."""
    inverse = GeneralizedPIInverse(3, 2)
    good = {k: v.clone() for k, v in inverse.state_dict().items()}
    good["lower"].fill_(-5.0)
    bad = {k: v.clone() for k, v in good.items()}
    bad[key].reshape(-1)[0] = value
    with pytest.raises(ValueError, match=r"^net\." + match):
        torch.nn.ModuleDict({"net": inverse}).load_state_dict(
            {"net." + k: v for k, v in bad.items()})
    assert float(inverse.lower) == -math.inf
    inverse.load_state_dict(good)
    assert float(inverse.lower) == -5.0
