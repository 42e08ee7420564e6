"""Every registered operator through the same checks of the operator protocol.

The names are read from ``torchhys.operator.OPERATORS`` when this module is imported (entry
points included), so an operator registered later is covered without editing this file. Each
check builds the operator's :class:`~torchhys.operator.Example` (``register_operator(name,
cls, example=...)``; by default ``cls()``) in float64 and compares within its ``atol`` (0:
bit for bit), relative to the output's scale. Family-specific maths (references, analytic
values, ties at turning points, other settings) stay in the families' own test files.
"""

from __future__ import annotations

import contextlib
import copy
import re
from collections.abc import Iterator

import pytest
import torch
from _helpers import RAW
from torch.utils._pytree import tree_flatten

from torchhys import InverseHysteresisNet, signals
from torchhys.export import load_aoti, to_aoti, to_torchscript
from torchhys.functional._filter_kernel import (
    filter_kernel_enabled,
    filter_kernel_unavailable_reason,
)
from torchhys.functional._kernel import kernel_enabled, kernel_unavailable_reason
from torchhys.operator import (
    OPERATORS,
    Example,
    check_operator,
    example_of,
    load_entry_points,
)
from torchhys.streaming import StreamingCompensator

load_entry_points()
NAMES = sorted(OPERATORS)
LIMITS = (-1e6, 1e6)  # command limits that never act
EXPORT_ATOL = 1e-12
"""The compensators against each other and the network's sequence path (float64): the step
of the network's head, TorchScript's graph passes and AOTInductor's kernels round
differently."""
NEGATIVE_WIDTHS = ("a negative fixed width from a state dict loads (the constructor refuses "
                   "it): forward raises only when run, and the streaming step runs with it")
NEGATIVE_THRESHOLD = ("a negative threshold from a state dict loads (the constructor refuses "
                      "it): forward raises only when run, and the streaming step runs with it")
NAMES_Y = "forward(x) names its input y in its errors (stop_pi_inverse's functional form)"
KNOWN_DEFECTS: dict[tuple[str, str, str | None], str] = {
    ("bad_value", "backlash", "fixed_widths"): NEGATIVE_WIDTHS,
    ("bad_value", "prandtl_ishlinskii", "fixed_widths"): NEGATIVE_WIDTHS,
    ("bad_value", "generalized_pi", "fixed_widths"): NEGATIVE_WIDTHS,
    ("bad_value", "eiho", "threshold"): NEGATIVE_THRESHOLD,
    ("bad_value", "zhao_tan", "threshold"): NEGATIVE_THRESHOLD,
    ("wrong_shape", "generalized_pi_inverse", None): (
        "a wrong-shaped lower or upper bound fails in the constraint check with 'Boolean value "
        "of Tensor with more than one value is ambiguous', not naming the entry (the module "
        "is left unchanged)"),
    ("bad_input", "eiho", "text"): (
        "forward on a non-tensor raises AttributeError ('str' object has no attribute "
        "'is_floating_point') before the input is checked"),
    **{("bad_input", "stop_pi_inverse", case): NAMES_Y
       for case in ("text", "integer", "3-d", "nan")},
}
"""``(check, name, case)`` -> the defect that makes an operator fail a check: marked xfail
(strict: the mark goes when the defect is fixed)."""


def _param(check: str, name: str, case: str | None = None) -> object:
    reason = KNOWN_DEFECTS.get((check, name, case))
    marks = [pytest.mark.xfail(reason=reason, strict=True)] if reason else []
    values = (name,) if case is None else (name, case)
    return pytest.param(*values, marks=marks, id=name if case is None else f"{name}-{case}")


def names(check: str) -> list:
    return [_param(check, n) for n in NAMES]


@contextlib.contextmanager
def compiled(on: bool) -> Iterator[None]:
    """The sequence paths with the compiled play and filter kernels on (where they run) or
    off (the pure-torch scans)."""
    with kernel_enabled(on), filter_kernel_enabled(on):
        yield


@pytest.fixture(params=["kernels", "scans"])
def kernels(request: pytest.FixtureRequest) -> Iterator[None]:
    """Run a test with the compiled kernels and with the scans (the first skipped where no
    kernel can run: it would test the scans twice)."""
    on = request.param == "kernels"
    reasons = (kernel_unavailable_reason(), filter_kernel_unavailable_reason())
    if on and None not in reasons:
        pytest.skip(f"no compiled kernel runs here: {reasons[0]}; {reasons[1]}")
    with compiled(on):
        yield


def build(name: str) -> tuple[Example, torch.nn.Module]:
    example = example_of(name)
    torch.manual_seed(0)
    return example, example.build().to(torch.float64)


def causal(op: torch.nn.Module) -> None:
    if not op.causal:
        pytest.skip(f"{type(op).__name__} is not causal: it cannot stream or be exported")


def signal(T: int = 90) -> torch.Tensor:
    """(2, T) float64 in [-1, 1]: nested reversals, and a walk on a grid of 1/8 with flat
    stretches (exact ties with thresholds, repeated samples)."""
    t = torch.linspace(0.0, 1.0, T, dtype=torch.float64)
    nested = signals.nested_reversals(t, amplitude=0.9, n_reversals=9, ratio=0.8)
    g = torch.Generator().manual_seed(3)
    steps = torch.randn(T, generator=g, dtype=torch.float64) * 0.25
    steps[torch.rand(T, generator=g) < 0.2] = 0.0
    walk = ((steps.cumsum(0).clamp(-1.0, 1.0)) * 8).round() / 8
    return torch.stack([nested, walk])


def smooth(T: int = 12) -> torch.Tensor:
    """(2, T) float64 without ties (no repeated samples, none on a grid): for gradcheck."""
    t = torch.arange(T, dtype=torch.float64)
    return torch.stack([0.8 * torch.sin(0.61 * t + 0.3) + 0.05 * t ** 0.5,
                        0.7 * torch.cos(0.83 * t + 0.1) - 0.013 * t])


def assert_close(got: torch.Tensor, ref: torch.Tensor, atol: float) -> None:
    tol = atol * max(1.0, float(ref.abs().max()))
    torch.testing.assert_close(got, ref, rtol=0, atol=tol)


def features(op: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """The operator's features as (batch, time, n_outputs)."""
    with torch.no_grad():
        f, _ = op(x)
    return f.reshape(x.shape[0], x.shape[1], op.n_outputs)


def network(op: torch.nn.Module, x: torch.Tensor) -> InverseHysteresisNet:
    torch.manual_seed(0)
    net = InverseHysteresisNet([op], hidden=3).double()
    net.fit_normalization(x, torch.tanh(2 * x) + 0.3 * x)
    return net


def state_dict_copy(module: torch.nn.Module) -> dict:
    return {k: v.clone() for k, v in module.state_dict().items()}


def assert_same_state(module: torch.nn.Module, before: dict) -> None:
    now = module.state_dict()
    assert list(now) == list(before)
    for k, v in now.items():
        torch.testing.assert_close(v, before[k], rtol=0, atol=0, equal_nan=True, msg=k)


@pytest.mark.parametrize("name", names("example"))
def test_the_example_is_an_operator_of_its_name(name: str) -> None:
    _, op = build(name)
    check_operator(op, f"the example of {name!r}")
    factory = OPERATORS[name]
    assert not isinstance(factory, type) or isinstance(op, factory)


def run_chunked(op: torch.nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, object]:
    """``op`` over x (batch, time) or (time,) in chunks of 1, 1, 2, 27 and the rest samples,
    the state carried: the outputs joined along time and the last state."""
    parts, state = [], None
    with torch.no_grad():
        for chunk in x.split([1, 1, 2, 27, x.shape[-1] - 31], dim=-1):
            f, state = op(chunk, state)
            parts.append(f)
    return torch.cat(parts, x.dim() - 1), state


def assert_same_states(got: object, ref: object, atol: float) -> None:
    """Equal states (tensors, or tuples and lists of them), leaf by leaf."""
    leaves, spec = tree_flatten(got)
    ref_leaves, ref_spec = tree_flatten(ref)
    assert spec == ref_spec
    for a, b in zip(leaves, ref_leaves, strict=True):
        assert_close(a, b, atol if a.is_floating_point() else 0.0)


@pytest.mark.parametrize("name", names("chunked"))
def test_chunked_calls_equal_one_call(name: str, kernels: None) -> None:
    """In chunks with the state carried: a batch, and one row as (time,), whose output and
    state equal its row of the batch."""
    example, op = build(name)
    x = signal()
    with torch.no_grad():
        whole, last = op(x)
        row, row_last = op(x[1:])
        unbatched, unbatched_last = op(x[1])
    for xs, ref, ref_last in ((x, whole, last), (x[1], unbatched, unbatched_last)):
        got, got_last = run_chunked(op, xs)
        assert_close(got, ref, example.atol)
        assert_same_states(got_last, ref_last, example.atol)
    assert unbatched.shape == row.shape[1:]
    assert_close(unbatched, row[0], example.atol)
    flat = [t.reshape(-1) for t in tree_flatten(unbatched_last)[0]]
    assert_same_states(flat, [t.reshape(-1) for t in tree_flatten(row_last)[0]],
                       example.atol)


@pytest.mark.parametrize("name", names("step"))
def test_the_step_equals_forward(name: str, kernels: None) -> None:
    example, op = build(name)
    causal(op)
    x = signal()
    step = op.streaming_step(torch.float64)
    assert step.n_outputs == op.n_outputs
    with torch.no_grad():
        got = step.run(x)
    assert_close(got, features(op, x), example.atol)


@pytest.mark.parametrize("name", names("gradcheck"))
def test_gradcheck_of_forward_in_the_input(name: str, kernels: None) -> None:
    example, op = build(name)
    if example.no_gradcheck is not None:
        pytest.skip(example.no_gradcheck)
    x = smooth().requires_grad_()
    assert torch.autograd.gradcheck(lambda v: op(v)[0], (x,))


@pytest.mark.parametrize("name", names("torchscript"))
def test_torchscript_equals_the_streaming_compensator(name: str, tmp_path) -> None:
    """The eager compensator equals the network's sequence path (kernels on and off), and
    the scripted one both."""
    _, op = build(name)
    causal(op)
    x = signal()
    net = network(op, x)
    eager = StreamingCompensator(net, limits=LIMITS, **RAW)(x)
    for on in (True, False):
        with compiled(on), torch.no_grad():
            assert_close(eager, net(x)[0], EXPORT_ATOL)
    scripted = to_torchscript(net, tmp_path / "comp.pt", limits=LIMITS, **RAW)
    assert_close(scripted(x), eager, EXPORT_ATOL)
    with torch.no_grad():
        assert_close(scripted(x), net(x)[0], EXPORT_ATOL)


@pytest.mark.slow
@pytest.mark.parametrize("name", names("aoti"))
def test_aoti_equals_the_streaming_compensator(name: str, tmp_path) -> None:
    """Stepped through an AOTInductor package (a compile each, about 10 s), then a NaN."""
    _, op = build(name)
    causal(op)
    x = signal(40)[1]
    net = network(op, x[None])
    eager = StreamingCompensator(net, limits=LIMITS, **RAW)(x)
    stepper = load_aoti(to_aoti(net, tmp_path / "comp.pt2", limits=LIMITS, **RAW))
    got = torch.cat([stepper.step(v.reshape(1)) for v in x])
    assert_close(got, eager, EXPORT_ATOL)
    with torch.no_grad():
        assert_close(got, net(x)[0], EXPORT_ATOL)
    held = stepper.step(torch.tensor([float("nan")], dtype=torch.float64))
    assert torch.equal(held, got[-1:]) and int(stepper.nonfinite_count()) == 1


@pytest.mark.parametrize("name", names("nan"))
def test_a_nan_sample_is_held(name: str) -> None:
    """The command before a NaN sample is repeated, the counter counts it, and the state is
    held: the samples after it get the commands they get without it."""
    _, op = build(name)
    causal(op)
    x = signal()
    comp = StreamingCompensator(network(op, x), limits=LIMITS, **RAW)
    k = 37
    ref = comp(x[:1])[0]
    with_nan = torch.cat([x[0, :k], torch.tensor([float("nan")], dtype=x.dtype), x[0, k:]])
    comp.reset()
    got = torch.cat([comp.step(v.reshape(1)) for v in with_nan])
    assert torch.equal(got[k], got[k - 1])
    assert comp.nonfinite_count().tolist() == [1]
    assert torch.equal(torch.cat([got[:k], got[k + 1:]]), ref)


@pytest.mark.parametrize("name", names("wrong_shape"))
def test_a_wrong_shape_in_a_state_dict_loads_nothing(name: str) -> None:
    """Other valid values (1% larger wherever that still loads), then a wrong shape in the
    last entry: nothing loads (all or nothing), and the error names the entry."""
    _, op = build(name)
    before = state_dict_copy(op)
    other = {}
    for key, value in before.items():
        scaled = value * 1.01 if value.is_floating_point() else value
        try:
            copy.deepcopy(op).load_state_dict({**before, key: scaled})
        except (RuntimeError, ValueError):
            scaled = value
        other[key] = scaled
    last = next(reversed(other))
    wrong = {**other, last: torch.zeros(other[last].numel() + 1, dtype=other[last].dtype)}
    with pytest.raises((RuntimeError, ValueError)) as error:
        op.load_state_dict(wrong)
    assert_same_state(op, before)
    op.load_state_dict(other)  # the valid values load
    assert_same_state(op, other)
    assert last in str(error.value)


BAD_VALUES = [_param("bad_value", n, key) for n in NAMES for key in example_of(n).bad_values]


@pytest.mark.skipif(not BAD_VALUES, reason="no example declares bad_values")
@pytest.mark.parametrize("name, key", BAD_VALUES)
def test_a_value_breaking_a_constraint_is_rejected(name: str, key: str) -> None:
    """A state-dict entry filled with the example's bad value (a negative density, a zero
    threshold, ...): ``ValueError`` naming the entry, the module unchanged."""
    example, op = build(name)
    before = state_dict_copy(op)
    bad = {**before, key: torch.full_like(before[key], example.bad_values[key])}
    with pytest.raises(ValueError, match=re.escape(key)):
        op.load_state_dict(bad)
    assert_same_state(op, before)


BAD_INPUTS = {
    "text": (TypeError, lambda: "text"),
    "integer": (TypeError, lambda: torch.arange(5)),
    "3-d": (ValueError, lambda: torch.zeros(2, 3, 4, dtype=torch.float64)),
    "nan": (ValueError, lambda: torch.tensor([[0.0, float("nan"), 0.5]], dtype=torch.float64)),
}


@pytest.mark.parametrize("name, case", [_param("bad_input", n, c) for n in NAMES
                                        for c in BAD_INPUTS])
def test_bad_input_names_x(name: str, case: str) -> None:
    _, op = build(name)
    error, value = BAD_INPUTS[case]
    with pytest.raises(error, match=r"(^|\W)x\W"):
        op(value())


@pytest.mark.parametrize("name", names("bad_state"))
def test_a_bad_state_names_state(name: str) -> None:
    """A state from a batch of another size (and, for a tensor state, a NaN in it) is an
    error naming ``state``, the argument the caller wrote."""
    _, op = build(name)
    x = signal(20)
    with torch.no_grad():
        _, state = op(x)
        if state is None:
            pytest.skip(f"{type(op).__name__} has no state")
        with pytest.raises(ValueError, match=r"^state\W"):
            op(torch.cat([x, x[:1]]), state)
        if isinstance(state, torch.Tensor) and state.is_floating_point():
            with pytest.raises(ValueError, match=r"^state\W"):
                op(x, torch.full_like(state, float("nan")))
