"""Generalized Prandtl-Ishlinskii model: reference loop, reduction to the PI model, the
per-sample step (eager, TorchScript, float32), autograd, fitting an asymmetric saturating
loop, bad input (chunked calls, streaming inside a network: tests/test_conformance.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from _gpi_helpers import F64, WIDTHS, model, walks
from _helpers import (
    play_reference,
    scripted_run,
    smooth_input,
    step_loop,
)

from torchhys import Backlash, InverseHysteresisNet, PrandtlIshlinskii
from torchhys.functional import prandtl_ishlinskii
from torchhys.identification.fitting import fit_full_batch, fit_prandtl_ishlinskii, play_width_grid
from torchhys.identification.generalized_pi import fit_generalized_pi
from torchhys.operators.generalized_pi import GeneralizedPrandtlIshlinskii
from torchhys.registry import OPERATORS, make_operator

ROOT = Path(__file__).resolve().parents[1]


def test_matches_a_plain_loop():
    m = model()
    x = walks()
    y, state = m(x)
    plays = play_reference(x.numpy(), np.array(WIDTHS))
    p = 0.4 * x.numpy() + plays @ np.array([0.3, 0.8, 0.05, 0.5, 0.2])
    units = np.tanh(np.array([0.7, 2.0, 1.2]) * (p[..., None] - np.array([-1.0, 0.2, 1.5])))
    ref = 0.3 * p + units @ np.array([0.5, 0.3, 0.9]) - 0.2
    np.testing.assert_allclose(y.detach().numpy(), ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(state.detach().numpy(), plays[:, -1], rtol=0, atol=0)


def test_identity_g_is_the_pi_model():
    weights = torch.tensor([0.3, 0.8, 0.1, 0.5, 0.2], dtype=F64)
    gpi = GeneralizedPrandtlIshlinskii(torch.tensor(WIDTHS, dtype=F64), weights,
                                       linear_weight=0.4, centers=[])  # g(v) = 1 v + 0
    x = walks()
    y, state = gpi(x)
    pi_part = gpi.prandtl_ishlinskii()
    h, pi_state = pi_part(x)
    assert torch.equal(y, h) and torch.equal(state, pi_state)  # bit for bit
    torch.testing.assert_close(pi_part.weights, weights, rtol=1e-15, atol=0)
    assert float(pi_part.linear_weight) == pytest.approx(0.4, rel=1e-15)
    ref = prandtl_ishlinskii(x, torch.tensor(WIDTHS, dtype=F64), weights, linear_weight=0.4)
    torch.testing.assert_close(y, ref, rtol=1e-15, atol=1e-14)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_step_eager_and_scripted_equal_sequence(dtype):
    m = model(dtype)
    x = walks().to(dtype)
    with torch.no_grad():
        y, final = m(x)
    step = m.streaming_step(dtype)
    assert step.n_outputs == 1 and [b.size for b in step.state_spec] == [5]
    tol = 1e-13 if dtype == torch.float64 else 1e-5
    for f, state in (step_loop(step, x, step.initial_state(x[:, :1])), scripted_run(step, x)):
        assert f.shape == (3, 200, 1) and f.dtype == dtype
        torch.testing.assert_close(f[..., 0], y, rtol=0, atol=tol)
        torch.testing.assert_close(state[0], final, rtol=0, atol=0)


def rough_input(T: int = 25) -> torch.Tensor:
    """A random walk without repeated samples (a repeat sits on a bound: not differentiable)."""
    return torch.randn(2, T, dtype=F64, generator=torch.Generator().manual_seed(3)).cumsum(1)


@pytest.mark.parametrize("x", [smooth_input(30), rough_input()])
def test_gradcheck_forward(x):
    m = model(learnable_widths=True, weights=[0.3, 0.8, 0.1, 0.5, 0.2])
    names = [n for n, _ in m.named_parameters()]
    assert set(names) == {"raw_widths", "raw_weights", "log_linear_weight", "log_gain",
                          "raw_unit_weights", "centers", "log_slopes", "offset"}
    params = tuple(p.detach().clone().requires_grad_(True) for p in m.parameters())

    def f(x, *ps):
        return torch.func.functional_call(m, dict(zip(names, ps, strict=True)), (x,))[0]

    torch.autograd.gradcheck(f, (x.clone().requires_grad_(True), *params))


def asymmetric_plant(x: torch.Tensor) -> torch.Tensor:
    """A saturating, asymmetric loop: tanh of a PI output with an offset."""
    widths = torch.linspace(0.2, 2.0, 6, dtype=F64)
    weights = torch.tensor([0.5, 0.3, 0.4, 0.2, 0.3, 0.2], dtype=F64)
    return torch.tanh(0.8 * prandtl_ishlinskii(x, widths, weights, linear_weight=0.3) + 0.4)


def multisine(T: int, seed: int) -> torch.Tensor:
    t = torch.linspace(0, 1, T, dtype=F64)
    g = torch.Generator().manual_seed(seed)
    f, phase = torch.rand(4, generator=g, dtype=F64) * 6 + 1, torch.rand(4, generator=g) * 6
    amp = torch.rand(4, generator=g, dtype=F64) + 0.3
    x = (amp[:, None] * torch.sin(2 * math.pi * f[:, None] * t + phase[:, None])).sum(0)
    return (2.0 * x / x.abs().max())[None]


def test_fits_a_saturating_asymmetric_loop_better_than_pi():
    n_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        x, x_test = multisine(1500, 0), multisine(1500, 1)
        y, y_test = asymmetric_plant(x), asymmetric_plant(x_test)
        widths = play_width_grid(x, 12, power=1.0)
        gpi = fit_generalized_pi(x, y, widths, units=4)
    finally:
        torch.set_num_threads(n_threads)
    with torch.no_grad():
        rms = {name: float((m(x_test)[0] - y_test).square().mean().sqrt()) for name, m in
               (("gpi", gpi), ("pi", fit_prandtl_ishlinskii(x, y, widths)),
                ("pi>=0", fit_prandtl_ishlinskii(x, y, widths, nonnegative=True)))}
        h, _ = gpi(x_test)
    assert rms["gpi"] < 0.02 and rms["gpi"] < rms["pi"] / 20 and rms["gpi"] < rms["pi>=0"] / 20
    moving = x_test.diff() != 0  # strictly increasing along every branch
    assert bool((torch.sign(h.diff()) == torch.sign(x_test.diff()))[moving].all())


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_fit_is_the_same_in_any_units_of_y(scale):
    """y in micro- or mega-units fits as well as in its own units (the fit sees y over its
    standard deviation); fitted in the units of y, L-BFGS's absolute tolerances stopped it
    at once on micro-units (0.39 relative RMSE) and the loss turned NaN on mega-units."""
    x = multisine(1500, 0)
    y = asymmetric_plant(x)
    widths = play_width_grid(x, 12, power=1.0)
    n_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        gpi = fit_generalized_pi(x, scale * y, widths, units=4)
    finally:
        torch.set_num_threads(n_threads)
    with torch.no_grad():
        relative = float((gpi(x)[0] / scale - y).square().mean().sqrt())
    assert relative < 0.02, relative  # measured: 0.006 (units of y), 0.007, 0.009


@pytest.mark.parametrize("epochs", [300, 1000])
def test_fit_holds_its_scale_on_measured_loops(epochs):
    """The field from the flux density of two measured steel loops (the forward fit of the
    inverse route): without w0 held and the log-gain and log-slopes anchored, the fit drifts
    along the model's scale symmetry until w0 underflows (no inverse, 300 epochs) or the loss
    turns NaN (1000 epochs)."""
    data = np.genfromtxt(ROOT / "examples/data/real/jamodel_bh_loops.csv", delimiter=",",
                         names=True, dtype=None, encoding="utf-8")
    field, flux = (torch.stack([torch.as_tensor(np.tile(data[c][data["recording"] == r], 2))
                                for r in (0, 2)]) for c in ("H_Apm", "B_T"))
    u, out = ((v - v.mean()) / v.std() for v in (field, flux))
    warmup = u.shape[-1] // 2
    n_threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        gpi = fit_generalized_pi(u, out, play_width_grid(u, 10, power=2.0), units=4, ridge=0.1,
                                 lbfgs_epochs=epochs, warmup=warmup)
    finally:
        torch.set_num_threads(n_threads)
    _, _, w0, gain, _, _, slopes, _ = (t.detach() for t in gpi.parameters_effective())
    initial = fit_prandtl_ishlinskii(u, out, play_width_grid(u, 10, power=2.0), ridge=0.1,
                                     nonnegative=True, warmup=warmup)
    # held at the initial fit's (of out over its std)
    assert float(w0) == pytest.approx(float(initial.linear_weight / out[:, warmup:].std()),
                                      rel=1e-12)
    assert 1e-4 < float(gain) < 1e2 and bool(((slopes > 1e-3) & (slopes < 1e3)).all())
    with torch.no_grad():
        fit = float((gpi(u)[0] - out)[:, warmup:].square().mean().sqrt())
        back = float((gpi.inverse()(out)[0] - u)[:, warmup:].square().mean().sqrt())
    # measured (300, 1000 epochs): fit 0.029, 0.018; inverse 0.062, 0.028 (standardized)
    assert fit < 0.04 and back < 0.1


def test_fit_full_batch_trains_an_operator_with_adam():
    x = multisine(400, 2)
    y = asymmetric_plant(x)
    m = GeneralizedPrandtlIshlinskii(play_width_grid(x, 6, power=1.0), linear_weight=0.2)
    with torch.no_grad():
        before = float((m(x)[0] - y).square().mean())
    result = fit_full_batch(m, x, y, adam_epochs=100, lbfgs_epochs=0, lr=0.05)
    assert result.epochs == 100 and result.mse < before / 50
    assert all(bool((t > 0).all()) for t in m.parameters_effective()[1:5])  # still positive
    with pytest.raises(ValueError, match="causal operator with one output.*n_outputs=2"):
        fit_full_batch(Backlash([0.5, 1.0]).double(), x, y, adam_epochs=1)
    with pytest.raises(ValueError, match="no trainable parameters"):
        fit_full_batch(PrandtlIshlinskii([0.5]).double(), x, y, adam_epochs=1)


def test_registered_by_name():
    assert OPERATORS["generalized_pi"] is GeneralizedPrandtlIshlinskii
    op = make_operator("generalized_pi", widths=[0.5, 1.0], centers=[0.0])
    assert op.n_outputs == 1 and op.centers.shape == (1,)
    net = InverseHysteresisNet("generalized_pi", hidden=3,
                               operator_kwargs={"widths": [0.5, 1.0]})
    assert net.hidden.in_features == 2


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"weights": [0.3, -0.1, 0.0, 0.5, 0.2]}, "weights must be >= 0"),
        ({"weights": [0.3, 0.1]}, r"weights must have shape \(5,\)"),
        ({"weights": [0.3, math.nan, 0.0, 0.5, 0.2]}, "weights must be finite"),
        ({"linear_weight": 0.0}, "linear_weight must be > 0"),
        ({"linear_weight": math.inf}, "linear_weight must be a finite number"),
        ({"gain": -1.0}, "gain must be > 0"),
        ({"offset": "1"}, "offset must be a finite number"),
        ({"slopes": [1.0, 0.0, 1.0]}, "slopes must be > 0"),
        ({"unit_weights": [0.5, -0.3, 0.9]}, "unit_weights must be >= 0"),
        ({"unit_weights": [0.5]}, r"unit_weights must have shape \(3,\)"),
        ({"centers": [[0.0]]}, r"centers must have shape \(K,\)"),
    ],
)
def test_bad_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        model(**kwargs)
    with pytest.raises(TypeError, match="learnable_widths must be True or False, got str"):
        model(learnable_widths="no")


def test_bad_fit_input():
    x = multisine(100, 3)
    widths = play_width_grid(x, 4)
    with pytest.raises(ValueError, match="units must be an int >= 0"):
        fit_generalized_pi(x, x, widths, units=-1)
    with pytest.raises(ValueError, match="y does not increase with x"):
        fit_generalized_pi(x, -x, widths)
    with pytest.raises(ValueError, match="y must have the shape of x"):
        fit_generalized_pi(x, x[:, :-1], widths)
    with pytest.raises(TypeError, match="x must have a floating-point dtype"):
        fit_generalized_pi(x.long(), x, widths)
    with pytest.raises(ValueError, match="widths must be non-negative"):
        fit_generalized_pi(x, x, -widths)
    with pytest.raises(ValueError, match="anchor must be >= 0"):
        fit_generalized_pi(x, x, widths, anchor=-1e-6)
    with pytest.raises(ValueError, match="anchor must be finite"):
        fit_generalized_pi(x, x, widths, anchor=math.nan)
    with pytest.raises(ValueError, match="y must vary over the scored samples"):
        fit_generalized_pi(x, torch.ones_like(x), widths)
    for bad in (-1, True, 2.5):
        with pytest.raises(ValueError, match=f"lbfgs_epochs must be an int >= 0, got {bad!r}"):
            fit_generalized_pi(x, x, widths, lbfgs_epochs=bad)
    with pytest.raises(ValueError, match="adam_epochs must be an int >= 0, got 1.5"):
        fit_generalized_pi(x, x, widths, adam_epochs=1.5)


def test_fit_full_batch_adds_a_penalty_and_reports_the_error_without_it():
    x = multisine(400, 2)
    y = asymmetric_plant(x)
    m = GeneralizedPrandtlIshlinskii(play_width_grid(x, 6, power=1.0), linear_weight=0.2)
    result = fit_full_batch(m, x, y, adam_epochs=0, lbfgs_epochs=50,
                            penalty=lambda: 1e4 * (m.offset - 3.0).square())
    with torch.no_grad():
        mse = float((m(x)[0] - y).square().mean())
    assert float(m.offset) == pytest.approx(3.0, abs=0.01)  # the penalty pulls it there
    assert result.mse == pytest.approx(mse, rel=1e-12)


def test_exported_step_equals_sequence():
    m = model(torch.float32)
    x = walks()[:2, :60].float()
    step = m.streaming_step(torch.float32)
    state = step.initial_state(x[:, :1])
    exported = torch.export.export(step, (x[:, :1], state)).module()
    with torch.no_grad():
        y, final = m(x)
        outs = []
        for xt in x.unbind(1):
            f, state = exported(xt.unsqueeze(1), state)
            outs.append(f)
    torch.testing.assert_close(torch.stack(outs, 1)[..., 0], y, rtol=0, atol=1e-5)
    torch.testing.assert_close(state[0], final, rtol=0, atol=0)


def test_fit_leaves_the_warmup_samples_out():
    """Targets in the warm-up only run the plays: corrupting them changes nothing, and the
    fit scored without them is the fit of the clean data."""
    x = multisine(600, 4)
    y = asymmetric_plant(x)
    bad = y.clone()
    bad[..., :100] = 50.0 * torch.randn(bad[..., :100].shape, dtype=F64,
                                        generator=torch.Generator().manual_seed(0))
    widths = play_width_grid(x, 6, power=1.0)
    clean = fit_generalized_pi(x, y, widths, units=2, lbfgs_epochs=40, warmup=100)
    robust = fit_generalized_pi(x, bad, widths, units=2, lbfgs_epochs=40, warmup=100)
    for a, b in zip(clean.parameters_effective(), robust.parameters_effective(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    naive = fit_generalized_pi(x, bad, widths, units=2, lbfgs_epochs=40)
    with torch.no_grad():
        def scored(m):
            return float((m(x)[0] - y)[..., 100:].square().mean().sqrt())
        assert scored(robust) < scored(naive) / 5
    with pytest.raises(ValueError, match="warmup must leave samples to fit"):
        fit_full_batch(clean, x, y, lbfgs_epochs=1, warmup=x.shape[-1])
    with pytest.raises(ValueError, match="warmup must be an int >= 0"):
        fit_full_batch(clean, x, y, lbfgs_epochs=1, warmup=-1)


@pytest.mark.parametrize("learnable", [False, True])
def test_predictor_equals_forward_with_its_gradient(learnable):
    """The fitting closure (plays once, matrix products) equals the sequence path up to
    rounding, and so does its gradient with respect to every parameter."""
    m = model(learnable_widths=learnable)
    x = walks(300)
    predict = m.predictor(x)
    out = predict()
    ref = m(x)[0]
    torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)
    grads = torch.autograd.grad(out.square().sum(), list(m.parameters()))
    refs = torch.autograd.grad(ref.square().sum(), list(m.parameters()))
    for g, r in zip(grads, refs, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-10)
    with torch.no_grad():  # the closure reads the current parameters
        m.offset.add_(1.0)
    torch.testing.assert_close(predict(), ref.detach() + 1.0, rtol=0, atol=1e-12)


@pytest.mark.parametrize("learnable", [False, True])
def test_mse_closure_equals_autograd_through_forward(learnable, monkeypatch):
    """The fitting loss (plays once, the masked rows, the analytic gradient of
    ``monotone_mse``, here from any number of rows) equals the masked MSE of the sequence
    path, and its gradient that of autograd through it, for every parameter."""
    monkeypatch.setattr("torchhys.operators.generalized_pi.ANALYTIC_ROWS", 0)
    m = model(learnable_widths=learnable)
    x = walks(300)
    y = torch.sin(3.0 * x) + 0.1 * x
    samples = torch.rand(x.shape, generator=torch.Generator().manual_seed(1)) < 0.7
    loss = m.mse_closure(x, y, samples)()
    ref = (m(x)[0] - y)[samples].square().mean()
    torch.testing.assert_close(loss, ref, rtol=1e-12, atol=0)
    params = list(m.parameters())
    grads = torch.autograd.grad(loss, params)
    refs = torch.autograd.grad(ref, params)
    for g, r in zip(grads, refs, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-10, atol=1e-12)


def test_monotone_mse_gradcheck():
    from torchhys.functional.generalized_pi import monotone_mse

    gen = torch.Generator().manual_seed(2)
    design = torch.randn(40, 4, generator=gen, dtype=F64)
    y = torch.randn(40, generator=gen, dtype=F64)
    params = [torch.randn(4, generator=gen, dtype=F64), torch.tensor(0.7, dtype=F64),
              torch.rand(3, generator=gen, dtype=F64), torch.randn(3, generator=gen, dtype=F64),
              torch.rand(3, generator=gen, dtype=F64) + 0.5, torch.tensor(0.2, dtype=F64)]
    params = [p.requires_grad_() for p in params]
    assert torch.autograd.gradcheck(lambda *p: monotone_mse(design, y, *p), params)


def test_mse_closure_below_analytic_rows_is_autograd_through_predictor():
    """Below ANALYTIC_ROWS scored samples the loss and its gradient are autograd's through
    the predictor, to the bit (the fits of short records are unchanged); from it on, the
    analytic ones."""
    from torchhys.operator import HysteresisOperator
    from torchhys.operators import generalized_pi as gpi

    m = model()
    x = walks(300)
    y = torch.sin(3.0 * x)
    samples = torch.ones_like(x, dtype=torch.bool)
    params = list(m.parameters())
    loss = m.mse_closure(x, y, samples)()
    ref = HysteresisOperator.mse_closure(m, x, y, samples)()
    assert "MonotoneMSE" not in type(loss.grad_fn).__name__
    assert torch.equal(loss, ref)
    for g, r in zip(torch.autograd.grad(loss, params), torch.autograd.grad(ref, params),
                    strict=True):
        assert torch.equal(g, r)
    rows = int(samples.sum())
    assert rows < gpi.ANALYTIC_ROWS
    big = walks(gpi.ANALYTIC_ROWS // x.shape[0] + 1)
    fast = m.mse_closure(big, torch.sin(big), torch.ones_like(big, dtype=torch.bool))()
    assert "MonotoneMSE" in type(fast.grad_fn).__name__
