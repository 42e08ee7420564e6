"""Bad input to the linear dynamics: each a TypeError or ValueError that names the argument."""

from __future__ import annotations

import math

import pytest
import torch

from torchhys.dynamics import StateSpace, TransferFunction
from torchhys.functional.linear_filter import lfilter, linear_recurrence, state_space
from torchhys.registry import make_operator

X = torch.randn(2, 20, dtype=torch.float64)
B = torch.tensor([0.2, 0.3, -0.1], dtype=torch.float64)
A = torch.tensor([1.0, -1.5, 0.7], dtype=torch.float64)


def _with(value: float, index: tuple[int, ...] = (1, 5)) -> torch.Tensor:
    x = X.clone()
    x[index] = value
    return x


@pytest.mark.parametrize("kwargs,error,match", [
    ({"x": X.tolist()}, TypeError, "x must be a torch.Tensor"),
    ({"x": X.long()}, TypeError, "x must have a floating-point dtype"),
    ({"x": torch.tensor(1.0)}, ValueError, r"x must have shape \(\.\.\., time\)"),
    ({"x": X[:, :0]}, ValueError, "time >= 1"),
    ({"x": _with(math.nan)}, ValueError, r"x must be finite.*\(1, 5\)"),
    ({"x": _with(math.inf)}, ValueError, "x must be finite"),
    ({"b": B[None]}, ValueError, r"b must have shape \(length,\)"),
    ({"b": B[:0]}, ValueError, "b must have shape"),
    ({"b": B.long()}, TypeError, "b must have a floating-point dtype"),
    ({"a": torch.tensor([1.0, math.nan])}, ValueError, "a must be finite"),
    ({"a": torch.tensor([0.0, 1.0, 0.5])}, ValueError, r"a\[0\] must be non-zero"),
    ({"state": torch.zeros(3, 2)}, ValueError,
     r"state must have shape \(2,\) or \(2, 2\).*\(3, 2\)"),
    ({"state": torch.full((2,), math.inf)}, ValueError, "state must be finite"),
    ({"state": [0.0, 0.0]}, TypeError, "state must be a torch.Tensor"),
])
def test_lfilter(kwargs, error, match):
    args = {"x": X, "b": B, "a": A, "state": None} | kwargs
    with pytest.raises(error, match=match):
        lfilter(args["x"], args["b"], args["a"], state=args["state"])


def test_linear_recurrence_and_state_space():
    w = torch.randn(2, 10, 3, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"A must have shape \(3, 3\), got shape \(3, 2\)"):
        linear_recurrence(torch.zeros(3, 2, dtype=torch.float64), w)
    with pytest.raises(ValueError, match=r"w must have shape \(\.\.\., time, n\)"):
        linear_recurrence(torch.zeros(3, 3), w[0, :, 0])
    with pytest.raises(ValueError, match=r"state must have shape \(3,\) or \(2, 3\)"):
        linear_recurrence(torch.zeros(3, 3), w, state=torch.zeros(4))
    Am, Bv, C, D = torch.zeros(3, 3), torch.zeros(3), torch.zeros(2, 3), torch.zeros(2)
    with pytest.raises(ValueError, match="A must be a matrix"):
        state_space(X, Bv, Bv, C, D)
    with pytest.raises(ValueError, match=r"B must have shape \(3,\)"):
        state_space(X, Am, torch.zeros(2), C, D)
    with pytest.raises(ValueError, match=r"C must have shape \(2, 3\)"):
        state_space(X, Am, Bv, torch.zeros(2, 2), D)
    with pytest.raises(ValueError, match=r"D must have shape \(2,\)"):
        state_space(X, Am, Bv, C, torch.zeros(3))


@pytest.mark.parametrize("order", [0, -1, True, 2.0, "2"])
def test_transfer_function_order(order):
    with pytest.raises(ValueError, match="order must be an int >= 1"):
        TransferFunction(order)


@pytest.mark.parametrize("radius", [0.0, 1.0, 1.5, -0.5, True, "0.9"])
def test_radius_outside_the_unit_interval(radius):
    with pytest.raises(ValueError, match=r"max_pole_radius must be a float in \(0, 1\)"):
        TransferFunction(2, max_pole_radius=radius)
    with pytest.raises(ValueError, match=r"max_norm must be a float in \(0, 1\)"):
        StateSpace(2, max_norm=radius)


@pytest.mark.parametrize("b,a,kwargs,match", [
    ([1.0], [1.0, -2.5, 1.0], {}, "not stable: it has a pole of magnitude 2 "),
    ([1.0], [1.0, -1.0], {}, "pole of magnitude 1 "),
    ([1.0, 0.5], [1.0, 0.0, 1.0], {}, "pole of magnitude 1 "),
    ([1.0, 0.5], [0.0, 1.0, 0.5], {}, r"a\[0\] must be non-zero.*non-causal"),
    ([2.0], [1.0], {}, "order = max.*must be >= 1"),
    ([0.5, 0.2], [1.0, -0.5], {"feedthrough": False}, r"b\[0\] must be 0 without feedthrough"),
    ([0.5, math.nan], [1.0, -0.5], {}, "b must be finite"),
    ([[0.5, 0.2]], [1.0, -0.5], {}, "b must be non-empty with 1 dimension"),
    ([], [1.0, -0.5], {}, "b must be non-empty"),
    ([1.0], [1.0, -0.9], {"max_pole_radius": 0.8}, "max_pole_radius must exceed .* 0.9"),
])
def test_transfer_function_from_coefficients(b, a, kwargs, match):
    with pytest.raises(ValueError, match=match):
        TransferFunction.from_coefficients(b, a, **kwargs)


def test_forward_takes_a_tensor_state():  # other bad input: tests/test_conformance.py
    for block in (TransferFunction(2).double(), StateSpace(2).double()):
        with pytest.raises(TypeError, match="state must be a torch.Tensor or None"):
            block(X, [0.0, 0.0])


def test_state_space_construction():
    with pytest.raises(ValueError, match="n_states must be an int >= 1"):
        StateSpace(0)
    with pytest.raises(ValueError, match="n_outputs must be an int >= 1"):
        StateSpace(2, 0)
    good = dict(A=[[0.5, 0.0], [0.0, 0.2]], B=[1.0, 0.0], C=[[1.0, 1.0]])
    with pytest.raises(ValueError, match="not stable: it has an eigenvalue of magnitude 1.1"):
        StateSpace.from_matrices(**good | {"A": [[1.1, 0.0], [0.0, 0.2]]})
    with pytest.raises(ValueError, match=r"shapes \(n, n\), \(n,\), \(p, n\), \(p,\)"):
        StateSpace.from_matrices(**good | {"B": [1.0, 0.0, 0.0]})
    with pytest.raises(ValueError, match="A must be finite"):
        StateSpace.from_matrices(**good | {"A": [[math.nan, 0.0], [0.0, 0.2]]})
    with pytest.raises(ValueError, match="max_norm must be at least"):
        StateSpace.from_matrices(**good, max_norm=0.3)


def test_unknown_option_by_name():
    with pytest.raises(ValueError, match="operator 'transfer_function'.*poles"):
        make_operator("transfer_function", poles=3)
