"""Bad input to torchhys.compose: one-line errors that name the node (or the argument) and
what was expected."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import torch
from _compose_models import make
from torch import nn

import torchhys
from torchhys.compose import compose
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.step import OperatorStep, StateBlock


def _module(forward: Callable, **layers: nn.Module) -> nn.Module:
    class User(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            for name, layer in layers.items():
                setattr(self, name, layer)

    User.forward = forward
    return User().double()


def _gru() -> nn.GRU:
    return nn.GRU(1, 2, batch_first=True)


BAD = {
    "cumsum": (_module(lambda s, x: x.cumsum(1)),
               r"^node 'cumsum' \(Tensor.cumsum\) mixes samples in time: .* not causal$"),
    "torch.cumsum": (_module(lambda s, x: torch.cumsum(x, 1) * 0.5),
                     r"^node 'cumsum' \(torch.cumsum\) mixes samples in time"),
    "flip": (_module(lambda s, x: s.lin(x.flip(1).unsqueeze(-1)).squeeze(-1),
                     lin=nn.Linear(1, 1)),
             r"^node 'flip' \(Tensor.flip\) mixes samples in time: its value at sample 0"),
    "mean over time": (_module(lambda s, x: x - x.mean(1, keepdim=True)),
                       r"^node 'mean' \(Tensor.mean\) mixes samples in time"),
    "convolution": (_module(lambda s, x: s.conv(x.unsqueeze(1)).squeeze(1),
                            conv=nn.Conv1d(1, 1, 3, padding=1)),
                    r"^node 'conv' \(Conv1d\) mixes samples in time"),
    "bidirectional": (_module(lambda s, x: s.rnn(x.unsqueeze(-1))[0].sum(-1),
                              rnn=nn.LSTM(1, 2, batch_first=True, bidirectional=True)),
                      r"^node 'rnn' \(LSTM\) cannot stream: LSTM is bidirectional: .*not "
                      r"causal; use bidirectional=False$"),
    "projection": (_module(lambda s, x: s.rnn(x.unsqueeze(-1))[0].sum(-1),
                           rnn=nn.LSTM(1, 3, proj_size=1, batch_first=True)),
                   r"^node 'rnn' \(LSTM\) cannot stream: LSTM has proj_size=1"),
    "returned (h, c)": (_module(lambda s, x: s.rnn(x.unsqueeze(-1))[1][0][-1] + x,
                                rnn=nn.LSTM(1, 2, batch_first=True)),
                        r"^node 'rnn' \(LSTM\): only its output \(rnn\(u\)\[0\]\) may be "
                        r"used, not its returned \(h, c\)"),
    "initial state": (_module(lambda s, x: s.rnn(x.unsqueeze(-1), torch.zeros(
        1, x.shape[0], 2, dtype=x.dtype))[0].sum(-1), rnn=_gru()),
        r"^node 'rnn' \(GRU\) must be called on its input alone"),
    "cell": (_module(lambda s, x: s.cell(x)[0], cell=nn.LSTMCell(16, 2)),
             r"^node 'cell' \(LSTMCell\) cannot stream: a cell the module would loop over"),
    "attention": (_module(lambda s, x: s.att(x.unsqueeze(-1), x.unsqueeze(-1),
                                             x.unsqueeze(-1))[0].squeeze(-1),
                          att=nn.MultiheadAttention(1, 1, batch_first=True)),
                  r"^node 'att' \(MultiheadAttention\) cannot stream: attention"),
    "output shape": (_module(lambda s, x: s.rnn(x.unsqueeze(-1))[0], rnn=_gru()),
                     r"^User must map x \(batch, time\) to y \(batch, time\): on x of shape "
                     r"\(2, 16\) it returned \(2, 16, 2\)$"),
    "operator input": (_module(lambda s, x: s.bl(x.unsqueeze(-1))[0].sum(-1),
                               bl=torchhys.Backlash(torch.tensor([0.1]))),
                       r"^node 'bl' \(Backlash\) failed on an example x of shape \(2, 16\): "
                       r"ValueError: x must have shape"),
    "recurrent input": (_module(lambda s, x: s.rnn(x.unsqueeze(-1).transpose(0, 1))[0].sum(-1),
                                rnn=_gru()),
                        r"^node 'rnn' \(GRU\) expects its input of shape \(2, 16, 1\) "
                        r"\(batch_first=True\) on x of shape \(2, 16\), got \(16, 2, 1\)$"),
    "linear width": (_module(lambda s, x: s.lin(torch.stack([x, x], -1)).squeeze(-1),
                             lin=nn.Linear(3, 1)),
                     r"^node 'lin' \(Linear\) failed on an example x of shape \(2, 16\): "
                     r"RuntimeError: mat1 and mat2 shapes cannot be multiplied"),
    "control flow": (_module(lambda s, x: x if x.sum() > 0 else -x),
                     r"^User cannot be traced by torch.fx \(TraceError: .*\): its forward must "
                     r"not branch on or iterate over tensor values$"),
}


@pytest.mark.parametrize("case", BAD)
def test_bad_modules_are_refused_naming_the_node(case):
    module, match = BAD[case]
    with pytest.raises(ValueError, match=match) as info:
        compose(module)
    assert "\n" not in str(info.value)


@pytest.mark.filterwarnings("ignore::torchhys.operators.eiho_segment.NonCausalWarning")
def test_a_non_causal_operator_is_refused():
    module = _module(lambda s, x: s.op(x)[0], op=torchhys.SegmentEIHO())
    with pytest.raises(ValueError, match=r"^node 'op' \(SegmentEIHO\) is not causal"):
        compose(module)


def test_more_inputs_and_no_module_are_refused():
    class Two(nn.Module):
        def forward(self, x, z):
            return x + z

    with pytest.raises(ValueError, match=r"^Two.forward must take one input x \(batch, time\), "
                       r"got 2 \(x, z\)$"):
        compose(Two())
    with pytest.raises(TypeError, match=r"^module must be an nn.Module, got function$"):
        compose(lambda x: x)
    with pytest.raises(ValueError, match=r"x and y must be given together"):
        compose(make("backlash_lstm"), x=torch.zeros(1, 4, dtype=torch.float64))


class _NoStep(torchhys.HysteresisOperator):
    def forward(self, x, state=None):
        return x, None

    def streaming_step(self, dtype):
        raise NotImplementedError


class _NotAStep(_NoStep):
    def streaming_step(self, dtype):
        return nn.Identity()


def test_a_leaf_without_a_step_is_refused_naming_its_class():
    with pytest.raises(TypeError, match=r"^node 'op' \(_NoStep\) has no step "
                       r"\(_NoStep.streaming_step is not implemented\): give it "
                       r"streaming_step\(dtype\)"):
        compose(_module(lambda s, x: s.op(x)[0], op=_NoStep()))
    with pytest.raises(TypeError, match=r"^node 'op' \(_NotAStep\): its step must be a "
                       r"torchhys.step.OperatorStep, got Identity$"):
        compose(_module(lambda s, x: s.op(x)[0], op=_NotAStep()))


def test_a_wrong_state_given_to_the_composed_step():
    step = compose(make("backlash_lstm")).composed_step(torch.float64)
    x = torch.zeros(3, 1, dtype=torch.float64)
    good = step.initial_state(x)
    with pytest.raises(ValueError, match=r"^ComposedStep: state must be the list of 3 "
                       r"tensor\(s\) of its state_spec, got 2 item\(s\)$"):
        step(x, good[:2])
    bad = [good[0], torch.zeros(3, 7, dtype=torch.float64), good[2]]
    with pytest.raises(ValueError, match=r"^ComposedStep: state\[1\] \(block 'lstm.h'\) must "
                       r"have shape \(3, 8\), got \(3, 7\)$"):
        step(x, bad)
    with pytest.raises(ValueError, match=r"state\[0\] \(block 'bl.plays'\) must be floating "
                       r"point, got torch.int64"):
        step(x, [good[0].long(), good[1], good[2]])
    with pytest.raises(ValueError, match=r"^ComposedStep: x must have shape \(batch, 1\), got "
                       r"\(3, 2\)$"):
        step(torch.zeros(3, 2, dtype=torch.float64), good)


def test_the_compensator_refuses_a_step_of_several_inputs():
    class Deployable(nn.Module):
        def streaming_steps(self, dtype):
            return [torchhys.compose.LSTMStep(nn.LSTM(2, 3), dtype)]

        def streaming_head(self, dtype):
            return nn.Identity()

    with pytest.raises(TypeError, match=r"^streaming step 0 \(LSTMStep\) takes 2 input "
                       r"column\(s\), expected 1"):
        StreamingCompensator(Deployable(), limits=(-1.0, 1.0))


def test_a_step_of_several_inputs_needs_its_own_start_from_the_sample():
    class Anchored(OperatorStep):
        n_inputs = 2

        def __init__(self):
            super().__init__()
            self.n_outputs = 1
            self.state_spec = [StateBlock("s", 1, from_sample=1.0)]

        def forward(self, x, state):
            return x[:, :1], state

    with pytest.raises(ValueError, match=r"block 's' starts from the sample .* 2 inputs: "
                       r"override initial_state"):
        Anchored().initial_state(torch.zeros(1, 2))


class _OffBacklash(torchhys.Backlash):
    """A play whose step's half-width is 1e-9 wider than its forward's: the module and its
    step differ by up to 1e-9 (inside compose's own check, outside the suite's 1e-12)."""

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        step = super().streaming_step(dtype)
        with torch.no_grad():
            step.r.add_(1e-9)
        return step


class _Off(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.bl = _OffBacklash(torch.tensor([0.3]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.bl(x)[0].squeeze(-1)


def test_check_composed_fails_a_step_that_is_not_the_module() -> None:
    from torchhys.testing import check_composed

    with pytest.raises(AssertionError, match=r"^composed model _Off fails the check 'step' "
                                             r"\(.*\): the composed step sample by sample "
                                             r"against the module"):
        check_composed(lambda: _Off().double(), checks=["step"])
    assert check_composed(lambda: _Off().double(), checks=["chunked"]) == {"chunked": None}


def test_check_composed_float32_and_a_module_given_built() -> None:
    """A module given built (each check composes a copy), in float32: gradcheck does not
    apply; the module itself is left as it was."""
    from _compose_models import make

    from torchhys.testing import COMPOSED_CHECKS, COMPOSED_COMPILE_CHECKS, check_composed

    module = make("parallel_gru")
    before = {k: v.clone() for k, v in module.state_dict().items()}
    result = check_composed(module, dtype=torch.float32)
    assert list(result) == [c for c in COMPOSED_CHECKS if c not in COMPOSED_COMPILE_CHECKS]
    assert result["gradcheck"] == "gradcheck runs in float64"
    assert all(why is None for c, why in result.items() if c != "gradcheck")
    assert all(torch.equal(v, before[k]) for k, v in module.state_dict().items())
    assert next(module.parameters()).dtype == torch.float64


@pytest.mark.parametrize("kwargs, error, message", [
    ({"checks": ["nope"]}, ValueError, r"^checks must be names of torchhys.testing."
                                       r"COMPOSED_CHECKS \[.*\], got \['nope'\]$"),
    ({"checks": "step"}, ValueError, r"^checks must be names of .*, got 'step'$"),
    ({"dtype": torch.float16}, ValueError, r"^dtype must be torch.float32 or torch.float64"),
    ({"model": 3}, TypeError, r"^model must be an nn.Module, an Example or a function that "
                              r"builds one, got int$"),
])
def test_check_composed_refuses_bad_arguments(kwargs: dict, error: type, message: str) -> None:
    from torchhys.testing import check_composed

    args = {"model": lambda: _Off().double(), **kwargs}
    with pytest.raises(error, match=message):
        check_composed(args.pop("model"), **args)


def test_check_composed_takes_an_example() -> None:
    """An Example of a composition: its atol and no_gradcheck (the reason returned)."""
    from _compose_models import CONFORMANCE

    from torchhys.testing import Example, check_composed

    example = Example(CONFORMANCE["parallel_gru"], atol=1e-12, no_gradcheck="not smooth")
    assert check_composed(example, checks=["step", "gradcheck"]) == {
        "step": None, "gradcheck": "not smooth"}
