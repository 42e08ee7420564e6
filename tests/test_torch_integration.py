"""torchhys inside a torch model under torch's own tools: no graph break inside torchhys's
code (``torch._dynamo.explain``) for the learnable Backlash + PrandtlIshlinskii + nn.LSTM
model, and the torch checks of :func:`torchhys.testing.check_conformance` as a plugin author
runs them (a defect is caught and named, a documented refusal of double backward is held to
its word). The per-operator matrix of those checks is ``tests/test_conformance.py``'s;
``docs/torch_integration.md`` says what each covers."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import Tensor, nn

import torchhys
from torchhys import Backlash, HysteresisOperator, PrandtlIshlinskii
from torchhys.step import OperatorStep, StateBlock
from torchhys.testing import CHECKS, COMPILE_CHECKS, TORCH_CHECKS, Example, check_conformance

PACKAGE = str(Path(torchhys.__file__).resolve().parent)


class OperatorsLSTM(nn.Module):
    """The model of the issue: a learnable Backlash and PrandtlIshlinskii feeding an LSTM."""

    def __init__(self) -> None:
        super().__init__()
        widths = torch.linspace(0.05, 0.8, 4, dtype=torch.float64)
        self.backlash = Backlash(widths, learnable=True)
        self.pi = PrandtlIshlinskii(widths, learnable=True)
        self.lstm = nn.LSTM(6, 5, batch_first=True, dtype=torch.float64)
        self.readout = nn.Linear(5, 1, dtype=torch.float64)

    def forward(self, x: Tensor) -> Tensor:
        plays, _ = self.backlash(x)
        pi, _ = self.pi(x)
        h, _ = self.lstm(torch.cat([x[..., None], plays, pi[..., None]], -1))
        return self.readout(h)[..., 0]


def _x(T: int = 12) -> Tensor:
    t = torch.linspace(0, 1, T, dtype=torch.float64)
    return torch.stack([0.9 * torch.sin(12 * t), 0.5 * torch.cos(7 * t) * t])


def test_no_graph_break_inside_torchhys() -> None:
    """``torch._dynamo.explain`` of the operators + LSTM model: no graph break whose stack
    passes through torchhys; by default Dynamo stops at ``nn.LSTM`` itself (torch's
    "step_unsupported": the only break, in torch's code)."""
    torch.manual_seed(0)
    model, x = OperatorsLSTM(), _x()
    torch._dynamo.reset()
    explanation = torch._dynamo.explain(model)(x)
    ours = [r for r in explanation.break_reasons
            if any(f.filename.startswith(PACKAGE) for f in r.user_stack)]
    assert not ours, "graph breaks inside torchhys: " + "; ".join(
        f"{r.reason} at {r.user_stack[-1].filename}:{r.user_stack[-1].lineno}" for r in ours)
    assert [r.reason for r in explanation.break_reasons] == ["step_unsupported"]
    torch._dynamo.reset()


@pytest.mark.slow
def test_the_operators_and_lstm_model_is_one_graph_with_rnn_support() -> None:
    """With torch's RNN support on (``torch._dynamo.config.allow_rnn``) the operators + LSTM
    model is one graph, ``fullgraph=True`` compiles it (AOTAutograd), and its output and
    gradients equal eager's."""
    torch.manual_seed(0)
    model, x = OperatorsLSTM(), _x()
    torch._dynamo.reset()
    with torch._dynamo.config.patch(allow_rnn=True):
        explanation = torch._dynamo.explain(model)(x)
        assert (explanation.graph_count, explanation.break_reasons) == (1, [])
        compiled = torch.compile(model, backend="aot_eager", fullgraph=True)
        got, ref = compiled(x), model(x)
        torch.testing.assert_close(got, ref, rtol=0, atol=1e-13)
        params = list(model.parameters())
        g_got = torch.autograd.grad(got.square().sum(), params)
        g_ref = torch.autograd.grad(ref.square().sum(), params)
        for a, b in zip(g_got, g_ref, strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    torch._dynamo.reset()


class _Square(torch.autograd.Function):
    """x ** 2 with a backward that is not differentiable again (``once_differentiable``)."""

    @staticmethod
    def forward(x: Tensor) -> Tensor:
        return x * x

    @staticmethod
    def setup_context(ctx: object, inputs: tuple, output: Tensor) -> None:
        ctx.save_for_backward(*inputs)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx: object, g: Tensor) -> Tensor:
        (x,) = ctx.saved_tensors
        return 2 * x * g


class _Step(OperatorStep):
    def __init__(self, item: bool) -> None:
        super().__init__()
        self.n_outputs, self.item = 1, item
        self.state_spec = [StateBlock("last", 1)]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        return torch.sin(x), [x]


class _Toy(HysteresisOperator):
    """``sin(x)`` (or, ``square``, ``sin(x) ** 2`` through an autograd Function whose backward
    is once differentiable); ``item``: reads a value on the host in forward (as a value check
    written with ``bool(tensor)`` does). The state: the last sample."""

    n_outputs = 1

    def __init__(self, *, item: bool = False, square: bool = False) -> None:
        super().__init__()
        self.item, self.square = item, square
        self.register_buffer("scale", torch.ones(()))

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        if self.item and not bool(torch.isfinite(x).all()):
            raise ValueError("x must be finite")
        y = self.scale * torch.sin(x)
        return (_Square.apply(y) if self.square else y), x[..., -1:]

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return _Step(self.item)


@pytest.mark.parametrize("check", ["vmap", "vmap_params", "meta", "fake", "func_grad"])
def test_a_plugin_passes_the_torch_checks(check: str) -> None:
    """A plugin author's operator written with torch ops alone passes the cheap torch checks
    through torchhys.testing."""
    assert check_conformance(_Toy, Example(_Toy), checks=[check]) == {check: None}


@pytest.mark.parametrize("check, message", [
    ("vmap", r"vmap.*data-dependent control flow"),
    ("meta", r"item\(\) cannot be called on meta tensors"),
    ("fake", r"DataDependentOutputException"),
])
def test_a_host_read_fails_the_torch_checks(check: str, message: str) -> None:
    """An operator that reads a value on the host in forward fails vmap, meta and fake, the
    error naming the operator, the check and torch's reason."""
    with pytest.raises(AssertionError, match=rf"operator _Toy fails the check '{check}'.*"
                       + message):
        check_conformance(_Toy, Example(lambda: _Toy(item=True)), checks=[check])


def test_gradgradcheck_and_its_documented_refusal() -> None:
    """Double backward: gradgradcheck runs where the example declares nothing; a declared
    refusal must be raised (the check says so, with torch's message); a refusal declared for
    an operator whose double backward works, or an undeclared once-differentiable backward,
    fails the check."""
    assert check_conformance(_Toy, Example(_Toy), checks=["gradgradcheck"]) == \
        {"gradgradcheck": None}
    refused = Example(lambda: _Toy(square=True), no_gradgradcheck="differentiate twice")
    why = check_conformance(_Toy, refused, checks=["gradgradcheck"])["gradgradcheck"]
    assert why.startswith("double backward is refused as documented")
    with pytest.raises(AssertionError, match="does not raise the documented refusal"):
        check_conformance(_Toy, Example(_Toy, no_gradgradcheck="x"), checks=["gradgradcheck"])
    with pytest.raises(AssertionError, match="fails the check 'gradgradcheck'"):
        check_conformance(_Toy, Example(lambda: _Toy(square=True)), checks=["gradgradcheck"])


def test_the_torch_checks_are_named() -> None:
    """The torch checks are checks of torchhys.testing, the compiling ones outside the
    default run of check_conformance."""
    assert set(TORCH_CHECKS) <= set(CHECKS) and {"compile", "export"} <= set(COMPILE_CHECKS)
