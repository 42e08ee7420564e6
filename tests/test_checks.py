"""The shared input checks: ints, choices, equal shapes (accepted values and messages)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from torchhys._checks import (
    as_batched_sequence,
    check_bool,
    check_choice,
    check_int,
    check_same_shape,
)


@pytest.mark.parametrize("value, minimum", [(0, None), (-5, None), (3, 3), (10, 3), (0, 0)])
def test_int_accepts_and_returns(value: int, minimum: int | None) -> None:
    assert check_int(value, "n", minimum=minimum) is value


@pytest.mark.parametrize("value, minimum, match", [
    (2, 3, r"^max_depth must be an int >= 3, got 2$"),
    (-1, 0, r"^max_depth must be an int >= 0, got -1$"),
    (True, None, r"^max_depth must be an int, got True$"),  # a bool is not an int here
    (False, 0, r"^max_depth must be an int >= 0, got False$"),
    (3.0, 3, r"^max_depth must be an int >= 3, got 3.0$"),
    ("4", None, r"^max_depth must be an int, got '4'$"),
    (None, 1, r"^max_depth must be an int >= 1, got None$"),
    (torch.tensor(4), 3, r"^max_depth must be an int >= 3, got tensor\(4\)$"),
])
def test_int_rejects(value: object, minimum: int | None, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        check_int(value, "max_depth", minimum=minimum)


def test_choice_accepts_and_returns() -> None:
    assert check_choice("b", "mode", ("a", "b")) == "b"
    assert check_choice(None, "schedule", (None, "cosine")) is None
    assert check_choice("y", "key", {"x": 1, "y": 2}) == "y"  # a dict: its keys
    assert check_choice("y", "key", iter(["x", "y"])) == "y"  # any iterable, read once


@pytest.mark.parametrize("value", ["c", "A", "", None, ["a"], np.array([1, 2]), torch.ones(2)])
def test_choice_rejects_and_lists_the_choices(value: object) -> None:
    with pytest.raises(ValueError, match=r"^mode must be one of \['a', 'b'\], got ") as info:
        check_choice(value, "mode", ("a", "b"))
    assert str(info.value).endswith(repr(value))


def test_same_shape() -> None:
    check_same_shape(torch.zeros(2, 5), torch.ones(2, 5), "y", "x")
    with pytest.raises(ValueError, match=r"^y must have the shape of x \(2, 5\), got shape "
                                         r"\(2, 4\)$"):
        check_same_shape(torch.zeros(2, 4), torch.zeros(2, 5), "y", "x")
    with pytest.raises(ValueError, match=r"x \(5,\), got shape \(1, 5\)"):
        check_same_shape(torch.zeros(1, 5), torch.zeros(5), "y", "x")  # no broadcasting


def test_bool_accepts_only_bools() -> None:
    assert check_bool(True, "flag") is True and check_bool(False, "flag") is False
    assert check_bool(np.bool_(True), "flag") is True
    assert check_bool(torch.tensor(False), "flag") is False
    for bad in ("false", 0, 1.0, None, torch.tensor([True, False])):
        with pytest.raises(TypeError,
                           match=f"flag must be True or False, got .*{re.escape(repr(bad))}"):
            check_bool(bad, "flag")


def test_a_sequence_needs_a_row_and_a_sample() -> None:
    with pytest.raises(ValueError, match=r"x must hold at least one row, got shape \(0, 5\)"):
        as_batched_sequence(torch.zeros(0, 5))
    with pytest.raises(ValueError, match=r"x must hold at least one sample"):
        as_batched_sequence(torch.zeros(2, 0))
