"""The inverse Jiles-Atherton model: against a float64 loop written from the equations,
physical properties of its loops, the step and its export, gradients, identification and bad
input (chunked calls, streaming inside a network: tests/test_conformance.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from _helpers import sine_loops

from torchhys import JilesAtherton, fit_jiles_atherton
from torchhys.functional.jiles_atherton import (
    MU0,
    jiles_atherton,
    langevin,
    langevin_slope,
)
from torchhys.registry import OPERATORS, make_operator

F64 = torch.float64
# a MnZn ferrite core, about what fit_jiles_atherton finds on the measured loops
FERRITE = dict(ms=3.0e5, a=18.0, k=13.0, alpha=1.2e-4, c=0.8)


def reference(b: np.ndarray, ms: float, a: float, k: float, alpha: float, c: float,
              mu0: float = MU0, substeps: int = 2) -> np.ndarray:
    """The model written from its equations, one float at a time (math, no tensors)."""

    def lang(z: float) -> float:
        return 1 / math.tanh(z) - 1 / z if abs(z) > 1e-3 else z / 3 - z**3 / 45

    def dlang(z: float) -> float:
        if abs(z) > 300:  # sinh overflows; 1/sinh^2 < 1e-260
            return 1 / z**2
        return 1 / z**2 - 1 / math.sinh(z) ** 2 if abs(z) > 1e-3 else 1 / 3 - z * z / 15

    out = []
    bp = hp = 0.0
    for bt in b:
        d = (bt - bp) / substeps
        delta = 1.0 if d >= 0 else -1.0
        for _ in range(substeps):
            m = bp / mu0 - hp
            he = hp + alpha * m
            man = ms * lang(he / a)
            mirr = (m - c * man) / (1 - c)
            dirr = (man - mirr) / (k * delta) if delta * (man - mirr) > 0 else 0.0
            x = max((1 - c) * dirr + c * ms / a * dlang(he / a), 0.0)
            chi = x / max(1 - alpha * x, 1e-2)
            hp += d / (mu0 * (1 + chi))
            bp += d
        out.append(hp)
    return np.array(out)


def test_langevin_against_its_closed_form_and_derivative():
    z = torch.cat([torch.linspace(-40, -0.2, 200), torch.linspace(0.2, 40, 200)]).to(F64)
    np.testing.assert_allclose(langevin(z).numpy(), 1 / np.tanh(z.numpy()) - 1 / z.numpy(),
                               rtol=1e-12)
    # the series and the closed form meet at |z| = 0.1; L' is L's derivative everywhere
    w = torch.linspace(-3, 3, 601, dtype=F64, requires_grad=True)
    (grad,) = torch.autograd.grad(langevin(w).sum(), w)
    torch.testing.assert_close(langevin_slope(w.detach()), grad, rtol=1e-7, atol=1e-9)
    near = torch.tensor([0.0999999, 0.1000001], dtype=F64)
    assert abs(float(langevin(near)[1] - langevin(near)[0])) < 1e-7
    assert float(langevin_slope(torch.tensor([1e4], dtype=F64))) == pytest.approx(1e-8)
    assert float(langevin(torch.tensor([0.0], dtype=F64))) == 0.0


@pytest.mark.parametrize("substeps", [1, 3])
def test_equals_a_float64_loop_written_from_the_equations(substeps):
    g = torch.Generator().manual_seed(0)
    b = 0.35 * torch.cumsum(torch.randn(150, generator=g, dtype=F64), 0) / 6
    b = b.clamp(-0.36, 0.36)  # into saturation (mu0 ms = 0.377 T)
    m = JilesAtherton(**FERRITE, substeps=substeps)
    with torch.no_grad():
        h, state = m(b)
    expected = reference(b.numpy(), **FERRITE, substeps=substeps)
    np.testing.assert_allclose(h.numpy(), expected, rtol=1e-7, atol=1e-8)
    assert state.tolist() == [float(b[-1]), float(h[-1])]


def test_loops_close_are_odd_and_run_clockwise_with_rising_branches():
    m = JilesAtherton(**FERRITE)
    b = sine_loops([0.1, 0.3], periods=4)
    with torch.no_grad():
        h, _ = m(b)
        h_neg, _ = m(-b)
    n = 128
    last, before = h[:, -n:], h[:, -2 * n:-n]
    assert float((last - before).abs().max()) < 1e-3 * float(last.abs().max())  # closed loop
    torch.testing.assert_close(h_neg, -h)  # demagnetised start: an odd model
    # H moves with B (never against it), and H dB around the loop is the loss, > 0
    db, dh = b.diff(dim=1), h.diff(dim=1)
    assert bool((dh * db >= 0).all())
    loss = (0.5 * (last[:, 1:] + last[:, :-1]) * b[:, -n:].diff(dim=1)).sum(1)
    assert bool((loss > 0).all())
    # the larger loop reaches the larger field
    width = [float(last[i].max() - last[i].min()) for i in range(2)]
    assert width[0] < width[1]


@pytest.mark.parametrize("dtype, atol", [(F64, 1e-10), (torch.float32, 0.05)])
def test_streaming_step_equals_the_sequence_path(dtype, atol):
    m = JilesAtherton(**FERRITE, substeps=3)
    b = sine_loops([0.25, 0.05], periods=2)
    step = m.streaming_step(dtype)
    with torch.no_grad():
        h, _ = m(b)
        f = step.run(b.to(dtype))
    # float32: M ~ 3e5 A/m is B / mu0 - H, H ~ 10 A/m: about 5 significant digits of H
    torch.testing.assert_close(f[..., 0].to(F64), h, rtol=0, atol=atol)


def test_exported_step_equals_the_sequence_path():
    m = JilesAtherton(**FERRITE)
    b = sine_loops([0.2], periods=1, n=40)
    step = m.streaming_step(F64)
    state = step.initial_state(b[:, :1])
    exported = torch.export.export(step, (b[:, :1], state)).module()
    scripted = torch.jit.script(step)
    with torch.no_grad():
        h, _ = m(b)
        for run in (exported, scripted):
            s, outs = step.initial_state(b[:, :1]), []
            for bt in b.unbind(1):
                f, s = run(bt.unsqueeze(1), s)
                outs.append(f)
            torch.testing.assert_close(torch.cat(outs, 1), h, rtol=0, atol=1e-10)


def test_registered():
    assert OPERATORS["jiles_atherton"] is JilesAtherton
    assert isinstance(make_operator("jiles_atherton", **FERRITE), JilesAtherton)


def test_gradients_match_finite_differences():
    m = JilesAtherton(**FERRITE, substeps=1)
    b = sine_loops([0.2], periods=1, n=24)[0]

    def run(raw: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        ms, a, k, alpha = raw[:4].exp().unbind()
        h, _ = jiles_atherton(x[None], ms, a, k, alpha, torch.sigmoid(raw[4]), substeps=1)
        return h / 100

    raw = m.raw.detach().clone().requires_grad_(True)
    x = b.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(run, (raw, x), eps=1e-7, atol=1e-5, rtol=1e-4)


def test_state_dict_round_trip():
    m = JilesAtherton(**FERRITE, substeps=3)
    other = JilesAtherton(substeps=3)
    other.load_state_dict(m.state_dict())
    b = sine_loops([0.2], periods=1)
    with torch.no_grad():
        torch.testing.assert_close(other(b)[0], m(b)[0], rtol=0, atol=0)
    for name, value in zip(("ms", "a", "k", "alpha", "c"), other.parameters_effective(),
                           strict=True):
        assert float(value.detach()) == pytest.approx(FERRITE[name], rel=1e-12)


def test_fit_recovers_the_model_and_predicts_another_amplitude():
    true = JilesAtherton(**FERRITE)
    b = sine_loops([0.12, 0.36], periods=3, n=64)
    with torch.no_grad():
        h, _ = true(b)
    fit = fit_jiles_atherton(b, h, warmup=128, starts=4, iterations=40)
    for name, value in zip(("ms", "a", "k", "alpha", "c"), fit.parameters_effective(),
                           strict=True):
        assert float(value.detach()) == pytest.approx(FERRITE[name], rel=0.05), name
    other = sine_loops([0.24], periods=3, n=64)
    with torch.no_grad():
        err = (fit(other)[0] - true(other)[0])[:, 128:].abs().max()
        span = true(other)[0].abs().max()
    assert float(err) < 0.01 * float(span)


def test_fit_picks_substeps_from_the_largest_sample_step():
    b = sine_loops([0.3], periods=2, n=16)  # steps of up to 0.3 * 2 pi / 16 = 0.12 T
    with torch.no_grad():
        h, _ = JilesAtherton(**FERRITE)(b)
    fit = fit_jiles_atherton(b, h, starts=1, iterations=1)
    jump = float(b.diff(dim=1).abs().max())
    assert fit.substeps == math.ceil(jump * 32 / 0.6)
    assert fit_jiles_atherton(b, h, starts=1, iterations=1, substeps=5).substeps == 5


@pytest.mark.parametrize("kwargs, match", [
    ({"ms": 0.0}, "ms must be a finite number > 0"),
    ({"a": -1.0}, "a must be a finite number > 0"),
    ({"k": float("nan")}, "k must be a finite number > 0"),
    ({"alpha": float("inf")}, "alpha must be a finite number > 0"),
    ({"c": 1.0}, r"c must be in \(0, 1\)"),
    ({"mu0": 0.0}, "mu0 must be a finite number > 0"),
    ({"substeps": 0}, "substeps must be"),
])
def test_bad_parameters_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        JilesAtherton(**kwargs)


def test_bad_input_is_named():
    m = JilesAtherton(**FERRITE)
    b = sine_loops([0.2, 0.1], periods=1, n=16)
    with pytest.raises(TypeError, match="state must be a torch.Tensor, got list"):
        m(b, [[0.0, 0.0], [0.0, 0.0]])
    with pytest.raises(ValueError, match="warmup must leave samples to fit: warmup=16 of 16"):
        fit_jiles_atherton(b, b, warmup=16)
    with pytest.raises(ValueError, match="y must have the shape of x"):
        fit_jiles_atherton(b, b[:, :-1])
    with pytest.raises(ValueError, match="x and y must vary"):
        fit_jiles_atherton(b, torch.zeros_like(b))
    with torch.no_grad():
        h, _ = m(b)
    with pytest.raises(ValueError, match="y must rise with x .* but it falls: check the sign"):
        fit_jiles_atherton(b, -h)


def test_fit_to_a_degenerate_optimum_returns_a_valid_model():
    """The smallest measured ferrite loop (0.09 T, Rayleigh region) drives the coupling
    alpha toward 0: the fit keeps it a small positive number and returns a model that fits
    the loop (it once underflowed to alpha = 0 and raised)."""
    path = Path(__file__).resolve().parents[1] / "examples/data/mnzn_ferrite_bh_loops.csv"
    table = np.genfromtxt(path, delimiter=",", names=True, skip_header=4)
    rows = table["loop"] == 0
    b, h = (torch.tensor(np.tile(table[k][rows], 3))[None] for k in ("B_T", "H_Apm"))
    w = 2 * int(rows.sum())
    fit = fit_jiles_atherton(b, h, warmup=w, iterations=20)
    assert all(float(v) > 0 for v in fit.parameters_effective())
    with torch.no_grad():
        rmse = float((fit(b)[0] - h)[:, w:].square().mean().sqrt())
    slope, offset = np.polyfit(b[0, w:].numpy(), h[0, w:].numpy(), 1)
    line = float(np.sqrt(np.mean((slope * b[0, w:].numpy() + offset - h[0, w:].numpy()) ** 2)))
    assert rmse < 0.5 * line, (rmse, line)


def test_state_dict_carries_mu0_and_substeps():
    """A module built with the defaults and loaded from a fitted one's state dict runs as
    the fitted one did (the config families load fitted models into placeholders)."""
    fitted = JilesAtherton(**FERRITE, mu0=4e-4 * math.pi, substeps=5)
    state = fitted.state_dict()
    assert int(state["saved_substeps"]) == 5 and state["saved_substeps"].dtype == torch.int64
    assert float(state["saved_mu0"]) == 4e-4 * math.pi
    loaded = JilesAtherton()
    loaded.load_state_dict(state)
    assert loaded.substeps == 5 and loaded.mu0 == 4e-4 * math.pi
    b = 1e3 * sine_loops([0.2], periods=1, n=32)  # mT
    with torch.no_grad():
        assert torch.equal(loaded(b)[0], fitted(b)[0])
    assert loaded.streaming_step(F64).substeps == 5
    loaded.substeps = 3
    assert int(loaded.state_dict()["saved_substeps"]) == 3
    with pytest.raises(ValueError, match="substeps must be"):
        loaded.substeps = 0


@pytest.mark.parametrize("key, value, match", [
    ("saved_substeps", torch.tensor(0), "saved_substeps must be an integer >= 1, got \\[0.0\\]"),
    ("saved_mu0", torch.tensor(-1.0, dtype=F64), "saved_mu0 must be finite and > 0"),
    ("raw", torch.full((5,), math.nan, dtype=F64), "raw must be finite"),
])
def test_a_bad_state_dict_is_an_error_and_leaves_the_module(key, value, match):
    m = JilesAtherton(**FERRITE, substeps=3)
    before = {k: v.clone() for k, v in m.state_dict().items()}
    state = JilesAtherton(**FERRITE, substeps=5, mu0=2e-6).state_dict()
    state["raw"] = state["raw"] + 0.1
    state[key] = value
    with pytest.raises(ValueError, match=match):
        m.load_state_dict(state)
    for k, v in m.state_dict().items():
        assert torch.equal(v, before[k]), k
    assert m.substeps == 3 and m.mu0 == MU0
