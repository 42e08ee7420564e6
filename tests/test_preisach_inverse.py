"""Graded Preisach grids and the exact inverse of a Preisach model: the grid and the graded
linear term against plain formulas and a float64 relay loop, the inverse against a plain loop
that solves each sample by bisection, round trips both ways, chunked calls, the sequence
path's windows against a loop of the per-sample step, the step (eager and scripted),
gradcheck, fitting a graded model, the ``preisach`` family in the inverse direction, bad
input and all-or-nothing loading (export inside a network: tests/test_conformance.py, whose
example is graded)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from _helpers import random_walk, run_split, scripted_run
from _helpers import step_loop as run_steps

from torchhys import Preisach, PreisachInverse, fit_preisach
from torchhys.functional.preisach import graded_input, graded_input_inverse, preisach_grid
from torchhys.functional.preisach_inverse import (
    _inverse_windows,
    preisach_inverse,
    preisach_inverse_constants,
    preisach_inverse_step,
)
from torchhys.operators.preisach import PreisachInverseStep
from torchhys.registry import OPERATORS, make_operator

F64 = torch.float64


def model(n: int = 6, scale: float | None = 0.5, seed: int = 0, lo: float = -2.0,
          hi: float = 3.0) -> Preisach:
    """A random hard-relay model with a positive linear term (invertible), float64."""
    g = torch.Generator().manual_seed(seed)
    m = Preisach(lo, hi, n, scale=scale).double()
    with torch.no_grad():
        w = torch.rand(m.n_relays, generator=g, dtype=F64)
        w[torch.rand(m.n_relays, generator=g) < 0.3] = 0.0  # exact zeros, as NNLS gives
        m.weights.copy_(w)
        m.linear.fill_(0.7)
        m.offset.fill_(-0.4)
    return m


def walks(B: int = 3, T: int = 200) -> torch.Tensor:
    """Random walks (quantized and not) spanning about the grid's range: (B, T)."""
    return torch.stack([0.6 * random_walk(s, T=T, quantize=s % 2 == 0) + 0.5
                        for s in range(B)])


# --- the references: plain float64 loops ----------------------------------------------------


def relays_after(x: float, alpha: np.ndarray, beta: np.ndarray, r: np.ndarray) -> np.ndarray:
    return np.where(x >= alpha, 1.0, np.where(x <= beta, -1.0, r))


def forward_reference(m: Preisach, x: np.ndarray, r0: np.ndarray) -> np.ndarray:
    """The model sample by sample: relays, then ``offset + linear g(x) + w @ r`` with
    g written out (``c + s asinh((x - c) / s)``)."""
    a, b = m.alpha.numpy(), m.beta.numpy()
    w, lin, off = m.weights.detach().numpy(), m.linear.item(), m.offset.item()
    c = 0.5 * (m.lo + m.hi)
    s = m.scale
    r, out = r0.copy(), []
    for v in x:
        r = relays_after(float(v), a, b, r)
        g = v if s is None else c + s * math.asinh((v - c) / s)
        out.append(off + lin * g + w @ r)
    return np.array(out)


def inverse_reference(m: Preisach, y: np.ndarray, r0: np.ndarray) -> np.ndarray:
    """Per sample: the least x whose output (from the relays before it) reaches y, by 200
    bisection halvings on a bracket grown until it holds it, or the threshold that the
    bisection ends at (a y inside a jump); then the relays switch."""
    a, b = m.alpha.numpy(), m.beta.numpy()
    levels = np.unique(np.concatenate([a, b]))
    w, lin, off = m.weights.detach().numpy(), m.linear.item(), m.offset.item()
    c, s = 0.5 * (m.lo + m.hi), m.scale

    def out(v: float, r: np.ndarray) -> float:
        g = v if s is None else c + s * math.asinh((v - c) / s)
        return off + lin * g + w @ relays_after(v, a, b, r)

    r, xs = r0.copy(), []
    for target in y:
        lo, hi = -1.0, 1.0
        while out(lo, r) >= target:
            lo *= 2.0
        while out(hi, r) < target:
            hi *= 2.0
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if out(mid, r) < target else (lo, mid)
        near = levels[np.abs(levels - hi) < 1e-9]
        x = float(near[0]) if near.size else hi  # inside a jump: the threshold itself
        xs.append(x)
        r = relays_after(x, a, b, r)
    return np.array(xs)


# --- 1. the graded grid and the graded linear term -------------------------------------------


def test_graded_grid_levels_are_even_in_the_graded_variable():
    lo, hi, n, s = -1.0, 5.0, 7, 0.4
    alpha, beta = preisach_grid(lo, hi, n, scale=s, dtype=F64)
    levels = alpha.unique()
    c = 0.5 * (lo + hi)
    g = c + s * np.arcsinh((levels.numpy() - c) / s)
    glo, ghi = c + s * np.arcsinh((lo - c) / s), c + s * np.arcsinh((hi - c) / s)
    np.testing.assert_allclose(g, glo + (ghi - glo) * (np.arange(n) + 0.5) / n, atol=1e-12)
    assert torch.equal(beta.unique(), levels)
    # symmetric about the center, denser near it
    np.testing.assert_allclose(levels.numpy() + levels.flip(0).numpy(), 2 * c, atol=1e-12)
    gaps = levels.diff()
    assert float(gaps[n // 2 - 1]) < float(gaps[0])


def test_even_grid_unchanged_and_graded_input_round_trips():
    alpha, beta = preisach_grid(-1.0, 2.0, 5, dtype=F64)
    levels = -1.0 + 3.0 * (torch.arange(5, dtype=F64) + 0.5) / 5
    assert torch.equal(alpha.unique(), levels)
    x = torch.linspace(-30, 30, 101, dtype=F64)
    assert torch.equal(graded_input(x, 0.3, None), x)
    torch.testing.assert_close(graded_input_inverse(graded_input(x, 0.3, 2.0), 0.3, 2.0), x,
                               rtol=1e-13, atol=1e-12)


@pytest.mark.parametrize("scale", [None, 0.5])
def test_graded_model_against_a_plain_loop(scale):
    m = model(scale=scale, seed=1)
    x = walks(3, 150)
    y, last = m(x)
    r0 = m.initial_relays.numpy()
    for b in range(3):
        np.testing.assert_allclose(y[b].detach().numpy(),
                                   forward_reference(m, x[b].numpy(), r0), atol=1e-12)
    step_out, state = scripted_run(m.streaming_step(F64), x)
    torch.testing.assert_close(step_out[..., 0], y.detach(), rtol=0, atol=1e-12)
    assert torch.equal(state[0], last)


def test_bad_scale_is_refused():
    for bad in (0.0, -1.0, math.inf, math.nan, "1", True):
        with pytest.raises(ValueError, match="scale"):
            Preisach(-1.0, 1.0, 4, scale=bad)


# --- 2. the inverse against the plain loop, and round trips ------------------------------------


@pytest.mark.parametrize("scale", [None, 0.5])
def test_inverse_against_bisection(scale):
    m = model(scale=scale, seed=2)
    g = torch.Generator().manual_seed(3)
    y = (torch.randn(2, 120, generator=g, dtype=F64).cumsum(1) * 0.5)
    x, last = m.inverse()(y)
    r0 = m.initial_relays.numpy()
    for b in range(2):
        np.testing.assert_allclose(x[b].numpy(), inverse_reference(m, y[b].numpy(), r0),
                                   atol=1e-9)
    # the relays it returns are those the model holds after the solved input
    assert torch.equal(last, m(x)[1])


@pytest.mark.parametrize("scale", [None, 0.5])
def test_round_trips(scale):
    m = model(scale=scale, seed=4)
    x = walks(3, 200)
    y, r = m(x)
    xi, ri = m.inverse()(y.detach())
    torch.testing.assert_close(xi, x, rtol=0, atol=1e-10)
    assert torch.equal(ri, r)
    # the other way: the model reproduces every target it can reach; the others lie inside
    # a jump, where the inverse returns that threshold
    g = torch.Generator().manual_seed(5)
    t = torch.randn(3, 200, generator=g, dtype=F64).cumsum(1) * 0.3
    xi, _ = m.inverse()(t)
    back, _ = m(xi)
    at_level = torch.isin(xi, m.alpha.unique())
    assert at_level.float().mean() < 0.9
    torch.testing.assert_close(back.detach()[~at_level], t[~at_level], rtol=0, atol=1e-10)


def test_inverse_with_a_given_state_and_chunked_calls():
    m = model(seed=6)
    inv = m.inverse()
    x = walks(2, 160)
    y, _ = m(x)
    y = y.detach()
    _, r_mid = m(x[:, :70])
    xi, _ = inv(y[:, 70:], r_mid)
    torch.testing.assert_close(xi, x[:, 70:], rtol=0, atol=1e-10)
    full, last = inv(y)
    joined, state = run_split(inv, y, [1, 50, 9, 100])
    # the same relays at every sample; x to the last bit or two of the graded map's sinh
    # (vectorized and scalar evaluation round differently, and the chunks cut the windows
    # of the sequence path elsewhere; the compiled loop forms its sums afresh at each call)
    assert torch.equal(state, last)
    torch.testing.assert_close(joined, full, rtol=0, atol=1e-14)


def step_loop(y: torch.Tensor, r: torch.Tensor, m: Preisach) -> tuple[torch.Tensor, torch.Tensor]:
    """The sequence path's reference: :func:`preisach_inverse_step` sample by sample."""
    linear = m.linear.detach().reshape(())
    tables = preisach_inverse_constants(m.alpha, m.beta, m.weights.detach(), linear,
                                        m.offset.detach().reshape(()), m.center, m.scale)
    xs = []
    for t in range(y.shape[1]):
        x, r = preisach_inverse_step(y[:, t:t + 1], r, m.alpha, m.beta, *tables, linear,
                                     m.center, m.scale)
        xs.append(x)
    return torch.cat(xs, 1), r


@pytest.mark.parametrize("scale", [None, 0.5])
@pytest.mark.parametrize("windows", [(1, 1), (1, 3), (8, 4096), (64, 64)])
def test_windows_equal_a_loop_of_steps(scale, windows):
    """Windows of any sizes give the loop's relays at every sample and its inputs (to the
    bit on an even grid): targets from the model (on its branches), noisy ones and ones
    inside the jumps; rows that switch at different samples; a diagonal-only density (relays
    that switch on both sides of one threshold); a state given."""
    g = torch.Generator().manual_seed(11)
    heavy = model(n=5, scale=scale, seed=12)
    with torch.no_grad():
        heavy.weights.mul_(20.0)  # jumps far above the linear term: many targets inside them
    diag = model(n=6, scale=scale, seed=13)
    with torch.no_grad():
        diag.weights.mul_((diag.alpha == diag.beta).to(F64))
    for m in (model(scale=scale, seed=10), heavy, diag):
        y = m(walks(3, 300))[0].detach()
        y = torch.cat([y, y + 0.05 * torch.randn(y.shape, generator=g, dtype=F64)])
        r0 = torch.where(torch.rand(6, m.n_relays, generator=g) < 0.5, 1.0, -1.0).to(F64)
        linear = m.linear.detach().reshape(())
        tables = preisach_inverse_constants(m.alpha, m.beta, m.weights.detach(), linear,
                                            m.offset.detach().reshape(()), m.center, m.scale)
        x, r = _inverse_windows(y, r0, m.alpha, m.beta, tables, linear, m.center, m.scale,
                                *windows)
        ref, r_ref = step_loop(y, r0, m)
        assert torch.equal(r, r_ref)
        if scale is None:
            assert torch.equal(x, ref)
        else:
            torch.testing.assert_close(x, ref, rtol=0, atol=4e-15)
        # the relays at every sample: those the model holds after the solved inputs
        for t in (1, 57, 299):
            _, r_t = m(x[:, :t], r0)
            _, r_ref_t = step_loop(y[:, :t], r0, m)
            assert torch.equal(r_t, r_ref_t)


@pytest.mark.parametrize("dtype,atol", [(F64, 1e-12), (torch.float32, 1e-4)])
def test_step_eager_and_scripted_equal_the_sequence_path(dtype, atol):
    m = model(seed=7)
    inv = m.inverse().to(dtype)
    y = m(walks(2, 120))[0].detach().to(dtype)
    seq, last = inv(y)
    step = inv.streaming_step(dtype)
    assert isinstance(step, PreisachInverseStep)
    out, state = scripted_run(step, y)
    torch.testing.assert_close(out[..., 0], seq, rtol=0, atol=atol)
    if dtype == F64:
        assert torch.equal(state[0], last)


@pytest.mark.parametrize("scale", [None, 0.5])
def test_step_through_torch_export_equals_the_sequence_path(scale):
    m = model(scale=scale, seed=14)
    inv = m.inverse()
    y = m(walks(2, 120))[0].detach()
    seq, last = inv(y)
    step = inv.streaming_step(F64)
    state = step.initial_state(y[:, :1])
    exported = torch.export.export(step, (y[:, :1], state)).module()
    with torch.no_grad():
        x, state = run_steps(exported, y, state)
    torch.testing.assert_close(x[..., 0], seq, rtol=0, atol=1e-12)
    assert torch.equal(state[0], last)


def test_gradcheck():
    m = model(n=4, seed=8)
    a, b, r0 = m.alpha, m.beta, m.initial_relays
    y = m(walks(1, 40)[0])[0].detach() + 0.01  # off the thresholds: inside segments
    w = (m.weights.detach() + 0.1).requires_grad_()  # off 0: finite differences stay >= 0
    lin = torch.tensor(0.7, dtype=F64, requires_grad=True)
    off = torch.tensor(-0.4, dtype=F64, requires_grad=True)
    yy = y.clone().requires_grad_()

    def f(yy, w, lin, off):
        return preisach_inverse(yy, w, a, b, offset=off, linear=lin, state=r0,
                                center=m.center, scale=m.scale)[0]

    assert torch.autograd.gradcheck(f, (yy, w, lin, off))


# --- 3. fitting a graded model, and the family ------------------------------------------------


def magnetic_plant(scale: float) -> tuple[Preisach, torch.Tensor, torch.Tensor]:
    """A graded Preisach plant H -> B (density peaked near the origin) on a grid over
    [-1.5, 1.5], and three loops of its field of amplitudes 0.1, 0.4 and 1.5, three periods
    each: (plant, H, B)."""
    plant = Preisach(-1.5, 1.5, 24, scale=scale).double()
    with torch.no_grad():
        a, b = plant.alpha, plant.beta
        plant.weights.copy_(torch.exp(-((a - b) / 0.3) ** 2 - ((a + b) / 0.6) ** 2))
        plant.linear.fill_(0.5)
        plant.offset.zero_()
    t = torch.arange(3 * 96, dtype=F64) / 96
    H = torch.stack([amp * torch.cos(2 * math.pi * t) for amp in (0.1, 0.4, 1.5)])
    return plant, H, plant(H)[0].detach()


def test_fit_of_a_graded_plant_is_exact_and_beats_the_even_grid():
    plant, H, B = magnetic_plant(0.15)
    m = fit_preisach(H, B, n=24, scale=0.15, warmup=96)
    rmse = float((m(H)[0] - B)[:, 96:].square().mean().sqrt())
    even = fit_preisach(H, B, n=24, warmup=96)
    rmse_even = float((even(H)[0] - B)[:, 96:].square().mean().sqrt())
    assert rmse < 1e-8 < rmse_even
    # and its inverse, the compensator, returns the field from the flux density
    torch.testing.assert_close(m.inverse()(B)[0][:, 96:], H[:, 96:], rtol=0, atol=1e-6)


def test_preisach_family_in_the_inverse_direction():
    from torchhys.identification.preisach import _preisach

    plant, H, B = magnetic_plant(0.15)  # in the family: grid over H's range, 0.1 of 1.5
    placeholder, fit = _preisach(
        {"fit": "preisach", "n": 24, "grading": 0.1, "direction": "inverse"})
    assert isinstance(placeholder, PreisachInverse)
    op = fit(B, H, 96)  # input B, target H: the compensator
    assert isinstance(op, PreisachInverse)
    t = (H - H[:, 96:].mean()) / H[:, 96:].std()
    out = op(B)[0][:, 96:]
    sign = 1.0 if float((out * t[:, 96:]).sum()) > 0 else -1.0
    assert float((sign * out - t[:, 96:]).square().mean().sqrt()) < 1e-6
    # the checkpoint round trip of torchhys fit: the placeholder loads the fitted operator
    placeholder.double().load_state_dict(op.state_dict())
    torch.testing.assert_close(placeholder(B)[0], op(B)[0], rtol=0, atol=0)
    for bad, match in (({"grading": 0}, "grading"), ({"direction": "up"}, "direction"),
                       ({"levels": 3}, "unknown option")):
        with pytest.raises(ValueError, match=match):
            _preisach({"fit": "preisach", **bad})


# --- 4. bad input, loading, the registry --------------------------------------------------------


def test_models_without_an_inverse_are_refused():
    m = model(seed=10)
    with torch.no_grad():
        m.linear.fill_(0.0)
    with pytest.raises(ValueError, match="linear must be one finite number > 0"):
        m.inverse()
    smooth = Preisach(-1.0, 1.0, 4, smooth=0.1)
    with pytest.raises(ValueError, match="hard relays"):
        smooth.inverse()
    with pytest.raises(TypeError, match="must be a Preisach"):
        PreisachInverse.from_model(torch.nn.Linear(1, 1))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="weights must be finite and non-negative"):
        preisach_inverse(torch.zeros(5, dtype=F64), -m.weights.detach() - 1, m.alpha, m.beta,
                         offset=torch.tensor(0.0), linear=torch.tensor(1.0))


def test_loading_is_checked_all_or_nothing():
    inv = model(seed=11).inverse()
    target = PreisachInverse(6).double()
    target.load_state_dict(inv.state_dict())
    y = walks(1, 50)
    torch.testing.assert_close(target(y)[0], inv(y)[0], rtol=0, atol=0)
    assert target.scale == inv.scale and target.center == inv.center
    before = {k: v.clone() for k, v in target.state_dict().items()}
    for key, value, match in (
            ("linear", torch.tensor(-1.0, dtype=F64), "linear"),
            ("weights", -inv.weights, "weights"),
            ("alpha", inv.beta - 1.0, "alpha"),
            ("initial_relays", torch.zeros_like(inv.initial_relays), "initial_relays"),
            ("grading", torch.tensor([0.0, -1.0], dtype=F64), "grading"),
            ("offset", torch.tensor(math.nan, dtype=F64), "offset")):
        bad = dict(inv.state_dict())
        bad[key] = value
        with pytest.raises(ValueError, match=match):
            target.load_state_dict(bad)
        for k, v in target.state_dict().items():
            assert torch.equal(v, before[k]), k
    with pytest.raises(ValueError, match="linear"):  # a partial dict is checked too
        target.load_state_dict({"linear": torch.tensor(0.0, dtype=F64)}, strict=False)


def test_graded_model_state_dict_round_trip():
    m = model(seed=12, scale=0.3)
    plain = Preisach(0.0, 1.0, 6).double()
    plain.load_state_dict(m.state_dict())
    x = walks(2, 80)
    torch.testing.assert_close(plain(x)[0], m(x)[0], rtol=0, atol=0)
    assert plain.scale == pytest.approx(0.3) and plain.lo == pytest.approx(m.lo)
    assert plain.hi == pytest.approx(m.hi)
    even = model(seed=12, scale=None)
    loaded = Preisach(0.0, 1.0, 6).double()
    loaded.load_state_dict(even.state_dict())
    assert loaded.scale is None
    torch.testing.assert_close(loaded(x)[0], even(x)[0], rtol=0, atol=0)
    with pytest.raises(RuntimeError, match="grading"):  # a state dict without the grading
        loaded.load_state_dict({k: v for k, v in even.state_dict().items() if k != "grading"})
    with pytest.raises(ValueError, match="grading"):
        loaded.load_state_dict({**even.state_dict(), "grading": torch.tensor([0.0, math.inf])})


def test_registry():
    assert OPERATORS["preisach_inverse"] is PreisachInverse
    assert isinstance(make_operator("preisach_inverse", n=3), PreisachInverse)


@pytest.mark.parametrize("scale", [None, 0.5])
@pytest.mark.parametrize("dtype", [F64, torch.float32])
def test_compiled_loop_equals_the_windows(scale, dtype):
    """The compiled sequence loop (no gradients, CPU) gives the windowed torch path's relays
    and inputs (which are the step loop's: test_windows_equal_a_loop_of_steps) up to
    rounding, on that test's targets, and is what preisach_inverse returns without
    gradients. In float32 a target within rounding of a jump may land on its other side:
    those samples (and the switches they cause) are counted, not compared."""
    from torchhys.functional._preisach_kernel import inverse_kernel, inverse_kernel_available

    g = torch.Generator().manual_seed(11)
    heavy = model(n=5, scale=scale, seed=12)
    with torch.no_grad():
        heavy.weights.mul_(20.0)
    for m in (model(scale=scale, seed=10), heavy, model(n=12, scale=scale, seed=14)):
        y = m(walks(3, 300))[0].detach()
        y = torch.cat([y, y + 0.05 * torch.randn(y.shape, generator=g, dtype=F64)]).to(dtype)
        r0 = torch.where(torch.rand(6, m.n_relays, generator=g) < 0.5, 1.0, -1.0).to(dtype)
        m = m.to(dtype)
        linear = m.linear.detach().reshape(())
        tables = preisach_inverse_constants(m.alpha, m.beta, m.weights.detach(), linear,
                                            m.offset.detach().reshape(()), m.center, m.scale)
        assert not inverse_kernel_available(y, m.weights)  # a gradient: the torch path
        with torch.no_grad():
            assert inverse_kernel_available(y, m.weights)
            x, r = inverse_kernel(y, r0, m.alpha, m.beta, tables, linear, m.center, m.scale)
            ref, r_ref = _inverse_windows(y, r0, m.alpha, m.beta, tables, linear, m.center,
                                          m.scale)
            assert torch.equal(m.inverse()(y, r0)[0], x)
        # the solution divides a difference of sums of up to 20x the target's size
        near = (x - ref).abs() <= (1e-12 if dtype == F64 else 1e-4) * (1.0 + ref.abs())
        if dtype == F64:
            assert torch.equal(r, r_ref) and bool(near.all())
        else:
            assert float((r != r_ref).double().mean()) < 0.02
            assert float(near.double().mean()) > 0.9
