"""Stop-type Prandtl-Ishlinskii model with piecewise-linear characteristics: a plain float64
loop of the definition, the stop's analytic properties (bounds, elasticity, memoryless large
stops, clockwise dissipating loops of the exact area), the per-sample step (chunked calls:
tests/test_conformance.py), autograd, TorchScript export inside a network, identification
against numpy.linalg.lstsq and scipy.optimize.nnls, the ridge's hold-out choice, bad input,
all-or-nothing loading and the registry."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from _helpers import assert_torchscript_as_eager, random_walk, scripted_run
from scipy.optimize import nnls

import torchhys
from torchhys.functional.stop_pi import stop_characteristic, stop_pi, stop_segments
from torchhys.identification.fitting import select_pi_ridge
from torchhys.identification.stop_pi import fit_stop_pi, select_stop_pi_ridge
from torchhys.operators.stop_pi import StopPIStep, StopPrandtlIshlinskii
from torchhys.registry import OPERATORS, make_operator

F64 = torch.float64
R = [0.3, 0.8, 1.5]  # thresholds of the forward tests


# --- the reference: a plain Python float64 loop of the definition -----------------------------


def stop_reference(u: list[float], r: float, p0: float = 0.0) -> list[float]:
    """The stop operator of threshold r: ``e[t] = clip(e[t-1] + u[t] - u[t-1], -r, r)``,
    ``e[0] = clip(u[0] - p0, -r, r)`` (p0: the play before the first sample)."""
    e = [min(r, max(-r, u[0] - p0))]
    for t in range(1, len(u)):
        e.append(min(r, max(-r, e[-1] + u[t] - u[t - 1])))
    return e


def segment_features(e: float, r: float, K: int) -> list[float]:
    """``clip(e, kappa_k, kappa_{k+1})``, ``kappa_k = r (2 k / K - 1)``, k = 0..K-1."""
    knots = [r * (2.0 * k / K - 1.0) for k in range(K + 1)]
    return [min(knots[k + 1], max(knots[k], e)) for k in range(K)]


def stops_reference(x: np.ndarray, thresholds, center: float, p0=None) -> np.ndarray:
    """The stop outputs of every row: x (B, T) -> (B, T, N); p0 (N,) or (B, N) or None."""
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    B, T = x.shape
    N = len(thresholds)
    p = np.zeros((B, N)) if p0 is None else np.broadcast_to(np.asarray(p0, np.float64), (B, N))
    out = np.empty((B, T, N))
    for b in range(B):
        u = [float(v) - center for v in x[b]]
        for i, r in enumerate(thresholds):
            out[b, :, i] = stop_reference(u, float(r), float(p[b, i]))
    return out


def model_reference(x, thresholds, W, *, center=0.0, w0=0.0, offset=0.0, p0=None):
    """``offset + w0 u + sum_i sum_k W[i, k] clip(e_i, kappa_ik, kappa_i(k+1))`` and the final
    plays ``u - e`` at the last sample: x (B, T) -> (y (B, T), plays (B, N))."""
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    W = np.asarray(W, dtype=np.float64)
    N, K = W.shape
    e = stops_reference(x, thresholds, center, p0)
    B, T = x.shape
    y = np.empty((B, T))
    for b in range(B):
        for t in range(T):
            u = float(x[b, t]) - center
            acc = offset + w0 * u
            for i in range(N):
                feats = segment_features(float(e[b, t, i]), float(thresholds[i]), K)
                acc += sum(float(W[i, k]) * feats[k] for k in range(K))
            y[b, t] = acc
    plays = (x[:, -1] - center)[:, None] - e[:, -1, :]
    return y, plays


def design_reference(x, thresholds, K: int, center: float, warmup: int = 0) -> np.ndarray:
    """The design ``[1, u, features of stop 0 (K), features of stop 1, ...]`` of the samples
    ``warmup:`` of every row (the stops run from the first sample), rows stacked."""
    x = np.atleast_2d(np.asarray(x, dtype=np.float64))
    e = stops_reference(x, thresholds, center)
    rows = []
    for b in range(x.shape[0]):
        for t in range(warmup, x.shape[1]):
            feats = [f for i, r in enumerate(thresholds)
                     for f in segment_features(float(e[b, t, i]), float(r), K)]
            rows.append([1.0, float(x[b, t]) - center, *feats])
    return np.array(rows)


def weights_of(N: int, K: int, seed: int, nonnegative: bool = False) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    W = torch.rand(N, K, generator=g, dtype=F64) + 0.1
    if not nonnegative:
        W = W * torch.where(torch.rand(N, K, generator=g) < 0.4, -1.0, 1.0).to(F64)
    return W


def walks(B: int = 3, T: int = 150) -> torch.Tensor:
    """Random walks, quantized (exact threshold ties) and not, (B, T)."""
    return 0.6 * torch.stack([random_walk(s, T=T, quantize=s % 2 == 0) for s in range(B)])


def stop_model(K: int, seed: int = 0, **kw) -> StopPrandtlIshlinskii:
    W = weights_of(len(R), K, seed)
    kw = {"center": 0.25, "linear_weight": 0.4, "offset": -0.3, **kw}
    return StopPrandtlIshlinskii(torch.tensor(R, dtype=F64), W, **kw)


# --- 1. forward against the loop ----------------------------------------------------------------


@pytest.mark.parametrize("K", [1, 2, 5])
def test_forward_matches_the_loop_reference(K, backend):
    m = stop_model(K, seed=K)
    x = walks()
    W = m.weights.numpy()
    ref, plays = model_reference(x.numpy(), R, W, center=0.25, w0=0.4, offset=-0.3)
    y, state = m(x)
    assert y.shape == x.shape and state.shape == (3, len(R)) and y.dtype == F64
    np.testing.assert_allclose(y.numpy(), ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(state.numpy(), plays, rtol=0, atol=1e-12)
    y1, s1 = m(x[1])  # unbatched
    assert y1.shape == (x.shape[1],) and s1.shape == (len(R),)
    np.testing.assert_allclose(y1.numpy(), ref[1], rtol=0, atol=1e-12)
    # the functional core, from a given initial play state (one per row)
    p0 = torch.tensor([[0.2, -0.9, 1.1], [3.0, -3.0, 0.0], [0.0, 0.5, -0.7]], dtype=F64)
    ref0, plays0 = model_reference(x.numpy(), R, W, center=0.25, w0=0.4, offset=-0.3,
                                   p0=p0.numpy())
    y0, s0 = stop_pi(x, m.thresholds, m.weights, center=0.25, linear_weight=0.4, offset=-0.3,
                     state=p0)
    np.testing.assert_allclose(y0.numpy(), ref0, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s0.numpy(), plays0, rtol=0, atol=1e-12)
    assert not np.allclose(ref0, ref, atol=1e-3)  # the initial state matters


def test_one_segment_is_the_classical_stop_pi_model():
    """K = 1: ``offset + w0 u + sum_i W[i, 0] e_i`` (the characteristic is the identity on
    [-r, r], where the stop output lives)."""
    W = torch.tensor([[0.7], [-0.4], [1.3]], dtype=F64)
    m = StopPrandtlIshlinskii(torch.tensor(R, dtype=F64), W, center=-0.1, linear_weight=0.25,
                              offset=0.5)
    x = walks()
    e = stops_reference(x.numpy(), R, -0.1)
    ref = 0.5 + 0.25 * (x.numpy() + 0.1) + e @ W[:, 0].numpy()
    np.testing.assert_allclose(m(x)[0].numpy(), ref, rtol=0, atol=1e-12)
    # the characteristic of one segment spans [-r, r]: the features are the stop outputs
    s = torch.tensor(e, dtype=F64)
    torch.testing.assert_close(stop_segments(s, m.thresholds, 1)[..., 0], s, rtol=0, atol=0)
    torch.testing.assert_close(stop_characteristic(s, m.thresholds, W),
                               torch.tensor(e @ W[:, 0].numpy()), rtol=0, atol=1e-13)


def test_characteristic_is_piecewise_linear_with_equal_segments():
    """On the stop's range the characteristic's slope is W[i, k] on segment k, its knots at
    ``r (2 k / K - 1)``; at -r every feature sits at its lower knot, at r at its upper."""
    r = torch.tensor([2.0], dtype=F64)
    W = torch.tensor([[1.0, -2.0, 0.5, 3.0]], dtype=F64)  # knots -2, -1, 0, 1, 2
    s = torch.linspace(-2.0, 2.0, 401, dtype=F64)[:, None]
    f = stop_characteristic(s, r, W)
    slopes = f.diff() / s[:, 0].diff()
    expect = torch.tensor([1.0, -2.0, 0.5, 3.0], dtype=F64).repeat_interleave(100)
    torch.testing.assert_close(slopes, expect, rtol=0, atol=1e-10)
    assert float(f[0]) == 1.0 * -2 + -2.0 * -1 + 0.5 * 0 + 3.0 * 1  # sum_k W_k kappa_k
    assert float(f[-1]) == 1.0 * -1 + -2.0 * 0 + 0.5 * 1 + 3.0 * 2  # sum_k W_k kappa_k+1
    assert float(f[200]) == 1.0 * -1 + -2.0 * 0 + 0.5 * 0 + 3.0 * 1  # at s = 0


# --- 2. analytic properties --------------------------------------------------------------------


def test_stop_output_stays_in_its_bounds_and_follows_the_input_inside():
    """With one unit-slope segment and no linear term the output is the stop itself: in
    [-r, r] from any initial play, and moving with the input wherever it is strictly inside."""
    x = 2.5 * walks(4, 300)
    for r in (0.05, 0.5, 2.0):
        m = StopPrandtlIshlinskii(torch.tensor([r], dtype=F64), torch.ones(1, 1, dtype=F64))
        for p0 in (None, torch.tensor([-40.0, 0.3, 40.0, 5.0], dtype=F64)[:, None]):
            s, _ = m(x, p0)
            assert float(s.abs().max()) <= r * (1 + 1e-15)
            assert float(s.abs().max()) == pytest.approx(r)  # it does slip
            inside = (s[:, 1:].abs() < r - 1e-12)
            torch.testing.assert_close(s.diff()[inside], x.diff()[inside], rtol=0, atol=1e-12)


def test_a_stop_wider_than_the_input_is_memoryless():
    """Zero initial plays and |u| < r throughout: the stop output equals u, so the model is
    the static function ``offset + w0 u + sum_k W clip(u, kappa_k, kappa_k+1)`` of u."""
    center = 0.7
    t = torch.linspace(0, 20, 500, dtype=F64)
    x = center + 0.9 * torch.sin(t) * torch.cos(0.37 * t)  # |u| <= 0.9
    thresholds = torch.tensor([1.0, 1.6], dtype=F64)
    W = torch.tensor([[0.5, -1.0, 2.0], [1.5, 0.2, -0.3]], dtype=F64)
    m = StopPrandtlIshlinskii(thresholds, W, center=center, linear_weight=0.3, offset=0.1)
    y, _ = m(x)
    u = (x - center).tolist()
    static = [0.1 + 0.3 * v + sum(
        w * f for i in range(2)
        for w, f in zip(W[i].tolist(), segment_features(v, float(thresholds[i]), 3),
                        strict=True)) for v in u]
    torch.testing.assert_close(y, torch.tensor(static, dtype=F64), rtol=0, atol=1e-12)
    # no loop: the same input value gives the same output, whatever the history
    order = torch.argsort(x)
    y_sorted, x_sorted = y[order], x[order]
    assert bool((y_sorted.diff()[x_sorted.diff() == 0] == 0).all())
    # ... while a threshold inside the input's range makes a loop (not memoryless)
    narrow = StopPrandtlIshlinskii(torch.tensor([0.3], dtype=F64), torch.ones(1, 1, dtype=F64),
                                   center=center)
    s, _ = narrow(x)
    assert float((s - (x - center)).abs().max()) > 0.1


def triangle(amplitude: float, h: float, periods: int) -> torch.Tensor:
    """A triangle wave from -A up to A and back, step h, ``periods`` periods, closed."""
    n = round(2 * amplitude / h)
    up = [-amplitude + k * h for k in range(n)]
    down = [amplitude - k * h for k in range(n)]
    return torch.tensor((up + down) * periods + [-amplitude], dtype=F64)


def loop_integral(x: torch.Tensor, y: torch.Tensor) -> float:
    """``oint y dx`` of the polyline (trapezoids): > 0 for a clockwise loop in (x, y)."""
    return float((0.5 * (y[1:] + y[:-1]) * x.diff()).sum())


@pytest.mark.parametrize("K", [1, 2, 4])
def test_loops_run_clockwise_and_dissipate_the_exact_energy(K):
    """A triangle wave of amplitude A: stop i's play moves by 2 (A - r_i) each way per period,
    and its characteristic phi_i (slopes W[i]) rises ``phi_i(r) - phi_i(-r) = (2 r_i / K)
    sum_k W[i, k]``; the loop integral is ``oint y dx = sum_i (phi_i(r) - phi_i(-r)) 2 (A -
    r_i)^+`` (w0 and the offset add nothing), positive with W >= 0: the loops run clockwise
    (the output leads: it is higher on the rising branch). The knots and the slip points
    fall on samples, so the trapezoids are exact."""
    A, h = 2.0, 1.0 / 64
    x = triangle(A, h, periods=3)
    n = round(4 * A / h)  # samples a period
    thresholds = [0.25, 0.5, 1.0, 1.5, 2.5]  # 2.5 > A: never slips (no loop)
    W = weights_of(5, K, seed=10 + K, nonnegative=True)
    m = StopPrandtlIshlinskii(torch.tensor(thresholds, dtype=F64), W, linear_weight=0.7,
                              offset=0.2)
    y, _ = m(x)
    expect = sum((2 * r / K) * float(W[i].sum()) * 2 * max(A - r, 0.0)
                 for i, r in enumerate(thresholds))
    last = slice(len(x) - 1 - n, len(x))  # the last period, -A to -A
    area = loop_integral(x[last], y[last])
    assert area > 0.5
    assert area == pytest.approx(expect, rel=1e-12, abs=1e-12)
    # the loop is periodic from the first sample, and the rising branch lies above
    torch.testing.assert_close(y[:n], y[n:2 * n], rtol=0, atol=1e-12)
    rising, falling = y[: n // 2 + 1], y[n // 2 : n + 1].flip(0)  # both from -A to A
    assert bool((rising >= falling - 1e-12).all()) and bool((rising > falling + 1e-3).any())
    # negative slopes turn the loop counterclockwise, by the same area
    neg = StopPrandtlIshlinskii(m.thresholds, -W, linear_weight=0.7, offset=0.2)
    yn, _ = neg(x)
    assert loop_integral(x[last], yn[last]) == pytest.approx(-expect, rel=1e-12, abs=1e-12)


def test_nonnegative_slopes_dissipate_on_random_periodic_inputs():
    """Any periodic input, W >= 0 and w0 >= 0: the loop integral over a period (after the
    first) is >= 0 (in steady state the plays repeat)."""
    g = torch.Generator().manual_seed(4)
    base = torch.randn(80, generator=g, dtype=F64).cumsum(0)
    base = torch.cat([base, base.flip(0)[1:]])  # closed: ends where it starts
    x = torch.cat([base[:-1]] * 3 + [base[-1:]])
    period = len(base) - 1
    for seed in range(5):
        W = weights_of(4, 3, seed=seed, nonnegative=True)
        m = StopPrandtlIshlinskii(torch.tensor([0.2, 0.9, 2.0, 4.0], dtype=F64), W,
                                  linear_weight=0.5, center=float(base.mean()))
        y, _ = m(x)
        sl = slice(2 * period, 3 * period + 1)
        assert loop_integral(x[sl], y[sl]) > 0.1
        torch.testing.assert_close(y[period:2 * period], y[2 * period:3 * period],
                                   rtol=0, atol=1e-12)


# --- 3. the per-sample step (chunked calls: tests/test_conformance.py) -------------------------


def test_streaming_step_equals_the_sequence_path():
    m = stop_model(4, seed=3)
    x = walks()
    with torch.no_grad():
        y, final = m(x)
    step = m.streaming_step(F64)
    assert isinstance(step, StopPIStep)
    assert step.n_outputs == 1 and [(b.name, b.size) for b in step.state_spec] == [("plays", 3)]
    f = step.run(x)
    assert f.shape == (3, x.shape[1], 1) and f.dtype == F64
    torch.testing.assert_close(f[..., 0], y, rtol=0, atol=0)
    # the step's state is the sequence path's
    state = step.initial_state(x[:, :1])
    for xt in x.unbind(1):
        _, state = step(xt.unsqueeze(1), state)
    torch.testing.assert_close(state[0], final, rtol=0, atol=0)
    # scripted (the export path) equals eager
    torch.testing.assert_close(scripted_run(step, x)[0], f, rtol=0, atol=0)
    # float32: a step in float32 of the float64 model stays close
    f32 = m.streaming_step(torch.float32).run(x.float())
    assert f32.dtype == torch.float32
    torch.testing.assert_close(f32[..., 0].double(), y, rtol=0, atol=2e-5)
    # the step holds a copy: changing the model afterwards does not change it
    with torch.no_grad():
        m.weights.mul_(2.0)
    torch.testing.assert_close(step.run(x), f, rtol=0, atol=0)


def test_float32_module_matches_float64():
    m = stop_model(2, seed=1)
    x = walks()
    y64, _ = m(x)
    m32 = stop_model(2, seed=1).float()
    y32, s32 = m32(x.float())
    assert y32.dtype == torch.float32 and s32.dtype == torch.float32
    torch.testing.assert_close(y32.double(), y64, rtol=0, atol=2e-5)


# --- 4. autograd --------------------------------------------------------------------------------


def test_gradcheck_forward():
    m = StopPrandtlIshlinskii(torch.tensor(R, dtype=F64), weights_of(3, 3, seed=5),
                              center=0.1, linear_weight=0.3, offset=-0.2, learnable=True)
    names = [n for n, _ in m.named_parameters()]
    assert set(names) == {"weights", "linear_weight", "offset"}
    assert {n for n, _ in m.named_buffers()} == {"thresholds", "center"}
    params = tuple(p.detach().clone().requires_grad_(True) for p in m.parameters())
    g = torch.Generator().manual_seed(3)
    x = (0.4 * torch.randn(2, 25, dtype=F64, generator=g)).cumsum(1)  # no repeated samples
    p0 = torch.tensor([[0.1, -0.2, 0.3], [-0.05, 0.4, -0.6]], dtype=F64)

    def f(x, p0, *ps):
        return torch.func.functional_call(m, dict(zip(names, ps, strict=True)), (x, p0))[0]

    torch.autograd.gradcheck(f, (x.requires_grad_(True), p0.requires_grad_(True), *params))
    # the gradient reaches every parameter (none is silently detached)
    y, _ = m(x.detach())
    y.sum().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in m.parameters())


# --- 5. export ---------------------------------------------------------------------------------


def test_float32_torchscript_export_of_a_network(tmp_path):  # float64: test_conformance.py
    x = walks(3, 200).float()
    op = StopPrandtlIshlinskii(torch.tensor(R), weights_of(3, 2, seed=2).float(),
                               center=0.1, linear_weight=0.5, learnable=True)
    torch.manual_seed(0)
    net = torchhys.InverseHysteresisNet([op], hidden=4).float()
    net.fit_normalization(x, torch.tanh(x))
    assert_torchscript_as_eager(net, x, tmp_path / "comp.pt", 1e-5)


# --- 6. identification ----------------------------------------------------------------------------

FIT_R = [0.25, 0.6, 1.2, 2.0]


def fit_input(B: int = 2, T: int = 900, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (0.2 * torch.randn(B, T, generator=g, dtype=F64)).cumsum(1)


def noise(shape, sigma: float, seed: int) -> torch.Tensor:
    return sigma * torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=F64)


@pytest.mark.parametrize("nonnegative, K", [(False, 1), (False, 3), (True, 1), (True, 3)])
def test_fit_recovers_a_representable_model(nonnegative, K):
    W = weights_of(4, K, seed=20 + K, nonnegative=nonnegative)
    if nonnegative:
        W[0, 0] = 0.0  # a slope on its constraint
    true = StopPrandtlIshlinskii(torch.tensor(FIT_R, dtype=F64), W, center=0.35,
                                 linear_weight=-0.3 if not nonnegative else 0.3, offset=0.8)
    x = fit_input()
    y, _ = true(x)
    m = fit_stop_pi(x, y, torch.tensor(FIT_R, dtype=F64), segments=K, nonnegative=nonnegative,
                    center=0.35)
    assert isinstance(m, StopPrandtlIshlinskii) and m.segments == K and m.weights.dtype == F64
    assert float(m.center) == 0.35
    torch.testing.assert_close(m.weights, W, rtol=0, atol=1e-8)
    assert float(m.linear_weight) == pytest.approx(float(true.linear_weight), abs=1e-8)
    assert float(m.offset) == pytest.approx(0.8, abs=1e-8)
    assert not m.weights.requires_grad
    torch.testing.assert_close(m(x)[0], y, rtol=0, atol=1e-8)


@pytest.mark.parametrize("ridge, warmup, K", [(0.0, 0, 2), (0.0, 40, 3), (1e-3, 0, 2),
                                              (0.05, 25, 1)])
def test_unconstrained_fit_matches_numpy_lstsq(ridge, warmup, K):
    x = fit_input(seed=1)
    W = weights_of(4, K, seed=K)
    y, _ = stop_pi(x, torch.tensor(FIT_R, dtype=F64), W, center=0.1, linear_weight=0.4)
    y = y + noise(y.shape, 0.05, 2)
    m = fit_stop_pi(x, y, torch.tensor(FIT_R, dtype=F64), segments=K, ridge=ridge,
                    nonnegative=False, center=0.1, warmup=warmup)
    A = design_reference(x.numpy(), FIT_R, K, 0.1, warmup)
    b = y[:, warmup:].reshape(-1).numpy()
    n, cols = A.shape
    # mean squared residual + ridge |W|^2: rows sqrt(n ridge) on the W columns
    pen = np.hstack([np.zeros((cols - 2, 2)), math.sqrt(n * ridge) * np.eye(cols - 2)])
    theta = np.linalg.lstsq(np.vstack([A, pen]), np.concatenate([b, np.zeros(cols - 2)]),
                            rcond=None)[0]
    ours = np.concatenate([[float(m.offset), float(m.linear_weight)], m.weights.numpy().ravel()])
    np.testing.assert_allclose(ours, theta, rtol=0, atol=1e-8)


def objective(A: np.ndarray, b: np.ndarray, theta: np.ndarray, ridge: float) -> float:
    return float(np.mean((A @ theta - b) ** 2) + ridge * np.sum(theta[2:] ** 2))


@pytest.mark.parametrize("ridge, warmup, K", [(0.0, 0, 2), (1e-3, 30, 3), (0.0, 10, 1)])
def test_nonnegative_fit_matches_scipy_nnls(ridge, warmup, K):
    """scipy's NNLS on the design with the free columns (offset, w0) split into +/- parts
    and ridge rows for W: the same solution and objective; W >= 0 with active constraints,
    where the unconstrained fit goes negative."""
    x = fit_input(seed=3)
    W = weights_of(4, K, seed=30 + K)  # mixed signs
    y, _ = stop_pi(x, torch.tensor(FIT_R, dtype=F64), W, center=-0.2, linear_weight=0.4,
                   offset=-0.5)
    y = y + noise(y.shape, 0.05, 4)
    m = fit_stop_pi(x, y, torch.tensor(FIT_R, dtype=F64), segments=K, ridge=ridge,
                    center=-0.2, warmup=warmup)  # nonnegative by default
    A = design_reference(x.numpy(), FIT_R, K, -0.2, warmup)
    b = y[:, warmup:].reshape(-1).numpy()
    n, cols = A.shape
    split = np.hstack([A[:, :2], -A[:, :2], A[:, 2:]]) / math.sqrt(n)
    pen = np.hstack([np.zeros((cols - 2, 4)), math.sqrt(ridge) * np.eye(cols - 2)])
    z, _ = nnls(np.vstack([split, pen]), np.concatenate([b / math.sqrt(n), np.zeros(cols - 2)]),
                maxiter=50 * cols)
    theta = np.concatenate([z[:2] - z[2:4], z[4:]])
    ours = np.concatenate([[float(m.offset), float(m.linear_weight)], m.weights.numpy().ravel()])
    assert bool((m.weights >= 0).all())
    assert int((m.weights == 0).sum()) > 0  # constraints are active
    assert objective(A, b, ours, ridge) <= objective(A, b, theta, ridge) * (1 + 1e-10) + 1e-14
    np.testing.assert_allclose(ours, theta, rtol=0, atol=1e-7)
    free = fit_stop_pi(x, y, torch.tensor(FIT_R, dtype=F64), segments=K, ridge=ridge,
                       center=-0.2, warmup=warmup, nonnegative=False)
    assert float(free.weights.min()) < 0
    assert objective(A, b, np.concatenate([[float(free.offset), float(free.linear_weight)],
                                           free.weights.numpy().ravel()]), ridge) < \
        objective(A, b, ours, ridge)


@pytest.mark.parametrize("nonnegative, ridge, bound", [(True, 0.0, 0.9), (True, 1e-3, 0.0),
                                                       (False, 0.0, 0.9)])
def test_min_linear_weight_matches_scipy_bounded_least_squares(nonnegative, ridge, bound):
    """``w0 >= min_linear_weight`` (and W >= 0 when nonnegative) against
    scipy.optimize.lsq_linear with the same bounds on the design plus ridge rows: the same
    solution; the bound is active where the free fit's w0 is below it."""
    from scipy.optimize import lsq_linear

    x = fit_input(seed=8)
    K, warmup = 2, 20
    W = weights_of(4, K, seed=40)
    y, _ = stop_pi(x, torch.tensor(FIT_R, dtype=F64), W, center=0.1, linear_weight=-0.4,
                   offset=0.3)
    y = y + noise(y.shape, 0.05, 9)
    thresholds = torch.tensor(FIT_R, dtype=F64)
    m = fit_stop_pi(x, y, thresholds, segments=K, ridge=ridge, center=0.1, warmup=warmup,
                    nonnegative=nonnegative, min_linear_weight=bound)
    free = fit_stop_pi(x, y, thresholds, segments=K, ridge=ridge, center=0.1, warmup=warmup,
                       nonnegative=nonnegative)
    A = design_reference(x.numpy(), FIT_R, K, 0.1, warmup)
    b = y[:, warmup:].reshape(-1).numpy()
    n, cols = A.shape
    pen = np.hstack([np.zeros((cols - 2, 2)), math.sqrt(ridge * n) * np.eye(cols - 2)])
    lower = np.r_[-np.inf, bound, np.zeros(cols - 2) if nonnegative else np.full(cols - 2, -np.inf)]
    ref = lsq_linear(np.vstack([A, pen]), np.r_[b, np.zeros(cols - 2)], bounds=(lower, np.inf),
                     method="bvls", tol=1e-14).x
    ours = np.r_[float(m.offset), float(m.linear_weight), m.weights.numpy().ravel()]
    assert float(free.linear_weight) < bound == float(m.linear_weight)  # active
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-7)
    assert objective(A, b, ours, ridge) <= objective(A, b, ref, ridge) * (1 + 1e-10) + 1e-14
    # the same bound in the hold-out choice of the ridge: its fits respect it
    best, scores = select_stop_pi_ridge(x, y, thresholds, [0.0, 1e-2], segments=K,
                                        center=0.1, warmup=warmup, nonnegative=nonnegative,
                                        min_linear_weight=bound)
    assert best in scores and all(math.isfinite(v) for v in scores.values())
    _, free_scores = select_stop_pi_ridge(x, y, thresholds, [0.0, 1e-2], segments=K,
                                          center=0.1, warmup=warmup, nonnegative=nonnegative)
    assert scores != free_scores


@pytest.mark.parametrize("bound", [0.0, 0.05, 0.2, 0.5])
def test_min_linear_weight_on_collinear_stops_keeps_the_optimum(bound):
    """Thresholds up to the input's span (play_width_grid): the largest stops never slip, so
    their features and u are collinear and the Gram matrix is singular. A bound on w0 then
    costs nothing: with free slopes the bounded fit reaches the unbounded fit's error (the
    never-slipping stops take up the slope), deterministically."""
    from torchhys.identification.fitting import play_width_grid

    t = torch.linspace(0, 1, 1500, dtype=F64)
    x = 1.5 * torch.sin(12 * math.pi * t) * (0.3 + 0.7 * t)
    y = torch.tanh(2.0 * x) + stop_pi(x, torch.tensor([0.1, 0.3, 0.6], dtype=F64),
                                      torch.tensor([[0.2], [0.15], [0.1]], dtype=F64))[0]
    y = y + noise(y.shape, 1e-3, 12)
    thresholds = play_width_grid(x, 20, power=2.0)
    free = fit_stop_pi(x, y, thresholds, segments=4, nonnegative=False)

    def rmse(m: StopPrandtlIshlinskii) -> float:
        return float((m(x)[0] - y).square().mean().sqrt())

    fits = [fit_stop_pi(x, y, thresholds, segments=4, nonnegative=False,
                        min_linear_weight=bound) for _ in range(2)]
    assert float(fits[0].linear_weight) >= bound
    assert rmse(fits[0]) == pytest.approx(rmse(free), rel=1e-6)
    torch.testing.assert_close(fits[0].weights, fits[1].weights, rtol=0, atol=0)


def test_warmup_leaves_samples_out_of_the_fit_and_of_the_centre():
    x = fit_input(seed=5)
    thresholds = torch.tensor(FIT_R, dtype=F64)
    W = weights_of(4, 2, seed=6, nonnegative=True)
    y, _ = stop_pi(x, thresholds, W, center=0.2, linear_weight=0.3)
    bad = y.clone()
    bad[:, :60] += 5.0 * noise((2, 60), 1.0, 7)  # corrupt only the warmup
    x_spike = x.clone()
    x_spike[:, 3] = 40.0  # an extreme input inside the warmup
    a = fit_stop_pi(x, y, thresholds, segments=2, center=0.2, warmup=60)
    b = fit_stop_pi(x, bad, thresholds, segments=2, center=0.2, warmup=60)
    for p, q in ((a.weights, b.weights), (a.linear_weight, b.linear_weight),
                 (a.offset, b.offset)):
        torch.testing.assert_close(p, q, rtol=0, atol=0)
    torch.testing.assert_close(b.weights, W, rtol=0, atol=1e-8)
    c = fit_stop_pi(x, bad, thresholds, segments=2, center=0.2)  # no warmup: corrupted
    assert float((c.weights - W).abs().max()) > 1e-2
    # the default center is the midpoint of the fitted samples only
    d = fit_stop_pi(x_spike, y, thresholds, segments=2, warmup=60)
    xs = x_spike[:, 60:]
    assert float(d.center) == pytest.approx(0.5 * float(xs.min() + xs.max()), abs=1e-15)
    e = fit_stop_pi(x, y, thresholds, segments=2)
    assert float(e.center) == pytest.approx(0.5 * float(x.min() + x.max()), abs=1e-15)


def test_ridge_shrinks_the_slopes():
    x = fit_input(seed=8)
    thresholds = torch.tensor(FIT_R, dtype=F64)
    y, _ = stop_pi(x, thresholds, weights_of(4, 3, seed=9), center=0.0, linear_weight=0.2)
    y = y + noise(y.shape, 0.1, 10)
    for nonnegative in (False, True):
        norms = [float(fit_stop_pi(x, y, thresholds, segments=3, ridge=ridge, center=0.0,
                                   nonnegative=nonnegative).weights.norm())
                 for ridge in (0.0, 1e-3, 1e-2, 1e-1, 1.0, 100.0)]
        assert norms[-1] < 0.05 * norms[0]
        if not nonnegative:  # Tikhonov: the penalised norm falls strictly with the ridge
            assert all(a > b for a, b in zip(norms, norms[1:], strict=False))
        else:
            assert norms[-1] < norms[2] < norms[0]


@pytest.mark.parametrize("nonnegative, warmup, validation", [(False, 0, 0.25), (True, 30, 0.3)])
def test_select_ridge_scores_the_hold_out(nonnegative, warmup, validation):
    """Each candidate fitted on the first part of every row (center: the midpoint of the
    fitted samples), run over the whole rows, scored by the RMS error on the rest."""
    g = torch.Generator().manual_seed(11)
    t = torch.arange(700, dtype=F64)
    x = torch.stack([torch.sin(0.05 * t) * (1 + 0.5 * torch.sin(0.011 * t)) + 0.4 * torch.sin(
        0.23 * t), 1.2 * torch.sin(0.031 * t + 1.0) + 0.1 * torch.randn(700, generator=g,
                                                                       dtype=F64)])
    thresholds = torch.tensor([0.1, 0.3, 0.6, 1.0, 1.5], dtype=F64)
    y, _ = stop_pi(x, thresholds, weights_of(5, 2, seed=12, nonnegative=nonnegative),
                   center=0.05, linear_weight=0.3)
    y = y + noise(y.shape, 0.3, 13)
    ridges = [0.0, 1e-4, 1e-2, 0.3, 30.0]
    best, scores = select_stop_pi_ridge(x, y, thresholds, ridges, segments=3,
                                        nonnegative=nonnegative, validation=validation,
                                        warmup=warmup)
    T = x.shape[1]
    split = T - max(1, round(validation * T))
    xs = x[:, warmup:split]
    c = 0.5 * (float(xs.min()) + float(xs.max()))
    mine = {}
    for ridge in ridges:
        m = fit_stop_pi(x[:, :split], y[:, :split], thresholds, segments=3, ridge=ridge,
                        nonnegative=nonnegative, center=c, warmup=warmup)
        assert float(m.center) == c
        pred, _ = m(x)  # the stops run through the whole rows
        mine[ridge] = float((pred[:, split:] - y[:, split:]).square().mean().sqrt())
    assert set(scores) == set(ridges)
    for ridge in ridges:
        assert scores[ridge] == pytest.approx(mine[ridge], rel=1e-6)
    assert best == min(mine, key=mine.__getitem__)
    assert max(mine.values()) > 1.05 * min(mine.values())  # the choice matters


# --- 7. bad input -------------------------------------------------------------------------------

X = torch.linspace(-1.0, 1.0, 20, dtype=F64)
T3 = torch.tensor([0.2, 0.5, 1.0], dtype=F64)
W3 = torch.ones(3, 2, dtype=F64)
NAN = math.nan


@pytest.mark.parametrize("thresholds, weights, err, match", [
    (torch.tensor([0.2, 0.0, 1.0], dtype=F64), W3, ValueError, "thresholds must be positive"),
    (torch.tensor([0.2, -0.5, 1.0], dtype=F64), W3, ValueError,
     "thresholds must be positive, got minimum -0.5"),
    (torch.zeros(0, dtype=F64), torch.ones(0, 2, dtype=F64), ValueError,
     r"thresholds must have shape \(N,\) with N >= 1, got shape \(0,\)"),
    (torch.ones(3, 1, dtype=F64), W3, ValueError,
     r"thresholds must have shape \(N,\) with N >= 1, got shape \(3, 1\)"),
    (torch.tensor([0.2, NAN, 1.0], dtype=F64), W3, ValueError, "thresholds must be finite"),
    (torch.tensor([0.2, math.inf, 1.0], dtype=F64), W3, ValueError,
     "thresholds must be finite"),
    (T3, torch.ones(3, dtype=F64), ValueError, r"weights must have shape \(3, K\)"),
    (T3, torch.ones(2, 2, dtype=F64), ValueError,
     r"weights must have shape \(3, K\).* got shape \(2, 2\)"),
    (T3, torch.ones(3, 0, dtype=F64), ValueError, r"weights must have shape \(3, K\)"),
    (T3, torch.full((3, 2), NAN, dtype=F64), ValueError, "weights must be finite"),
])
def test_bad_thresholds_and_weights(thresholds, weights, err, match):
    with pytest.raises(err, match=match):
        stop_pi(X, thresholds, weights)
    with pytest.raises(err, match=match):
        StopPrandtlIshlinskii(thresholds, weights)


def test_the_functional_core_takes_float_tensor_thresholds_only():
    """The module converts a list or an integer tensor (to the default dtype); the
    functional core does not."""
    with pytest.raises(TypeError, match="thresholds must have a floating-point dtype"):
        stop_pi(X, torch.tensor([1, 2, 3]), W3)
    with pytest.raises(TypeError, match="thresholds must be a torch.Tensor"):
        stop_pi(X, [0.2, 0.5, 1.0], W3)
    with pytest.raises(TypeError, match="weights must have a floating-point dtype"):
        stop_pi(X, T3, torch.ones(3, 2, dtype=torch.long))
    with pytest.raises(TypeError, match="weights must be a torch.Tensor"):
        stop_pi(X, T3, [[1.0, 1.0]] * 3)
    # the module converts them (nested lists as a config gives them), to the thresholds' dtype
    for w in ([[1.0, 1.0]] * 3, torch.ones(3, 2, dtype=torch.long)):
        m = StopPrandtlIshlinskii(T3, w)
        assert m.weights.dtype == F64 and torch.equal(m.weights, W3)
    for bad, match in (("abc", "thresholds must be a tensor or a sequence of real numbers"),
                       ([0.1, None], "thresholds must be a tensor or a sequence of real"),
                       (torch.tensor([0.1 + 1j]), "thresholds must hold real numbers")):
        with pytest.raises(TypeError, match=match):
            StopPrandtlIshlinskii(bad)
    with pytest.raises(TypeError, match="weights must hold real numbers"):
        StopPrandtlIshlinskii(T3, torch.ones(3, 2, dtype=torch.complex128))
    for r in ([1, 2, 3], torch.tensor([1, 2, 3])):
        m = StopPrandtlIshlinskii(r, W3)
        assert m.thresholds.dtype == torch.get_default_dtype() == m.weights.dtype
        assert m.thresholds.tolist() == [1.0, 2.0, 3.0]


@pytest.mark.parametrize("kwargs, err, match", [
    # NaN, 3-D, integer x: tests/test_conformance.py (the module calls stop_pi)
    ({"x": torch.zeros(2, 0, dtype=F64)}, ValueError, "x must hold at least one sample"),
    ({"p0": torch.zeros(4, dtype=F64)}, ValueError, r"must have shape \(3,\) or \(1, 3\)"),
    ({"p0": torch.full((3,), NAN, dtype=F64)}, ValueError, "must be finite"),
])
def test_bad_sequence_input(kwargs, err, match):
    args = {"x": X, "p0": None, **kwargs}
    with pytest.raises(err, match=match):
        stop_pi(args["x"], T3, W3, state=args["p0"])
    m = StopPrandtlIshlinskii(T3, W3)
    with pytest.raises(err, match=match):
        m(args["x"], args["p0"])


@pytest.mark.parametrize("kwargs, err, match", [
    ({"learnable": "yes"}, TypeError, "learnable must be True or False, got str 'yes'"),
    ({"learnable": 1}, TypeError, "learnable must be True or False"),
    ({"center": NAN}, ValueError, "center must be a finite real number"),
    ({"linear_weight": math.inf}, ValueError, "linear_weight must be a finite real number"),
    ({"offset": "0"}, ValueError, "offset must be a finite real number"),
    ({"thresholds": []}, ValueError, r"thresholds must have shape \(N,\) with N >= 1"),
    ({"thresholds": [0.5, -1.0]}, ValueError, "thresholds must be positive"),
])
def test_bad_module_options(kwargs, err, match):
    args = {"thresholds": [0.2, 0.5, 1.0], **kwargs}
    with pytest.raises(err, match=match):
        StopPrandtlIshlinskii(args.pop("thresholds"), **args)


Y = torch.sin(3 * X)


@pytest.mark.parametrize("kwargs, err, match", [
    ({"y": Y[:-1]}, ValueError, r"y must have the shape of x \(1, 20\), got shape \(1, 19\)"),
    ({"y": torch.stack([Y, Y])}, ValueError, "y must have the shape of x"),
    ({"x": torch.tensor([0.0] * 19 + [NAN], dtype=F64)}, ValueError, "x must be finite"),
    ({"y": torch.full((20,), NAN, dtype=F64)}, ValueError, "y must be finite"),
    ({"thresholds": torch.tensor([0.2, 0.0], dtype=F64)}, ValueError,
     "thresholds must be positive"),
    ({"thresholds": torch.tensor([0.2, NAN], dtype=F64)}, ValueError,
     "thresholds must be finite"),
    ({"thresholds": torch.zeros(0, dtype=F64)}, ValueError, "thresholds must have shape"),
    ({"thresholds": [0.2, 0.5]}, TypeError, "thresholds must be a torch.Tensor"),
    ({"segments": 0}, ValueError, "segments must be an int >= 1, got 0"),
    ({"segments": 2.0}, ValueError, "segments must be an int >= 1, got 2.0"),
    ({"segments": True}, ValueError, "segments must be an int >= 1, got True"),
    ({"ridge": -1e-3}, ValueError, "ridge must be >= 0"),
    ({"ridge": NAN}, ValueError, "ridge must be finite"),
    ({"ridge": "0.1"}, TypeError, "ridge must be a real number"),
    ({"warmup": 20}, ValueError, "warmup must leave samples to fit: warmup=20 of 20"),
    ({"warmup": -1}, ValueError, "warmup must be an int >= 0"),
    ({"nonnegative": "no"}, TypeError, "nonnegative must be True or False"),
    ({"center": NAN}, ValueError, "center must be a finite real number"),
    ({"min_linear_weight": -0.1}, ValueError, "min_linear_weight must be >= 0"),
    ({"min_linear_weight": NAN}, ValueError, "min_linear_weight must be finite"),
    ({"min_linear_weight": "1"}, TypeError, "min_linear_weight must be a real number"),
])
def test_bad_fit_input(kwargs, err, match):
    args = {"x": X, "y": Y, "thresholds": T3, **kwargs}
    with pytest.raises(err, match=match):
        fit_stop_pi(args.pop("x"), args.pop("y"), args.pop("thresholds"), **args)


@pytest.mark.parametrize("kwargs, err, match", [
    ({"ridges": []}, ValueError, "ridges must hold at least one value"),
    ({"ridges": 0.1}, TypeError, "ridges must be a sequence"),
    ({"ridges": [0.0, -1.0]}, ValueError, "ridges must be >= 0"),
    ({"validation": 1.5}, ValueError, r"validation must be in \(0, 1\)"),
    ({"validation": 0.0}, ValueError, r"validation must be in \(0, 1\)"),
    ({"warmup": 16}, ValueError, r"warmup \(16\) leaves no training samples"),
    ({"segments": 0}, ValueError, "segments must be an int >= 1"),
    ({"nonnegative": None}, TypeError, "nonnegative must be True or False"),
    ({"y": Y[:5]}, ValueError, "y must have the shape of x"),
    ({"min_linear_weight": -1.0}, ValueError, "min_linear_weight must be >= 0"),
])
def test_bad_select_input(kwargs, err, match):
    args = {"x": X, "y": Y, "thresholds": T3, "ridges": [0.0, 1e-2], **kwargs}
    with pytest.raises(err, match=match):
        select_stop_pi_ridge(args.pop("x"), args.pop("y"), args.pop("thresholds"),
                             args.pop("ridges"), **args)


def snapshot(module: torch.nn.Module) -> dict:
    return {k: v.detach().clone() for k, v in module.state_dict().items()}


def assert_unchanged(module: torch.nn.Module, before: dict) -> None:
    after = module.state_dict()
    assert set(after) == set(before)
    assert all(torch.equal(after[k], v) for k, v in before.items())


@pytest.mark.parametrize("learnable", [False, True])
@pytest.mark.parametrize("key, value, match", [
    ("thresholds", torch.tensor([0.2, 0.0, 1.0], dtype=F64),
     "thresholds must be finite and > 0"),
    ("thresholds", torch.tensor([0.2, -3.0, 1.0], dtype=F64),
     "thresholds must be finite and > 0"),
    ("thresholds", torch.tensor([0.2, NAN, 1.0], dtype=F64),
     "thresholds must be finite and > 0"),
    ("weights", torch.tensor([[1.0, NAN]] * 3, dtype=F64), "weights must be finite"),
    ("weights", torch.tensor([[1.0, math.inf]] * 3, dtype=F64), "weights must be finite"),
])
def test_a_bad_state_dict_is_rejected_and_leaves_the_module_unchanged(key, value, match,
                                                                       learnable):
    m = StopPrandtlIshlinskii(T3, W3, center=0.2, linear_weight=0.5, learnable=learnable)
    before = snapshot(m)
    sd = snapshot(m)
    sd["linear_weight"] = torch.tensor(9.0, dtype=F64)  # a good change, loaded before the bad
    sd["offset"] = torch.tensor(-4.0, dtype=F64)
    sd[key] = value
    with pytest.raises(ValueError, match=match):
        m.load_state_dict(sd)
    assert_unchanged(m, before)
    # a good state dict loads
    sd = snapshot(m)
    sd["weights"] = 2.0 * W3
    sd["thresholds"] = 2.0 * T3
    m.load_state_dict(sd)
    assert torch.equal(m.weights, 2.0 * W3) and torch.equal(m.thresholds, 2.0 * T3)
    assert isinstance(m.weights, torch.nn.Parameter) == learnable


def test_a_bad_state_dict_leaves_a_network_unchanged():
    """Inside an InverseHysteresisNet: the head's new weights come before the operator's bad
    thresholds in the state dict, and nothing of them is loaded."""
    x = walks(2, 100).float()
    op = StopPrandtlIshlinskii([0.2, 0.5, 1.0], torch.ones(3, 2))
    net = torchhys.InverseHysteresisNet([op], hidden=4)
    net.fit_normalization(x, torch.tanh(x))
    before = snapshot(net)
    sd = snapshot(net)
    for k in sd:
        if k.startswith(("hidden", "output", "in_", "out_")):
            sd[k] = sd[k] + 1.0
    name = next(k for k in sd if k.endswith("thresholds"))
    sd[name] = torch.tensor([0.2, -0.5, 1.0])
    with pytest.raises(ValueError, match=r"0\.thresholds must be finite and > 0"):
        net.load_state_dict(sd)
    assert_unchanged(net, before)
    sd[name] = torch.tensor([0.2, 0.5, 1.0])
    sd[name.replace("thresholds", "weights")] = torch.full((3, 2), NAN)
    with pytest.raises(ValueError, match=r"0\.weights must be finite"):
        net.load_state_dict(sd)
    assert_unchanged(net, before)


@pytest.mark.parametrize("partial", [
    {"thresholds": torch.tensor([0.2, -1.0, 1.0], dtype=F64)},
    {"weights": torch.full((3, 2), NAN, dtype=F64)},
    {"center": torch.tensor(NAN, dtype=F64)},
    {"offset": torch.tensor(math.inf, dtype=F64)},
])
def test_a_partial_state_dict_is_checked_too(partial):
    m = StopPrandtlIshlinskii(T3, W3)
    before = snapshot(m)
    try:
        m.load_state_dict(partial, strict=False)
    except ValueError:
        assert_unchanged(m, before)
        return
    pytest.fail(f"loaded {partial} into {snapshot(m)}")


# --- 8. the registry ------------------------------------------------------------------------------


def test_registered_by_name():
    assert OPERATORS["stop_pi"] is StopPrandtlIshlinskii
    W = weights_of(2, 3, seed=14)
    op = make_operator("stop_pi", thresholds=[0.4, 1.1], weights=W, center=0.1,
                       linear_weight=0.3, offset=-0.1)
    assert isinstance(op, StopPrandtlIshlinskii) and op.segments == 3 and op.n_outputs == 1
    assert op.causal
    x = walks()
    ref, _ = model_reference(x.numpy(), [0.4, 1.1], W.numpy(), center=0.1, w0=0.3, offset=-0.1)
    # thresholds from a list: the default dtype (float32), the slopes converted to it
    assert op.thresholds.dtype == op.weights.dtype == torch.get_default_dtype()
    np.testing.assert_allclose(op(x)[0].numpy(), ref, rtol=0, atol=1e-6)
    default = make_operator("stop_pi", thresholds=[0.4, 1.1])  # zero slopes, one segment
    assert default.weights.shape == (2, 1) and not bool(default.weights.any())
    assert default.thresholds.dtype == torch.get_default_dtype()
    net = torchhys.InverseHysteresisNet("stop_pi", hidden=3,
                                        operator_kwargs={"thresholds": [0.4, 1.1]})
    assert isinstance(net.operators[0], StopPrandtlIshlinskii)
    with pytest.raises(ValueError, match="operator 'stop_pi'"):
        make_operator("stop_pi", widths=[0.4, 1.1])
    with pytest.raises(ValueError, match="thresholds must be positive"):
        make_operator("stop_pi", thresholds=[0.4, -1.0])
    assert torchhys.StopPrandtlIshlinskii is StopPrandtlIshlinskii
    assert torchhys.fit_stop_pi is fit_stop_pi
    assert torchhys.select_stop_pi_ridge is select_stop_pi_ridge


# --- segments the fitted samples never enter ----------------------------------------------------


@pytest.mark.parametrize("nonnegative", [True, False])
def test_segments_never_entered_get_zero_slope_and_the_solve_converges(nonnegative):
    """Thresholds up to three times the input's span: the outer segments of the wide stops are
    never entered (their features are constant, collinear with the offset). Their slopes are
    exactly 0 in the fit and in every candidate of the hold-out selection, the active-set
    solve converges without a warning, and the fit still reproduces the data."""
    t = torch.linspace(0, 6 * math.pi, 400, dtype=F64)
    x = (0.6 * torch.sin(t) + 0.3 * torch.sin(2.3 * t))[None]
    y = torch.tanh(2.0 * StopPrandtlIshlinskii(torch.tensor([0.2], dtype=F64),
                                               torch.ones(1, 1, dtype=F64))(x)[0])
    span = float(x.max() - x.min())
    r = torch.linspace(0.05, 3.0, 12, dtype=F64) * span
    K = 6
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        m = fit_stop_pi(x, y, r, segments=K, ridge=0.0, nonnegative=nonnegative)
        select_stop_pi_ridge(x, y, r, [0.0, 1e-8, 1e-4], segments=K, nonnegative=nonnegative)
    u = x[0] - m.center
    feats = stop_segments(u[:, None] - torchhys.functional.backlash(u, 2 * r), r, K)
    never = (feats.amax(0) == feats.amin(0))
    assert int(never.sum()) >= 12  # the test has segments that are never entered
    assert bool((m.weights[never] == 0).all())
    assert float((m(x)[0] - y).square().mean().sqrt()) < 0.25 * float(y.std())


@pytest.mark.parametrize("kwargs, match", [
    ({"center": NAN}, "center must be a finite real number"),
    ({"center": torch.tensor([0.0, 5.0], dtype=F64)},
     r"center must be a finite real number or a one-element real tensor, got a tensor of "
     r"shape \(2,\)"),
    ({"offset": "a"}, "offset must be a finite real number"),
    ({"offset": math.inf}, "offset must be a finite real number"),
    ({"linear_weight": torch.ones(2, dtype=F64)}, "linear_weight must be a finite real"),
    ({"linear_weight": torch.tensor(NAN)}, "linear_weight must be a finite real number"),
])
def test_functional_scalars_are_checked(kwargs, match):
    with pytest.raises(ValueError, match=match):
        stop_pi(X, T3, W3, **kwargs)


def test_functional_scalars_keep_their_gradient():
    c, w0, b = (torch.tensor(v, dtype=F64, requires_grad=True) for v in (0.1, 0.5, -0.2))
    y, _ = stop_pi(X, T3, W3, center=c, linear_weight=w0, offset=b)
    y.sum().backward()
    assert b.grad == X.numel() and w0.grad is not None and c.grad is not None
    torch.testing.assert_close(w0.grad, (X - 0.1).sum())


def test_project_clamps_the_slopes_after_a_step():
    """Projected gradient for a learnable model: after an optimizer step drives a slope
    negative, project_() sets it to 0 and leaves the others, in place."""
    m = StopPrandtlIshlinskii(T3, torch.tensor([[0.01, 1.0]] * 3, dtype=F64), learnable=True)
    opt = torch.optim.SGD(m.parameters(), lr=1.0)
    (m(X)[0].sum()).backward()  # every slope has a positive gradient
    opt.step()
    assert bool((m.weights < 0).any())
    before = m.weights.detach().clone()
    assert m.project_() is m
    torch.testing.assert_close(m.weights.detach(), before.clamp_min(0.0))
    assert isinstance(m.weights, torch.nn.Parameter)


@pytest.mark.parametrize("select", ["stop_pi", "pi", "preisach"])
@pytest.mark.parametrize("validation", [None, 0.0, 1.0, True, "0.25"])
def test_every_penalty_selection_names_a_bad_validation_share(select, validation):
    x = torch.sin(torch.linspace(0, 12, 200, dtype=F64))
    y = torch.tanh(2 * x)
    with pytest.raises(ValueError, match=r"validation must be in \(0, 1\)"):
        if select == "stop_pi":
            select_stop_pi_ridge(x, y, T3, [0.0], validation=validation)
        elif select == "pi":
            select_pi_ridge(x, y, T3, [0.0], validation=validation)
        else:
            torchhys.select_penalty(x, y, [0.0], validation=validation, n=4)


def test_sequence_path_without_gradients_equals_the_one_with_them():
    """Without gradients the characteristic is one clamp into one buffer: the same output to
    the bit as the path autograd records (which the step path shares)."""
    m = stop_model(3, seed=4, learnable=True)
    x = walks(2, 400)
    with torch.no_grad():
        fast = m(x)[0]
    slow = m(x)[0]
    assert slow.requires_grad and not fast.requires_grad
    assert torch.equal(fast, slow.detach())
