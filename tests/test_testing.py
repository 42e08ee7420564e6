"""torchhys.testing: the conformance checks as a function, for one operator.

tests/test_conformance.py runs them over the registry; here: they fail on operators broken
on purpose (naming the check), they take a class, an instance or a name, and their options
are checked."""
from __future__ import annotations

import pytest
import torch
from torch import Tensor

from torchhys import Backlash, SegmentEIHO
from torchhys.operators.backlash import PlayStep
from torchhys.registry import register_operator
from torchhys.step import OperatorStep
from torchhys.testing import (
    CHECKS,
    COMPILE_CHECKS,
    DEFAULT_CHECKS,
    Example,
    check_conformance,
    example_of,
)

WIDTHS = [0.0, 0.3, 0.8]


class _Shifted(OperatorStep):
    """A play step whose output is 1e-3 off its sequence path."""

    def __init__(self, step: PlayStep) -> None:
        super().__init__()
        self.step, self.n_outputs, self.state_spec = step, step.n_outputs, step.state_spec

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        y, new = self.step(x, state)
        return y + 1e-3, new


class OffStep(Backlash):
    """Plays whose step disagrees with their sequence."""

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return _Shifted(super().streaming_step(dtype))


class Forgetful(Backlash):
    """Plays that drop the state they are given: chunked calls restart."""

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        return super().forward(x, None)


class NaNTolerant(Backlash):
    """Plays that take a NaN input silently (no error naming x)."""

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        if isinstance(x, Tensor):
            x = torch.nan_to_num(x)
        return super().forward(x, state)


def example(cls: type) -> Example:
    return Example(lambda: cls(torch.tensor(WIDTHS, dtype=torch.float64)),
                   bad_values={"fixed_widths": -1.0})


def test_a_sound_operator_passes_every_default_check() -> None:
    result = check_conformance(Backlash, example(Backlash))
    assert result == dict.fromkeys(DEFAULT_CHECKS)  # None: held
    assert list(result) == [c for c in CHECKS if c not in COMPILE_CHECKS]


@pytest.mark.parametrize("cls, check, what", [
    (OffStep, "step", "the step run sample by sample against forward"),
    (Forgetful, "chunked", "in chunks of 1, 1, 2, 27 and the rest"),
    (NaNTolerant, "bad_input", r"a bad input x \(nan\): no ValueError raised"),
])
def test_a_broken_operator_fails_naming_the_check(cls: type, check: str, what: str) -> None:
    with pytest.raises(AssertionError, match=rf"^operator {cls.__name__} fails the check "
                       rf"{check!r} \(.*\).*: .*{what}"):
        check_conformance(cls, example(cls))
    others = ["protocol", "wrong_shape", "bad_value"]  # what the fault does not touch
    assert check_conformance(cls, example(cls), checks=others) == dict.fromkeys(others)


def test_the_step_check_fails_in_each_kernel_mode_it_runs() -> None:
    """The kernel modes are named: the scans always run."""
    with pytest.raises(AssertionError, match=r"'step' .* with (the compiled kernels|the scans)"):
        check_conformance(OffStep, example(OffStep), checks=["step"])


def test_a_name_an_instance_and_float32() -> None:
    assert check_conformance("backlash", checks=["protocol", "step"]) == {"protocol": None,
                                                                           "step": None}
    op = Backlash(torch.tensor(WIDTHS, dtype=torch.float64))
    assert check_conformance(op, checks=["chunked", "bad_value"]) == {
        "chunked": None, "bad_value": "the example declares no bad_values"}
    result = check_conformance("backlash", dtype=torch.float32,
                               checks=["chunked", "step", "gradcheck", "torchscript"])
    assert result == {"chunked": None, "step": None, "gradcheck": "gradcheck runs in float64",
                      "torchscript": None}


@pytest.mark.filterwarnings("ignore::torchhys.functional.NonCausalWarning")
def test_a_non_causal_operator_is_skipped_with_the_reason() -> None:
    result = check_conformance(SegmentEIHO, checks=["chunked", "step"])
    assert set(result) == {"chunked", "step"}
    assert all("not causal" in why for why in result.values())


def test_bad_options_are_one_line_errors() -> None:
    with pytest.raises(ValueError, match=r"^operator: no operator is registered as 'nope'"):
        check_conformance("nope")
    with pytest.raises(ValueError, match=r"^checks must be names of torchhys\.testing\.CHECKS"):
        check_conformance("backlash", checks=["stepp"])
    with pytest.raises(ValueError, match=r"^checks must be names"):
        check_conformance("backlash", checks="step")
    with pytest.raises(ValueError, match=r"^dtype must be torch\.float32 or torch\.float64"):
        check_conformance("backlash", dtype=torch.float16)
    with pytest.raises(TypeError, match=r"^operator must be a registered name"):
        check_conformance(3)
    with pytest.raises(TypeError, match=r"^example must be an Example or a function"):
        check_conformance("backlash", example=3)


def test_an_example_builds_when_called_and_the_registry_keeps_it_as_given() -> None:
    ex = example_of("backlash")
    assert isinstance(ex, Example) and isinstance(ex(), Backlash)
    assert ex.bad_values == {"fixed_widths": -1.0}
    with pytest.raises(TypeError, match=r"^example must be an Example or a function"):
        register_operator("backlash", Backlash, example=3)
    with pytest.raises(KeyError, match="no operator is registered as 'nope'"):
        example_of("nope")
