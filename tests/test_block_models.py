"""Tests of torchhys.models: chunking with carried state, gradients, references, save/load,
bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from torchhys.dynamics import TransferFunction
from torchhys.models import (
    BENCHMARK,
    BoucWenOscillator,
    HysteresisFeedback,
    LinearModel,
    fit_linear,
    fit_windows,
    init_from_linear,
    simulate,
)
from torchhys.models.bouc_wen_oscillator import _NODES, _lagrange
from torchhys.operators.duhem import DuhemHysteresis
from torchhys.operators.play_hysteresis import PlayHysteresis
from torchhys.plants import bouc_wen_state
from torchhys.registry import make_operator

FS = 750.0
DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "bouc_wen_benchmark.npz"
PLAYS = {"name": "play_hysteresis", "widths": [0.5, 1.0, 1.5], "hidden": 4}


def force(T: int = 200, batch: int | None = None, seed: int = 0) -> torch.Tensor:
    """A band-limited random force (N), about 50 N RMS."""
    g = torch.Generator().manual_seed(seed)
    shape = (T,) if batch is None else (batch, T)
    x = torch.randn(shape, generator=g, dtype=torch.float64)
    kernel = torch.ones(5, dtype=torch.float64) / 5
    x = torch.nn.functional.conv1d(x.reshape(-1, 1, T), kernel.view(1, 1, -1), padding=2)
    return 110 * x.reshape(shape)


def linear_block() -> TransferFunction:
    """A lightly damped second-order block in scaled units (DC gain about 1)."""
    p = 0.97 * np.exp(1j * 0.3)
    a = np.poly([p, np.conj(p)]).real
    return TransferFunction.from_coefficients([0.0, 0.5 * a.sum(), 0.5 * a.sum()], a)


def feedback(element: dict) -> HysteresisFeedback:
    torch.manual_seed(0)
    model = HysteresisFeedback(2, element, fs=FS, u_scale=50.0, y_scale=1e-3)
    init_from_linear(model, linear_block(), fraction=0.5)
    with torch.no_grad():  # move off the linear start so that every parameter matters
        for p in model.H.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return model


MODELS = {
    "linear": lambda: LinearModel(3, fs=FS, u_scale=50.0, y_scale=1e-3),
    "duhem": lambda: feedback({"name": "duhem", "hidden": 3}),
    "plays": lambda: feedback(PLAYS),
    "grey_box": lambda: BoucWenOscillator(**BENCHMARK, fs=FS, substeps=2, learn_exponent=True),
}


# --- streaming: chunked calls with the carried state equal one call --------------------------

@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("cut", [1, 37, 199])
def test_chunked_equals_whole(name: str, cut: int) -> None:
    model = MODELS[name]()
    u = force(200, batch=3)
    with torch.no_grad():
        whole, s_whole = model(u)
        a, s = model(u[:, :cut])
        b, s2 = model(u[:, cut:], s)
    torch.testing.assert_close(torch.cat([a, b], 1), whole, rtol=1e-12, atol=1e-18)
    torch.testing.assert_close(s2, s_whole, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("name", list(MODELS))
def test_batch_rows_are_independent(name: str) -> None:
    model = MODELS[name]()
    u = force(120, batch=3)
    with torch.no_grad():
        rows = torch.stack([model(u[i])[0] for i in range(3)])
        torch.testing.assert_close(model(u)[0], rows, rtol=1e-12, atol=1e-18)


# --- autograd (the Duhem element's gradcheck in its input: tests/test_conformance.py) -------

@pytest.mark.parametrize("name", list(MODELS))
def test_gradients_reach_every_parameter(name: str) -> None:
    model = MODELS[name]()
    y, _ = model(force(150))
    (y / 1e-3).square().mean().backward()
    for pname, p in model.named_parameters():
        if p.numel() == 0:  # e.g. the first-order section of an even-order block
            continue
        assert p.grad is not None, f"{pname} has no gradient"
        assert torch.isfinite(p.grad).all(), pname
        assert p.grad.abs().sum() > 0, f"{pname} has a zero gradient"


def test_gradcheck_grey_box() -> None:
    model = BoucWenOscillator(**BENCHMARK, fs=FS, substeps=1)
    u = force(12).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda u: model(u)[0] * 1e4, (u,))


# --- references ----------------------------------------------------------------------------

def _rhs(s: np.ndarray, u: float, c: dict[str, float]) -> np.ndarray:
    y, v, z = s
    return np.array([v, (u - c["c"] * v - c["k"] * y - z) / c["m"],
                     c["alpha"] * v - c["beta_gamma"] * abs(v) * z
                     - c["beta_delta"] * v * abs(z)])


def _cubic_input(u: np.ndarray):
    """The model's input between samples: the causal cubic through u[t-2..t+1] (held before
    the first sample)."""
    padded = np.concatenate([[u[0], u[0]], u])

    def at(time: float) -> float:
        t = min(int(math.floor(time)), len(u) - 2)
        w = _lagrange(_NODES["cubic"], time - t)
        return float(np.dot(w, padded[t: t + 4]))
    return at


def _rk4_reference(u: np.ndarray, c: dict[str, float], substeps: int) -> np.ndarray:
    """A plain float64 loop: classic RK4 of the benchmark's ODE, ``substeps`` steps a sample,
    the input on the causal cubic."""
    at = _cubic_input(u)
    h = 1 / (FS * substeps)
    s, out = np.zeros(3), [0.0]
    for t in range(len(u) - 1):
        for j in range(substeps):
            a = t + j / substeps
            k1 = _rhs(s, at(a), c)
            k2 = _rhs(s + 0.5 * h * k1, at(a + 0.5 / substeps), c)
            k3 = _rhs(s + 0.5 * h * k2, at(a + 0.5 / substeps), c)
            k4 = _rhs(s + h * k3, at(a + 1 / substeps), c)
            s = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(s[0])
    return np.array(out)


@pytest.mark.parametrize("substeps", [1, 3])
def test_grey_box_matches_a_plain_rk4_loop(substeps: int) -> None:
    """The benchmark's equations with the true coefficients, step for step."""
    u = force(80).numpy()
    model = BoucWenOscillator(**BENCHMARK, fs=FS, substeps=substeps)
    with torch.no_grad():
        y = model(torch.from_numpy(u))[0].numpy()
    ref = _rk4_reference(u, BENCHMARK, substeps)
    np.testing.assert_allclose(y, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


def test_grey_box_converges_to_the_ode_solution() -> None:
    """Against scipy's solution of the same ODE and input path (tight tolerances). The
    |y'| and |z| kinks at reversals cost RK4 its order there, so the error falls with the
    substeps but not as h^4."""
    from scipy.integrate import solve_ivp

    u = force(60).numpy()
    at = _cubic_input(u)
    sol = solve_ivp(lambda t, s: _rhs(s, at(t * FS), BENCHMARK), (0, (len(u) - 1) / FS),
                    np.zeros(3), t_eval=np.arange(len(u)) / FS, rtol=1e-11, atol=1e-14,
                    max_step=0.25 / FS)
    errors = []
    for substeps in (2, 8):
        model = BoucWenOscillator(**BENCHMARK, fs=FS, substeps=substeps)
        with torch.no_grad():
            y = model(torch.from_numpy(u))[0].numpy()
        errors.append(np.abs(y - sol.y[0]).max() / np.abs(sol.y[0]).max())
    assert errors[1] < 3e-4 and errors[1] < errors[0] / 3


def test_duhem_element_equals_the_bouc_wen_plant() -> None:
    """Slopes A - b z - g |z| up, A + b z - g |z| down: torchhys.plants.bouc_wen_state
    (RK4 in the input variable) with n = 1."""
    A, b, g = 0.5, 0.3, 0.1
    element = DuhemHysteresis().double()
    with torch.no_grad():
        element.coef.copy_(torch.tensor([[A, -b, -g], [A, b, -g]], dtype=torch.float64))
    v = 3 * torch.sin(torch.linspace(0, 12, 300, dtype=torch.float64)) \
        * torch.linspace(1, 0.3, 300, dtype=torch.float64)
    ref = bouc_wen_state(v, torch.arange(300, dtype=torch.float64), A=A, beta=b, gamma=g, n=1.0)
    start = torch.stack([v.new_zeros(()), v[0]]).view(1, 2)  # z = 0, previous v = v[0]
    z, _ = element(v.unsqueeze(0), start)
    torch.testing.assert_close(z[0], ref, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", ["duhem", "plays"])
def test_element_is_rate_independent(kind: str) -> None:
    """Repeating samples (the same path, slower) leaves the outputs at the samples alone."""
    element = feedback({"name": "duhem", "hidden": 3} if kind == "duhem" else PLAYS).H
    v = force(80).unsqueeze(0) / 50
    with torch.no_grad():
        z, _ = element(v)
        z_slow, _ = element(v.repeat_interleave(3, dim=1))
    torch.testing.assert_close(z_slow[:, 2::3], z, rtol=1e-12, atol=1e-14)


def test_feedback_model_starts_as_the_linear_model() -> None:
    G = linear_block()
    model = HysteresisFeedback(2, {"name": "duhem"}, fs=FS, u_scale=50.0, y_scale=1e-3)
    init_from_linear(model, G, fraction=0.6)
    u = force(300)
    with torch.no_grad():
        y = model(u)[0]
    torch.testing.assert_close(y, 1e-3 * G(u / 50.0)[0], rtol=1e-9, atol=1e-15)


@pytest.mark.skipif(not DATA.exists(), reason="the benchmark data (../shared/data) is absent")
def test_true_coefficients_reproduce_the_benchmark_output() -> None:
    d = np.load(DATA)
    model = BoucWenOscillator(**BENCHMARK, fs=float(d["fs"]), substeps=4)
    truth = d["train_y"][:2048]  # the training record starts at rest
    u = torch.from_numpy(d["train_u"][:2048].astype(np.float64))
    with torch.no_grad():
        y = model(u)[0].numpy()
    # the training output holds the benchmark's measurement noise (std about 7.4e-6 m)
    assert np.sqrt(np.mean((y - truth) ** 2)) < 8e-6


# --- save and load -------------------------------------------------------------------------

def test_the_element_is_an_operator_spec_or_an_operator() -> None:
    """``element`` goes through make_operator; ``config()`` gives the spec that rebuilds it."""
    by_spec = HysteresisFeedback(2, {"name": "play_hysteresis", "widths": [0.5, 1.0],
                                     "hidden": 2}, fs=FS)
    assert type(by_spec.H) is PlayHysteresis and by_spec.state_size == 2 * 2 + 2
    spec = by_spec.config()["element"]
    assert spec == {"name": "play_hysteresis", "widths": [0.0, 0.0], "hidden": 2}
    assert type(make_operator(spec)) is PlayHysteresis
    element = DuhemHysteresis(hidden=1)
    assert HysteresisFeedback(2, element, fs=FS).H is element
    assert HysteresisFeedback(2, fs=FS).config()["element"] == {"name": "duhem", "hidden": 0}


@pytest.mark.parametrize("name", list(MODELS))
def test_config_and_state_dict_rebuild_the_model(name: str, tmp_path: Path) -> None:
    model = MODELS[name]()
    path = tmp_path / "m.pt"
    torch.save({"config": model.config(), "state_dict": model.state_dict()}, path)
    saved = torch.load(path, weights_only=True)
    again = type(model)(**saved["config"])
    again.load_state_dict(saved["state_dict"])
    u = force(100)
    with torch.no_grad():
        torch.testing.assert_close(again(u)[0], model(u)[0], rtol=1e-13, atol=0)


# --- training ------------------------------------------------------------------------------

@pytest.mark.parametrize("optimizer,iterations", [("lbfgs", 5), ("adam", 60)])
def test_fit_windows_lowers_the_simulation_error(optimizer: str, iterations: int) -> None:
    """A linear model started off the true one, fitted by windows with carried states."""
    truth = LinearModel(2, fs=FS, u_scale=50.0, y_scale=1e-3)
    truth.G = linear_block()
    u = force(1201, seed=3)
    with torch.no_grad():
        y = truth(u)[0]
    model = LinearModel(2, fs=FS, u_scale=50.0, y_scale=1e-3)
    p = 0.95 * np.exp(1j * 0.33)
    model.G = TransferFunction.from_coefficients([0.0, 0.3, 0.3], np.poly([p, np.conj(p)]).real)
    before = float((simulate(model, u, fs=FS) - y).square().mean().sqrt())
    history = []
    fit = fit_windows(model, u, y, fs=FS, window=100, iterations=iterations,
                      optimizer=optimizer, lr=1.0 if optimizer == "lbfgs" else 0.02,
                      validation=200, eval_every=iterations, log=history.append)
    after = float((simulate(model, u, fs=FS) - y).square().mean().sqrt())
    assert fit.iterations == iterations and len(fit.history) == len(history) == 2
    assert after < 0.2 * before
    assert fit.val_rmse == pytest.approx(
        float((simulate(model, u, fs=FS) - y)[-200:].square().mean().sqrt()))


def test_fit_linear_recovers_a_linear_system() -> None:
    truth = LinearModel(2, fs=FS, u_scale=50.0, y_scale=1e-3)
    truth.G = linear_block()
    u = force(1500, seed=4)
    with torch.no_grad():
        y = truth(u)[0]
    model = fit_linear(u, y, order=2, fs=FS)
    error = float((simulate(model, u, fs=FS) - y).square().mean().sqrt())
    assert error < 1e-6 * float(y.std())


# --- bad input -----------------------------------------------------------------------------

def test_window_longer_than_the_record() -> None:
    model = MODELS["linear"]()
    u = force(100)
    with pytest.raises(ValueError, match=r"window must be an int in \[1, 99\]"):
        fit_windows(model, u, u * 1e-5, fs=FS, window=150, iterations=1)
    with pytest.raises(ValueError, match="window must be"):
        fit_windows(model, u, u * 1e-5, fs=FS, window=60, iterations=1, validation=50)


def test_sampling_frequency_must_match() -> None:
    model = MODELS["linear"]()
    u = force(100)
    with pytest.raises(ValueError, match=r"fs = 700.0 Hz .* differs from the model's fs = 750"):
        fit_windows(model, u, u * 1e-5, fs=700.0, window=10, iterations=1)
    with pytest.raises(ValueError, match="fs = 1000.0 Hz"):
        simulate(model, u, fs=1000.0)
    with pytest.raises(ValueError, match="fs must be a positive finite float"):
        BoucWenOscillator(fs=-1.0)


@pytest.mark.parametrize("name", ["u", "y"])
def test_nan_in_the_data(name: str) -> None:
    model = MODELS["linear"]()
    u, y = force(100), force(100, seed=1) * 1e-5
    (u if name == "u" else y)[17] = math.nan
    with pytest.raises(ValueError, match=rf"{name} must be finite.*index \(17,\)"):
        fit_windows(model, u, y, fs=FS, window=10, iterations=1)


def test_other_bad_input() -> None:
    model = MODELS["grey_box"]()
    with pytest.raises(ValueError, match=r"state must have shape \(6,\) or \(2, 6\)"):
        model(force(10, batch=2), torch.zeros(2, 5, dtype=torch.float64))
    with pytest.raises(ValueError, match="y must have the shape of u"):
        fit_windows(model, force(100), force(90), fs=FS, window=10, iterations=1)
    with pytest.raises(ValueError, match="m must be > 0"):
        BoucWenOscillator(m=0.0, fs=FS)
    with pytest.raises(ValueError, match="interpolation must be one of"):
        BoucWenOscillator(fs=FS, interpolation="sinc")
    with pytest.raises(ValueError, match=r"^element: no operator is registered as 'duhm'; "
                                         r"registered names: \[.*'duhem'.*'play_hysteresis'"):
        HysteresisFeedback(2, {"name": "duhm"}, fs=FS)
    with pytest.raises(ValueError, match=r"^element: a spec dict needs a 'name'"):
        HysteresisFeedback(2, {"kind": "duhem"}, fs=FS)
    with pytest.raises(TypeError, match=r"^element must be a feedback element .* got EIHO$"):
        HysteresisFeedback(2, "eiho", fs=FS)
    fb = HysteresisFeedback(2, "duhem", fs=FS)
    with pytest.raises(ValueError, match=r"fraction must be a float in \[0, 1\)"):
        init_from_linear(fb, linear_block(), fraction=1.0)
    with pytest.raises(ValueError, match="G must have the model's order 2"):
        init_from_linear(fb, TransferFunction(3), fraction=0.5)
