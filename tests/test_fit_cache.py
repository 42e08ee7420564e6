"""Fitted families shared between model selection's runs (torchhys.identification._fit_cache)."""

from __future__ import annotations

import pytest
import torch

from torchhys.identification import _fit_cache as fit_cache
from torchhys.identification.errors import FitError
from torchhys.identification.specs import build_operators


def _data(n: int = 400) -> tuple[torch.Tensor, torch.Tensor]:
    t = torch.linspace(0, 6 * torch.pi, n, dtype=torch.float64)
    x = (t.sin() * (1 + t / 10))[None]
    return x, 2 * x + 0.1 * torch.cumsum(x, -1) / n


def test_the_same_spec_on_the_same_data_is_fitted_once() -> None:
    fit_cache.clear()
    calls = []
    spec = {"fit": "stop_pi", "n_widths": 8, "segments": 2}
    (module,), fitters = build_operators([spec])
    x, y = _data()

    def counted(*args):
        calls.append(1)
        return inner(*args)

    from torchhys.identification.stop_pi import _stop_pi
    _, inner = _stop_pi(spec)
    fit = fit_cache.shared(spec, counted)
    a, b = fit(x, y, 10, None), fit(x.clone(), y.clone(), 10, None)
    assert len(calls) == 1 and a is not b
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k])
    # another warm-up, mask or spec is another fit
    fit(x, y, 20, None)
    mask = torch.ones_like(x, dtype=torch.bool)
    mask[:, 200:300] = False
    fit(x, y, 10, mask)
    assert len(calls) == 3
    # the wrapped fitter of build_operators gives the unwrapped fit's model
    direct = inner(x, y, 10, None)
    via = fitters[0](x, y, 10, None)
    for k, v in direct.state_dict().items():
        assert torch.equal(v, via.state_dict()[k])


def test_a_failed_fit_fails_again_without_refitting() -> None:
    fit_cache.clear()
    calls = []

    def failing(*args):
        calls.append(1)
        raise FitError("no inverse")

    fit = fit_cache.shared({"fit": "gpi"}, failing)
    x, y = _data()
    for _ in range(2):
        with pytest.raises(FitError, match="no inverse"):
            fit(x, y, 0, None)
    assert len(calls) == 1


def test_random_families_are_not_shared() -> None:
    def fit(*args):
        return None

    assert fit_cache.shared({"fit": "jiles_atherton"}, fit) is fit


def test_gpi_specs_that_run_the_same_iterations_share_a_fit() -> None:
    """On a long record (here: a small sample_iterations) the gpi spec with ``epochs: 200``
    runs the default spec's iterations: one fit; on a short one they differ: two."""
    from torchhys.identification.generalized_pi import fit_key

    x, y = _data()
    long = {"fit": "gpi", "sample_iterations": 400 * 50}
    assert fit_key(long, x, 0, None) == fit_key({**long, "epochs": 200}, x, 0, None)
    assert fit_key(long, x, 0, None)["epochs"] == 50
    short = {"fit": "gpi"}
    assert fit_key(short, x, 0, None) != fit_key({**short, "epochs": 200}, x, 0, None)
    fit_cache.clear()
    calls = []

    def counted(*args):
        calls.append(1)
        raise FitError("counted")

    for spec in (long, {**long, "epochs": 200}, short, {**short, "epochs": 200}):
        with pytest.raises(FitError):
            fit_cache.shared(spec, counted)(x, y, 0, None)
    assert len(calls) == 3
