"""Tests of the Bouc-Wen plant: reference, autograd, identification, batch, streaming, bad input."""

import math
import time

import numpy as np
import pytest
import torch

from torchhys import signals
from torchhys.plants import BoucWen, bouc_wen, bouc_wen_state
from torchhys.plants.bouc_wen import DEFAULTS


def reference_state(u: np.ndarray, t: np.ndarray, *, A: float, beta: float, gamma: float,
                    n: float, w0: float = 0.0, substeps: int = 100) -> np.ndarray:
    """Plain float64 RK4 in time of the survey's ODE, linear input, many steps per sample."""
    w, out = float(w0), [float(w0)]
    for k in range(len(u) - 1):
        rate = (u[k + 1] - u[k]) / (t[k + 1] - t[k])
        h = (t[k + 1] - t[k]) / substeps

        def f(w: float, rate: float = rate) -> float:
            return (A * rate - beta * abs(rate) * abs(w) ** (n - 1) * w
                    - gamma * rate * abs(w) ** n)

        for _ in range(substeps):
            k1 = f(w)
            k2 = f(w + 0.5 * h * k1)
            k3 = f(w + 0.5 * h * k2)
            k4 = f(w + h * k3)
            w += h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(w)
    return np.array(out)


def _paper(t_end: float = 8 * math.pi) -> tuple[torch.Tensor, torch.Tensor]:
    t = signals.time_grid(dt=0.01, t_end=t_end, dtype=torch.float64)
    return t, signals.sum_of_sines(t)


# --- agreement with the independent reference ---------------------------------------------

@pytest.mark.parametrize("n", [1.0, 1.5, 2.5])
@pytest.mark.parametrize("substeps,tol", [(1, 3e-5), (4, 3e-6)])
def test_matches_reference(n: float, substeps: int, tol: float) -> None:
    t, u = _paper(t_end=3 * math.pi)
    coef = {"A": 0.5, "beta": 0.3, "gamma": 0.1, "n": n}
    ref = reference_state(u.numpy(), t.numpy(), w0=0.2, **coef)
    w = bouc_wen_state(u, t, w0=0.2, substeps=substeps, **coef)
    np.testing.assert_allclose(w.numpy(), ref, rtol=0, atol=tol)


def test_adaptive_solver_matches_reference() -> None:
    t = torch.linspace(0, 3, 61, dtype=torch.float64) ** 1.5  # non-uniform sampling
    u = 3 * torch.sin(2 * t) * torch.exp(-0.2 * t)
    coef = {"A": 0.5, "beta": 0.3, "gamma": 0.1, "n": 1.5}
    ref = reference_state(u.numpy(), t.numpy(), **coef)
    w = bouc_wen_state(u, t, method="dopri5", rtol=1e-9, atol=1e-11, **coef)
    np.testing.assert_allclose(w.numpy(), ref, rtol=0, atol=1e-7)


def test_output_and_default_loop() -> None:
    t = signals.time_grid(dt=0.01, t_end=6 * math.pi, dtype=torch.float64)
    u = 6 * torch.sin(t)
    w = bouc_wen_state(u, t)
    y = bouc_wen(u, t)
    torch.testing.assert_close(y, DEFAULTS["k_x"] * u + DEFAULTS["k_w"] * w)
    bound = DEFAULTS["A"] / (DEFAULTS["beta"] + DEFAULTS["gamma"])
    assert w.abs().max() < bound
    # counter-clockwise (y lags u), visibly hysteretic, monotone branches
    late, rising = t > 2 * math.pi, torch.cos(t) > 0
    at_zero = late & (u.abs() < 0.05)
    width = y[at_zero & ~rising].mean() - y[at_zero & rising].mean()
    span = y[late].max() - y[late].min()
    assert 0.15 < width / span < 0.3
    assert torch.all(torch.diff(y)[late[1:]] * torch.diff(u)[late[1:]] >= 0)


def test_rate_independent_in_t() -> None:
    t, u = _paper(t_end=2 * math.pi)
    warped = t + 0.3 * t.square()  # same samples at other (increasing) times
    torch.testing.assert_close(bouc_wen(u, warped), bouc_wen(u, t))


# --- batch, dtypes, streaming, module ----------------------------------------------------

def test_batch_consistency_and_shapes() -> None:
    t, u = _paper(t_end=math.pi)
    batch = torch.stack([u, 0.5 * u, -u]).reshape(3, 1, -1).expand(3, 2, -1)
    w0 = torch.tensor([0.1, -0.2, 0.0]).reshape(3, 1)
    y = bouc_wen(batch, t, w0=w0)
    assert y.shape == batch.shape
    for i in range(3):
        torch.testing.assert_close(y[i, 1], bouc_wen(batch[i, 1], t, w0=float(w0[i])))


def test_float32_close_to_float64() -> None:
    t, u = _paper()
    y64 = bouc_wen(u, t)
    y32 = bouc_wen(u.float(), t.float())
    assert y32.dtype == torch.float32
    torch.testing.assert_close(y32.double(), y64, rtol=0, atol=1e-4)


def test_streaming_equals_whole_sequence() -> None:
    t, u = _paper(t_end=2 * math.pi)
    whole = bouc_wen_state(u, t)
    first = bouc_wen_state(u[:300], t[:300])
    second = bouc_wen_state(u[299:], t[299:], w0=first[-1])
    torch.testing.assert_close(torch.cat([first, second[1:]]), whole)
    torch.testing.assert_close(bouc_wen_state(u[:1], t[:1], w0=0.3), u.new_full((1,), 0.3))


def test_flat_input_holds_state() -> None:
    t = torch.arange(8, dtype=torch.float64)
    u = torch.tensor([0.0, 1.0, 2.0, 2.0, 2.0, 1.0, 1.0, 3.0], dtype=torch.float64,
                     requires_grad=True)
    w = bouc_wen_state(u, t)
    assert w[2] == w[3] == w[4] and w[5] == w[6]
    w.sum().backward()
    assert torch.isfinite(u.grad).all()


def test_module_matches_functional_and_registers() -> None:
    t, u = _paper(t_end=math.pi)
    model = BoucWen(A=0.6, beta=0.2, gamma=0.05, n=1.5, k_x=0.9, k_w=-0.8).double()
    expected = bouc_wen(u, t, A=0.6, beta=0.2, gamma=0.05, n=1.5, k_x=0.9, k_w=-0.8)
    torch.testing.assert_close(model(u, t), expected)
    names = {name for name, _ in model.named_parameters()}
    assert names == {"A", "beta", "gamma", "n_root", "k_x", "k_w"}
    assert float(model.coefficients()["n"].detach()) == pytest.approx(1.5)
    frozen = BoucWen(learnable=False)
    assert not list(frozen.parameters()) and len(list(frozen.buffers())) == 6
    clone = BoucWen(A=1.0)
    clone.load_state_dict(BoucWen(A=0.7).state_dict())
    assert float(clone.A.detach()) == pytest.approx(0.7)


# --- autograd ---------------------------------------------------------------------------

def test_gradcheck_parameters_input_and_state() -> None:
    t = torch.tensor([0.0, 0.1, 0.25, 0.4, 0.6, 0.7], dtype=torch.float64)
    u = torch.tensor([0.0, 0.8, 1.5, 0.9, 1.2, -0.5], dtype=torch.float64, requires_grad=True)
    args = [torch.tensor(v, dtype=torch.float64, requires_grad=True)
            for v in (0.5, 0.3, 0.1, 1.6, 1.0, -1.0, 0.2)]

    def f(u, A, beta, gamma, n, k_x, k_w, w0):
        return bouc_wen(u, t, A=A, beta=beta, gamma=gamma, n=n, k_x=k_x, k_w=k_w, w0=w0,
                        substeps=2)

    assert torch.autograd.gradcheck(f, (u, *args))


def test_gradient_finite_from_zero_state_with_n_one() -> None:
    t, u = _paper(t_end=math.pi)
    model = BoucWen().double()
    model(u, t).square().mean().backward()
    for name, p in model.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


def fit_lbfgs(model, params, u, t, y, *, max_iter: int) -> None:
    """Identify ``params`` of ``model`` from (u, y) by one strong-Wolfe L-BFGS run."""
    opt = torch.optim.LBFGS(params, max_iter=max_iter, tolerance_grad=1e-12,
                            tolerance_change=1e-15, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = (model(u, t) - y).square().mean()
        loss.backward()
        return loss

    opt.step(closure)


def test_identifies_perturbed_parameters() -> None:
    """LBFGS recovers A, beta, gamma, k_x from a short record (k_w and n held fixed).

    (A, beta, gamma, k_w) and (c A, c^(1-n) beta, c^(1-n) gamma, k_w / c) give the same
    output, so one of them must be fixed for the others to be identifiable.
    """
    t = signals.time_grid(dt=0.05, t_end=4 * math.pi, dtype=torch.float64)
    u = signals.sum_of_sines(t)
    with torch.no_grad():
        y = BoucWen().double()(u, t)
    model = BoucWen(A=0.35, beta=0.4, gamma=0.05, k_x=1.2).double()
    model.k_w.requires_grad_(False)
    model.n_root.requires_grad_(False)
    params = [p for p in model.parameters() if p.requires_grad]
    fit_lbfgs(model, params, u, t, y, max_iter=100)
    found = {k: float(v.detach()) for k, v in model.coefficients().items()}
    for name in ("A", "beta", "gamma", "k_x"):
        assert found[name] == pytest.approx(DEFAULTS[name], rel=1e-3), name


@pytest.mark.slow
def test_identifies_exponent_too() -> None:
    t = signals.time_grid(dt=0.05, t_end=4 * math.pi, dtype=torch.float64)
    u = signals.sum_of_sines(t)
    with torch.no_grad():
        y = BoucWen(n=2.0).double()(u, t)
    model = BoucWen(A=0.4, beta=0.25, gamma=0.15, n=1.5, k_x=1.1).double()
    model.k_w.requires_grad_(False)
    params = [p for p in model.parameters() if p.requires_grad]
    fit_lbfgs(model, params, u, t, y, max_iter=150)
    found = {k: float(v.detach()) for k, v in model.coefficients().items()}
    expected = {**DEFAULTS, "n": 2.0}
    for name in ("A", "beta", "gamma", "n", "k_x"):
        assert found[name] == pytest.approx(expected[name], rel=1e-3), name


@pytest.mark.slow
def test_simulates_2500_samples_quickly() -> None:
    t, u = _paper()
    start = time.perf_counter()
    with torch.no_grad():
        BoucWen()(u[:2500].float(), t[:2500].float())
    assert time.perf_counter() - start < 2.0


# --- bad input ---------------------------------------------------------------------------

_T = torch.arange(5, dtype=torch.float64)
_U = torch.sin(_T)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"u": torch.tensor([0.0, float("nan"), 1.0, 2.0, 3.0])}, "u must be finite"),
        ({"t": torch.tensor([0.0, 1.0, float("inf"), 3.0, 4.0])}, "t must be finite"),
        ({"t": torch.tensor([0.0, 1.0, 1.0, 3.0, 4.0])}, "strictly increasing"),
        ({"u": torch.zeros(4)}, "u must have shape"),
        ({"u": torch.tensor(1.0)}, "u must have shape"),
        ({"t": _T.reshape(1, 5)}, "t must have shape"),
        ({"n": 0.5}, "n must be >= 1"),
        ({"A": float("nan")}, "A must be finite"),
        ({"beta": torch.ones(2)}, "beta must be a scalar"),
        ({"method": "rk45"}, "method must be one of"),
        ({"substeps": 0}, "substeps"),
        ({"w0": torch.zeros(3)}, "w0 must broadcast"),
        ({"w0": float("inf")}, "w0"),
        ({"method": "dopri5", "rtol": 0.0}, "rtol"),
    ],
)
def test_bad_input_value_error(kwargs: dict, match: str) -> None:
    call = {"u": _U, "t": _T, **kwargs}
    with pytest.raises(ValueError, match=match):
        bouc_wen(call.pop("u"), call.pop("t"), **call)


@pytest.mark.parametrize(
    "u,t,kwargs,match",
    [
        (_U.numpy(), _T, {}, "u must be a torch.Tensor"),
        (torch.arange(5), _T, {}, "u must have a floating dtype"),
        (_U, torch.arange(5), {}, "t must have a floating dtype"),
        (_U, _T, {"k_x": "1"}, "k_x must be a float"),
    ],
)
def test_bad_input_type_error(u, t, kwargs: dict, match: str) -> None:
    with pytest.raises(TypeError, match=match):
        bouc_wen(u, t, **kwargs)


def test_module_rejects_bad_coefficients() -> None:
    with pytest.raises(ValueError, match="n must be >= 1"):
        BoucWen(n=0.9)
    with pytest.raises(ValueError, match="gamma must be a finite float"):
        BoucWen(gamma=float("nan"))
    with pytest.raises(ValueError, match="method must be one of"):
        BoucWen(method="euler")
