"""The exact inverse of the stop-type Prandtl-Ishlinskii model: against a plain float64 loop
that solves each sample by bisection, round trips with the model (both ways, both
orientations), the per-sample step (eager, scripted, float32), gradcheck, float32
TorchScript export inside a network, a fitted model as its own compensator, bad input and
models without an inverse, all-or-nothing loading and the registry (chunked calls, float64
and AOTI export: tests/test_conformance.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _helpers import assert_torchscript_as_eager, random_walk, scripted_run

import torchhys
from torchhys.functional.stop_pi import stop_pi, stop_pi_inverse
from torchhys.identification.fitting import play_width_grid
from torchhys.identification.stop_pi import fit_stop_pi
from torchhys.operators.stop_pi import StopPIInverse, StopPIInverseStep, StopPrandtlIshlinskii
from torchhys.registry import OPERATORS, make_operator

F64 = torch.float64
R = [0.3, 0.8, 1.5]


# --- the reference: a plain Python float64 loop, each sample solved by bisection ---------------


def output_at(u: float, plays: list[float], r: list[float], W: np.ndarray, w0: float,
              offset: float) -> float:
    """The model's output at the current input ``u`` (centered), given the plays before it:
    every stop at ``clip(u - p_i, -r_i, r_i)``, through its characteristic."""
    K = W.shape[1]
    acc = offset + w0 * u
    for i, ri in enumerate(r):
        e = min(ri, max(-ri, u - plays[i]))
        knots = [ri * (2.0 * k / K - 1.0) for k in range(K + 1)]
        acc += sum(float(W[i, k]) * min(knots[k + 1], max(knots[k], e)) for k in range(K))
    return acc


def inverse_reference(y: np.ndarray, r: list[float], W: np.ndarray, *, center: float,
                      w0: float, offset: float, p0=None) -> tuple[np.ndarray, np.ndarray]:
    """Per row and sample: u with ``output_at(u) = y`` by bisection (the output is monotone
    in u: increasing for w0 > 0, decreasing for w0 < 0) on a bracket grown until it holds
    the root, 200 halvings; then the plays move with u. Returns (x, final plays)."""
    y = np.atleast_2d(np.asarray(y, dtype=np.float64))
    B, T = y.shape
    N = len(r)
    p = np.zeros((B, N)) if p0 is None else np.array(np.broadcast_to(p0, (B, N)), np.float64)
    x = np.empty((B, T))
    sign = 1.0 if w0 > 0 else -1.0
    for b in range(B):
        plays = [float(v) for v in p[b]]
        for t in range(T):
            def g(u, plays=plays, target=float(y[b, t])):
                return sign * (output_at(u, plays, r, W, w0, offset) - target)
            lo, hi = -1.0, 1.0
            while g(lo) > 0:
                lo *= 2.0
            while g(hi) < 0:
                hi *= 2.0
            for _ in range(200):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if g(mid) < 0 else (lo, mid)
            u = 0.5 * (lo + hi)
            x[b, t] = u + center
            plays = [min(u + ri, max(u - ri, pi)) for pi, ri in zip(plays, r, strict=True)]
        p[b] = plays
    return x, p


def weights_of(N: int, K: int, seed: int, sign: float = 1.0, zeros: bool = True) -> torch.Tensor:
    """Slopes of one sign, some exactly 0 (flat segments) when ``zeros``."""
    g = torch.Generator().manual_seed(seed)
    W = torch.rand(N, K, generator=g, dtype=F64) + 0.05
    if zeros:
        W[torch.rand(N, K, generator=g) < 0.3] = 0.0
    return sign * W


def walks(B: int = 3, T: int = 120, scale: float = 0.6) -> torch.Tensor:
    """Random walks, quantized (exact ties with the breakpoints) and not, (B, T)."""
    return scale * torch.stack([random_walk(s, T=T, quantize=s % 2 == 0) for s in range(B)])


def model(K: int, seed: int = 0, sign: float = 1.0, **kw) -> StopPrandtlIshlinskii:
    kw = {"center": 0.25, "linear_weight": sign * 0.4, "offset": -0.3, **kw}
    return StopPrandtlIshlinskii(torch.tensor(R, dtype=F64), weights_of(3, K, seed, sign), **kw)


# --- 1. against the loop ----------------------------------------------------------------------


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("K", [1, 3])
def test_inverse_matches_the_bisection_reference(K, sign):
    m = model(K, seed=K, sign=sign)
    g = torch.Generator().manual_seed(7)
    y = (0.5 * torch.randn(2, 80, generator=g, dtype=F64)).cumsum(1)  # any output sequence
    p0 = torch.tensor([[0.1, -0.4, 0.9], [0.0, 0.3, -1.2]], dtype=F64)
    x, p = m.inverse()(y, p0)
    ref, ref_p = inverse_reference(y.numpy(), R, m.weights.numpy(), center=0.25,
                                   w0=sign * 0.4, offset=-0.3, p0=p0.numpy())
    np.testing.assert_allclose(x.numpy(), ref, rtol=0, atol=1e-11)
    np.testing.assert_allclose(p.numpy(), ref_p, rtol=0, atol=1e-11)


# --- 2. round trips -----------------------------------------------------------------------------


@pytest.mark.parametrize("sign", [1.0, -1.0])
@pytest.mark.parametrize("K", [1, 2, 5])
def test_inverse_of_the_models_output_is_its_input(K, sign):
    m = model(K, seed=10 + K, sign=sign)
    x = walks()  # quantized rows tie with the breakpoints exactly
    p0 = torch.tensor([0.2, -0.5, 1.0], dtype=F64)
    y, final = m(x, p0)
    xi, pi = m.inverse()(y, p0)
    torch.testing.assert_close(xi, x, rtol=0, atol=1e-12)
    torch.testing.assert_close(pi, final, rtol=0, atol=1e-12)


def test_the_model_of_the_inverse_output_is_the_target():
    m = model(4, seed=3)
    y = walks(scale=2.0)  # beyond every stop's range too: the linear term alone
    x, p = m.inverse()(y)
    back, final = m(x)
    torch.testing.assert_close(back, y, rtol=0, atol=1e-12)
    torch.testing.assert_close(final, p, rtol=0, atol=0)


# --- 3. the per-sample step ---------------------------------------------------------------------


def test_streaming_step_equals_the_sequence_path():
    m = model(4, seed=5)
    inv = m.inverse()
    y = walks()
    with torch.no_grad():
        x, final = inv(y)
    step = inv.streaming_step(F64)
    assert isinstance(step, StopPIInverseStep)
    assert step.n_outputs == 1 and [(b.name, b.size) for b in step.state_spec] == [("plays", 3)]
    f = step.run(y)
    torch.testing.assert_close(f[..., 0], x, rtol=0, atol=0)
    scripted, state = scripted_run(step, y)
    torch.testing.assert_close(scripted, f, rtol=0, atol=0)
    torch.testing.assert_close(state[0], final, rtol=0, atol=0)
    f32 = inv.streaming_step(torch.float32).run(y.float())
    assert f32.dtype == torch.float32
    torch.testing.assert_close(f32[..., 0].double(), x, rtol=0, atol=2e-5)
    # the step holds a copy
    inv.weights.mul_(2.0)
    torch.testing.assert_close(step.run(y), f, rtol=0, atol=0)


# --- 4. autograd --------------------------------------------------------------------------------


def test_gradcheck_inverse():
    g = torch.Generator().manual_seed(3)
    y = (0.4 * torch.randn(2, 20, dtype=F64, generator=g)).cumsum(1)
    r = torch.tensor(R, dtype=F64)
    W = weights_of(3, 3, seed=6, zeros=False)
    p0 = torch.tensor([[0.13, -0.21, 0.37], [-0.05, 0.42, -0.61]], dtype=F64)  # no ties
    args = [t.clone().requires_grad_(True) for t in (
        y, W, torch.tensor(0.1, dtype=F64), torch.tensor(0.5, dtype=F64),
        torch.tensor(-0.2, dtype=F64), p0)]

    def f(y, W, c, w0, off, p0):
        return stop_pi_inverse(y, r, W, center=c, linear_weight=w0, offset=off, state=p0)[0]

    torch.autograd.gradcheck(f, args)
    # the gradient reaches every argument (none silently detached)
    x = f(*args)
    assert all(a.grad is None for a in args)
    x.sum().backward()
    assert all(a.grad is not None and bool(a.grad.abs().sum() > 0) for a in args)


@pytest.mark.parametrize("y", [
    torch.tensor([0.0, 0.7, 1.4, 2.1, 2.1, 2.1, 1.0, 1.0, -0.5, -0.5], dtype=F64),
    walks(1, 60)[0],  # quantized, with held samples
])
def test_gradient_on_held_samples_is_one_sided(y):
    """A held target after the stops slipped puts the solution exactly on breakpoints (the
    slipped stops' ``p_i + r_i``), where the solution has a kink: dx_t/dy_t is then the
    derivative on one of the two segments (a one-sided difference quotient), never a split
    between them or 0."""
    inv = model(3, seed=2).inverse()
    J = torch.autograd.functional.jacobian(lambda v: inv(v)[0], y)
    x, _ = inv(y)
    h = 1e-7
    eye = torch.eye(len(y), dtype=F64)
    up, down = (torch.stack([(inv(y + d * eye[t])[0][t] - x[t]) / d for t in range(len(y))])
                for d in (h, -h))
    diag = J.diagonal()
    one_sided = ((diag - up).abs() <= 1e-5 * up.abs() + 1e-7) | (
        (diag - down).abs() <= 1e-5 * down.abs() + 1e-7)
    assert bool(one_sided.all()), (diag, up, down)
    held = (y[1:] == y[:-1]).nonzero().flatten() + 1
    kinks = (up - down).abs() > 1e-3
    assert bool(kinks[held].any())  # the case is there: held samples at a kink
    assert bool((diag > 0).all())


# --- 5. export ---------------------------------------------------------------------------------


def test_float32_torchscript_export_of_a_network(tmp_path):  # float64: test_conformance.py
    y = walks(3, 150).float()
    inv = model(2, seed=8).inverse()
    torch.manual_seed(0)
    net = torchhys.InverseHysteresisNet([inv], hidden=4).float()
    net.fit_normalization(y, torch.tanh(y))
    assert_torchscript_as_eager(net, y, tmp_path / "comp.pt", 1e-5)


# --- 6. a fitted model as a compensator -----------------------------------------------------------


def test_fitted_model_inverse_compensates_its_plant():
    """A saturating plant with friction-type hysteresis (a tanh spring and three stops),
    identified from noisy data as fit_stop_pi identifies it (thresholds up to the input's
    span): left free, the linear weight comes out negative (the largest stops carry the
    slope) and the model has no inverse; with ``min_linear_weight`` it fits nearly as well
    and its inverse drives the plant along a reference."""
    g = torch.Generator().manual_seed(11)
    friction = StopPrandtlIshlinskii(torch.tensor([0.1, 0.3, 0.6], dtype=F64),
                                     torch.tensor([[0.2], [0.15], [0.1]], dtype=F64))

    def plant(x: torch.Tensor) -> torch.Tensor:
        return torch.tanh(2.0 * x) + friction(x)[0]

    t = torch.linspace(0, 1, 1500, dtype=F64)
    x = 1.5 * torch.sin(12 * math.pi * t) * (0.3 + 0.7 * t)
    y = plant(x) + 1e-3 * torch.randn(1500, generator=g, dtype=F64)
    thresholds = play_width_grid(x, 20, power=2.0)
    free = fit_stop_pi(x, y, thresholds, segments=4)
    assert float(free.linear_weight) < 0
    with pytest.raises(ValueError, match="min_linear_weight"):
        free.inverse()
    fitted = fit_stop_pi(x, y, thresholds, segments=4, min_linear_weight=0.05)
    rmse = [float((m(x)[0] - y).square().mean().sqrt()) for m in (free, fitted)]
    assert rmse[1] < 1.1 * rmse[0] < 0.1
    reference = 0.8 * torch.sin(torch.linspace(0, 6 * math.pi, 600, dtype=F64) + 0.3)
    command, _ = fitted.inverse()(reference)
    torch.testing.assert_close(fitted(command)[0], reference, rtol=0, atol=1e-12)
    error = float((plant(command) - reference).abs().max())
    uncompensated = float((plant(reference) - reference).abs().max())
    assert error < 0.15 < 0.3 < uncompensated, (error, uncompensated)


# --- 7. bad input -------------------------------------------------------------------------------


@pytest.mark.parametrize("kw, match", [
    ({"linear_weight": 0.0}, "linear_weight must be nonzero"),
    ({"weights": [[0.5], [-0.1], [0.2]]}, "weights must be non-negative"),
    ({"weights": [[-0.5], [0.1], [-0.2]], "linear_weight": -0.3},
     "weights must be non-positive"),
    ({"weights": [[0.5], [0.1], [0.2]], "linear_weight": -0.3}, "weights must be non-positive"),
])
def test_a_model_without_an_inverse_is_refused(kw, match):
    kw = {"weights": [[0.5], [0.1], [0.2]], "linear_weight": 0.3, **kw}
    weights = torch.tensor(kw.pop("weights"), dtype=F64)
    m = StopPrandtlIshlinskii(torch.tensor(R, dtype=F64), weights, **kw)
    with pytest.raises(ValueError, match=match):
        m.inverse()
    with pytest.raises(ValueError, match=match):
        stop_pi_inverse(walks(), m.thresholds, m.weights, linear_weight=m.linear_weight)


@pytest.mark.parametrize("y, state, err, match", [
    # NaN, 3-D, integer x: tests/test_conformance.py
    (torch.zeros(0), None, ValueError, "x must hold at least one sample"),
    (torch.zeros(2, 5), torch.zeros(2, 4), ValueError, "state"),
    (torch.zeros(2, 5), torch.tensor([0.0, math.inf, 0.0]), ValueError, "state"),
])
def test_bad_sequence_input(y, state, err, match):
    inv = model(2).inverse()
    with pytest.raises(err, match=match):
        inv(y.double(), state)


@pytest.mark.parametrize("name, match", [("weights", "weights must be finite"),
                                         ("linear_weight", "linear_weight must be finite")])
def test_a_model_made_non_finite_has_no_inverse(name, match):
    m = model(2)
    getattr(m, name).fill_(math.nan)  # after construction, in place
    with pytest.raises(ValueError, match=match):
        m.inverse()


def test_from_model_takes_a_stop_model_only():
    with pytest.raises(TypeError, match="model must be a StopPrandtlIshlinskii"):
        StopPIInverse.from_model(torchhys.PrandtlIshlinskii(torch.tensor([0.5])))
    with pytest.raises(ValueError, match="n_stops"):
        StopPIInverse(0)
    with pytest.raises(ValueError, match="segments"):
        StopPIInverse(3, 0)


@pytest.mark.parametrize("key, value, match", [
    ("linear_weight", torch.tensor(0.0, dtype=F64), "linear_weight must be nonzero"),
    ("weights", -weights_of(3, 2, seed=1), "weights must be non-negative"),
    ("weights", torch.full((3, 2), math.nan, dtype=F64), "weights must be finite"),
    ("thresholds", torch.tensor([0.3, 0.0, 1.0], dtype=F64), "thresholds must be finite and > 0"),
    ("offset", torch.tensor(math.inf, dtype=F64), "offset must be finite"),
])
def test_a_bad_state_dict_is_rejected_and_leaves_the_module_unchanged(key, value, match):
    inv = model(2, seed=1).inverse()
    before = {k: v.clone() for k, v in inv.state_dict().items()}
    sd = {k: v.clone() for k, v in before.items()}
    sd["center"] = torch.tensor(9.0, dtype=F64)  # a good change, loaded before the bad
    sd[key] = value
    with pytest.raises(ValueError, match=match):
        inv.load_state_dict(sd)
    assert all(torch.equal(inv.state_dict()[k], v) for k, v in before.items())
    # partial: the missing keys keep their values, and the whole is checked
    with pytest.raises(ValueError, match=match):
        inv.load_state_dict({key: value}, strict=False)
    assert all(torch.equal(inv.state_dict()[k], v) for k, v in before.items())
    # a placeholder takes a good saved inverse
    placeholder = StopPIInverse(3, 2).double()
    placeholder.load_state_dict(before)
    y = walks()
    torch.testing.assert_close(placeholder(y)[0], inv(y)[0], rtol=0, atol=0)


def test_registered_by_name():
    assert OPERATORS["stop_pi_inverse"] is StopPIInverse
    op = make_operator("stop_pi_inverse", n_stops=4, segments=2)
    assert isinstance(op, StopPIInverse) and op.segments == 2 and op.n_outputs == 1 and op.causal
    assert torchhys.StopPIInverse is StopPIInverse
    assert torchhys.functional.stop_pi_inverse is stop_pi_inverse
    # the functional inverse against the functional model
    x = walks()
    W = weights_of(3, 2, seed=2)
    y, _ = stop_pi(x, torch.tensor(R, dtype=F64), W, center=0.1, linear_weight=0.2)
    back, _ = stop_pi_inverse(y, torch.tensor(R, dtype=F64), W, center=0.1, linear_weight=0.2)
    torch.testing.assert_close(back, x, rtol=0, atol=1e-12)
