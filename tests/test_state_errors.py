"""A bad initial state is a clear error that names ``state`` (the argument the caller
wrote), not the name of a function inside: the Preisach relays, the PI inverse (not a
registered operator); the functional stop-type model names its ``p0``."""

from __future__ import annotations

import pytest
import torch

import torchhys
from torchhys.functional import stop_pi

W = torch.tensor([0.2, 0.5], dtype=torch.float64)
X = torch.linspace(0.0, 0.5, 12, dtype=torch.float64)
# every registered operator: tests/test_conformance.py (a state from another batch, a NaN)


def test_a_preisach_state_that_is_not_plus_or_minus_one_names_state() -> None:
    op = torchhys.Preisach(-1.0, 1.0, 4).double()
    _, good = op(X)
    with pytest.raises(ValueError, match=r"^state must hold relay values \+1 or -1"):
        op(X, torch.zeros_like(good))


def test_the_functional_stop_model_names_state() -> None:
    weights = torch.ones(2, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^state must have shape \(2,\)"):
        stop_pi(X, W, weights, state=torch.zeros(5, dtype=torch.float64))
    with pytest.raises(ValueError, match="^state must be finite"):
        stop_pi(X, W, weights, state=torch.tensor([0.0, float("inf")], dtype=torch.float64))


def test_the_pi_inverse_names_its_input_x_and_checks_a_linear_models_state() -> None:
    inverse = torchhys.PrandtlIshlinskii(W, linear_weight=1.0).inverse()
    with pytest.raises(ValueError, match=r"^x must be finite"):
        inverse(torch.tensor([0.0, float("nan")], dtype=torch.float64))
    _, good = inverse(X)
    with pytest.raises(ValueError, match=r"^state must have shape"):
        inverse(X, torch.zeros(good.numel() + 5, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"^state must be finite"):
        inverse(X, torch.full_like(good, float("nan")))
    # a zero-width play is linear: the inverse of 0.5 x + 0.5 x has no play
    linear = torchhys.PrandtlIshlinskii(torch.tensor([0.0], dtype=torch.float64),
                                        torch.tensor([0.5], dtype=torch.float64),
                                        linear_weight=0.5).inverse()
    y, state = linear(X)
    torch.testing.assert_close(y, X, rtol=0, atol=1e-15)
    assert state.shape == (0,)
    linear(X, state)  # its own (empty) state is accepted
    with pytest.raises(ValueError, match=r"^state must have shape \(0,\)"):
        linear(X, torch.zeros(3, dtype=torch.float64))
