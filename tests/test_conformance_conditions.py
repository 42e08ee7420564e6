"""The conditioned models through the conformance checks of models with operating conditions
(torchhys.testing.check_conditioned, CONDITIONED_CHECKS): the scheduled readout, the network
with conditions, and the conditioned play and Jiles-Atherton operators under an affine
readout (tests/test_conditions_play.PlayModel), one test a check and a model. Besides: the
checks fail on a model whose step is not its forward, on an unfitted model, at a kink in x,
on a NaN condition not held, and on an export's other commands or counters; bad arguments;
AOTInductor's check (slow, one compile); and the compensator's state shapes, which
step_explicit checks."""

# no `from __future__ import annotations`: test_conditions_play's head is scripted

import sys
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

import torchhys
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.testing import (
    CONDITIONED_CHECKS,
    CONDITIONED_COMPILE_CHECKS,
    check_conditioned,
)

sys.path.insert(0, str(Path(__file__).parent))
import test_conditions as scheduled  # noqa: E402
import test_conditions_network as network  # noqa: E402
import test_conditions_play as play  # noqa: E402

DT = torch.float64


def _scheduled() -> tuple[nn.Module, Tensor, Tensor]:
    x, c, y = scheduled._record()
    return scheduled._model().fit(x, c, y), x[:, 1:], c[:, 1:]  # x[:, 0] = 0: the plays' start


def _network() -> tuple[nn.Module, Tensor, Tensor]:
    net, x, c, _ = network._fitted(2)
    return net, x[:, 1:201], c[:, 1:201]


def _play() -> tuple[nn.Module, Tensor, Tensor]:
    m, x = play._model(2)
    return m, x[..., 0], x[..., 1:]


def _jiles_atherton() -> tuple[nn.Module, Tensor, Tensor]:
    import test_conditions_jiles_atherton as ja
    x = play._signal(B=3, T=200, n=2)
    return play.PlayModel(ja._op(2, 2, x=x)), x[..., 0], x[..., 1:]


MODELS: dict[str, Callable[[], tuple[nn.Module, Tensor, Tensor]]] = {
    "scheduled_readout": _scheduled,
    "network": _network,
    "conditioned_backlash": _play,
    "conditioned_jiles_atherton": _jiles_atherton,
}
"""Each conditioned model: a fitted model (two conditions for the operators), its x and
conditions."""
DEFAULT = [c for c in CONDITIONED_CHECKS if c not in CONDITIONED_COMPILE_CHECKS]


@pytest.fixture(scope="module")
def built() -> dict:
    return {name: make() for name, make in MODELS.items()}


@pytest.mark.parametrize("check", DEFAULT)
@pytest.mark.parametrize("name", list(MODELS))
def test_conditioned_conformance(name: str, check: str, built: dict) -> None:
    model, x, c = built[name]
    got = check_conditioned(model, x, c, checks=[check])
    skips = {"c": "no C compiler", "onnx": "ONNX Runtime parity needs"}
    if check in skips and got[check] is not None:
        assert got[check].startswith(skips[check])
        pytest.skip(got[check])
    assert got == {check: None}


@pytest.mark.slow
def test_aoti_conformance_of_the_conditioned_play(built: dict) -> None:
    """One compile (batch 3, two conditions): the package against the torch compensator."""
    model, x, c = built["conditioned_backlash"]
    assert check_conditioned(model, x, c, checks=["aoti"]) == {"aoti": None}


def test_a_builder_is_called_for_each_check() -> None:
    calls = []
    model, x, c = _scheduled()

    def build() -> nn.Module:
        calls.append(1)
        return model
    assert check_conditioned(build, x, c, checks=["protocol", "step"]) == dict.fromkeys(
        ["protocol", "step"])
    assert len(calls) == 2  # one a check


# --- the checks can fail -------------------------------------------------------------------


class _Scaled(nn.Module):
    def __init__(self, head: nn.Module) -> None:
        super().__init__()
        self.head = head

    def forward(self, z: Tensor) -> Tensor:
        return self.head(z) * (1 + 1e-9)


class _OffHead(torchhys.conditions.ScheduledReadout):
    """A scheduled readout whose streaming head is off by a relative 1e-9."""

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        return _Scaled(super().streaming_head(dtype))


def test_the_step_check_fails_on_a_step_that_is_not_the_model() -> None:
    x, c, y = scheduled._record()
    ops = [torchhys.Backlash(torch.linspace(0.0, 0.4, 6, dtype=DT))]
    off = _OffHead(ops, 1, degree=2, ridge=0.0).to(DT).fit(x, c, y)
    with pytest.raises(AssertionError, match=r"fails the check 'step' .* against the model's "
                       r"sequence output"):
        check_conditioned(off, x[:, 1:], c[:, 1:], checks=["step"])
    # the exports are the compensator's: they still agree with it
    assert check_conditioned(off, x[:, 1:], c[:, 1:], checks=["torchscript"]) == {
        "torchscript": None}


def test_the_protocol_check_fails_on_an_unfitted_model() -> None:
    _, x, c = _scheduled()
    with pytest.raises(AssertionError, match=r"fails the check 'protocol'.*cond_min must be "
                       r"a finite tensor"):
        check_conditioned(scheduled._model(), x, c, checks=["protocol"])


def test_gradcheck_in_x_sees_the_plays_start_and_no_gradcheck_x_skips_it() -> None:
    """At x[0] = 0 the plays start on a tie (their start is 0): gradcheck in x fails there,
    in the conditions it holds."""
    x, c, y = scheduled._record()
    m = scheduled._model().fit(x, c, y)
    with pytest.raises(AssertionError, match=r"fails the check 'gradcheck'.*Jacobian mismatch"):
        check_conditioned(m, x, c, checks=["gradcheck"])
    got = check_conditioned(m, x, c, checks=["gradcheck"], no_gradcheck_x="the plays' start")
    assert got == {"gradcheck": "gradcheck in the conditions only: the plays' start"}


def test_the_nan_check_fails_when_a_nan_condition_is_not_held() -> None:
    """A head that reads a NaN condition as 0 would give a finite command; the compensator
    holds it still (its test is on the conditions): the check holds, and it fails for a
    compensator that ignores the conditions' finiteness, simulated by patching its step."""
    model, x, c = _scheduled()
    assert check_conditioned(model, x, c, checks=["nan"]) == {"nan": None}

    original = StreamingCompensator._advance

    def finite(self, xt, state, conditions):  # the conditions' NaN replaced by 0
        return original(self, xt, state, torch.nan_to_num(conditions, nan=0.0, posinf=0.0))
    try:
        StreamingCompensator._advance = finite
        with pytest.raises(AssertionError, match=r"fails the check 'nan'.*a NaN in condition"):
            check_conditioned(model, x, c, checks=["nan"])
    finally:
        StreamingCompensator._advance = original


def test_the_export_comparison_fails_on_other_commands_or_counters() -> None:
    """The parity checks' comparison (the C, ONNX, TorchScript and AOTI checks share it): a
    step off by a relative 1e-11, or a counter off by one, fails."""
    import torchhys._conformance_conditions as conditioned
    model, x, c = _scheduled()
    case = conditioned.ConditionedCase("m", lambda: model, x, c, 1e-12, None)

    def torch_run(xs: Tensor, cs: Tensor) -> tuple:
        return conditioned.stepped(StreamingCompensator(model, **conditioned.EXPORT), xs, cs)
    conditioned._against(case, model, torch_run, "the same compensator")
    off = [lambda xs, cs: (torch_run(xs, cs)[0] * (1 + 1e-11), *torch_run(xs, cs)[1:]),
           lambda xs, cs: (torch_run(xs, cs)[0], [v + 1 for v in torch_run(xs, cs)[1]],
                           torch_run(xs, cs)[2])]
    for run, message in zip(off, [r"a step against the torch compensator", r"counters"],
                            strict=True):
        with pytest.raises(AssertionError, match=message):
            conditioned._against(case, model, run, "a step")


def test_bad_arguments_are_one_line_errors() -> None:
    model, x, c = _scheduled()
    cases = [
        (lambda: check_conditioned(model, x, c, checks=["gpu"]), ValueError,
         r"^checks must be names of torchhys\.testing\.CONDITIONED_CHECKS"),
        (lambda: check_conditioned(model, x, c, checks="step"), ValueError, r"^checks must"),
        (lambda: check_conditioned(model, x.float(), c), TypeError, r"^x must be float64"),
        (lambda: check_conditioned(model, x, c[..., 0]), ValueError, r"^conditions must be "
                                                                     r"finite of shape"),
        (lambda: check_conditioned(model, x, c[:, :50]), ValueError, r"^conditions must have "
                                                                     r"shape"),
        (lambda: check_conditioned(model, x[:, :20], c[:, :20]), ValueError, r"time >= 40"),
        (lambda: check_conditioned("model", x, c), TypeError, r"^model must be an nn\.Module"),
    ]
    for call, error, message in cases:
        with pytest.raises(error, match=message) as info:
            call()
        assert "\n" not in str(info.value)


def test_a_compensator_state_of_another_shape_is_a_one_line_error_naming_state() -> None:
    model, x, c = _scheduled()
    comp = StreamingCompensator(model, direction="none")
    state = comp.initial_state(x.shape[0])
    wide = [torch.zeros(x.shape[0], state[0].shape[1] + 1, dtype=state[0].dtype), *state[1:]]
    for bad in (wide, [s[:2] for s in state]):
        try:
            comp.step_explicit(x[:, 0], bad, c[:, 0])
        except ValueError as e:
            assert str(e).startswith("step_explicit: state") and "\n" not in str(e)
            continue
        except RuntimeError as e:
            raise AssertionError(f"not a ValueError naming state: {e}") from e
        raise AssertionError("no error")
