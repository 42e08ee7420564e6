"""Every registered operator through the same checks of the operator protocol.

The names are read from ``torchhys.registry.OPERATORS`` at import (entry points included): an
operator registered later is covered without editing this file. Each check builds the
operator's :class:`~torchhys.testing.Example` in float64 and compares within its ``atol``
(0: bit for bit), relative to the output's scale. The exports: the TorchScript and AOTI
compensators against the eager one; the C99 step (compiled) and the ONNX step (ONNX
Runtime) against the TorchScript file's, output and state. Family-specific maths
(references, analytic values, ties at turning points, other settings, float32) stay in the
families' test files.
"""

from __future__ import annotations

import contextlib
import copy
import importlib.util
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from _export_helpers import (
    CC,
    FLOAT32_RTOL,
    FLOAT64_RTOL,
    N32,
    NO_CC,
    assert_equal_runs,
    compile_harness,
    record,
    run_c,
    run_onnx,
    run_torchscript,
    training_range,
)
from _helpers import RAW, loop_net
from torch.utils._pytree import tree_flatten

from torchhys import InverseHysteresisNet, signals
from torchhys.deploy.export import load_aoti, to_aoti, to_torchscript
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.functional import _filter_kernel, _kernel
from torchhys.operator import check_operator
from torchhys.registry import OPERATORS, load_entry_points
from torchhys.testing import example_of

load_entry_points()
NAMES = sorted(OPERATORS)
LIMITS = (-1e6, 1e6)  # command limits that never act
EXPORT_ATOL = 1e-12
"""The compensators against each other and the network (float64): the head's step,
TorchScript's graph passes and AOTInductor's kernels round differently."""
KNOWN_DEFECTS: dict[tuple[str, str, str | None], str] = {}
"""``(check, name, case)`` -> the defect that makes an operator fail a check (xfail, strict:
the mark goes when the defect is fixed)."""


def names(check: str, cases: dict[str, list] | None = None, slow: tuple = ()) -> list:
    """The parameters of a check: every name (or ``(name, case)`` for the cases of each);
    the cases in ``slow`` run with the slow tests."""
    out = []
    for n in NAMES:
        for case in [None] if cases is None else cases[n]:
            reason = KNOWN_DEFECTS.get((check, n, case))
            marks = [pytest.mark.xfail(reason=reason, strict=True)] if reason else []
            out.append(pytest.param(*([n] if case is None else [n, case]),
                                    id=n if case is None else f"{n}-{case}",
                                    marks=marks + [pytest.mark.slow] * (case in slow)))
    return out


@contextlib.contextmanager
def compiled(on: bool) -> Iterator[None]:
    """The compiled play and filter kernels on (where they run) or off (the scans)."""
    with _kernel.kernel_enabled(on), _filter_kernel.filter_kernel_enabled(on):
        yield


@pytest.fixture(params=["kernels", "scans"])
def kernels(request: pytest.FixtureRequest) -> Iterator[None]:
    reasons = (_kernel.kernel_unavailable_reason(),
               _filter_kernel.filter_kernel_unavailable_reason())
    if request.param == "kernels" and None not in reasons:
        pytest.skip(f"no compiled kernel runs here: {reasons}")
    with compiled(request.param == "kernels"):
        yield


def build(name: str) -> tuple[float, torch.nn.Module]:  # the example's atol and operator
    """The example in float64; a non-causal operator (its forward needs the target) is
    outside the causal protocol these checks are about: skipped, with the reason."""
    torch.manual_seed(0)
    op = example_of(name).build().to(torch.float64)
    if not op.causal:
        pytest.skip(f"{type(op).__name__} is not causal: its forward takes the target, "
                    "outside the operator protocol (its own tests cover it)")
    return example_of(name).atol, op


def causal(op: torch.nn.Module) -> None:
    if not op.causal:
        pytest.skip(f"{type(op).__name__} is not causal: it cannot stream or be exported")


def signal(T: int = 90) -> torch.Tensor:
    """(2, T) in [-1, 1]: nested reversals, and a walk on a grid of 1/8 with flat stretches
    (ties with thresholds, repeated samples)."""
    t = torch.linspace(0.0, 1.0, T, dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    steps = torch.randn(T, generator=g, dtype=torch.float64) * 0.25
    steps[torch.rand(T, generator=g) < 0.2] = 0.0
    return torch.stack([signals.nested_reversals(t, amplitude=0.9, n_reversals=9, ratio=0.8),
                        (steps.cumsum(0).clamp(-1.0, 1.0) * 8).round() / 8])


def assert_close(got: torch.Tensor, ref: torch.Tensor, atol: float) -> None:
    atol = atol and atol * max(1.0, float(ref.abs().max()))
    torch.testing.assert_close(got, ref, rtol=0, atol=atol)


def assert_same_states(got: object, ref: object, atol: float, flat: bool = False) -> None:
    """Equal states (tensors, or tuples and lists of them) leaf by leaf; ``flat``: the
    leaves' values, whatever their shapes."""
    (leaves, spec), (ref_leaves, ref_spec) = tree_flatten(got), tree_flatten(ref)
    assert flat or spec == ref_spec
    for a, b in zip(leaves, ref_leaves, strict=True):
        if not isinstance(a, torch.Tensor):  # None: no state
            assert a == b
            continue
        a, b = (a.reshape(-1), b.reshape(-1)) if flat else (a, b)
        assert_close(a, b, atol if a.is_floating_point() else 0.0)


def network(op: torch.nn.Module, x: torch.Tensor) -> InverseHysteresisNet:
    torch.manual_seed(0)
    net = InverseHysteresisNet([op], hidden=3).double()
    net.fit_normalization(x, torch.tanh(2 * x) + 0.3 * x)
    return net


@pytest.mark.parametrize("name", names("example"))
def test_the_example_is_an_operator_of_its_name(name: str) -> None:
    _, op = build(name)
    check_operator(op, f"the example of {name!r}")
    assert not isinstance(OPERATORS[name], type) or isinstance(op, OPERATORS[name])


@pytest.mark.parametrize("name", names("chunked"))
def test_chunked_calls_equal_one_call(name: str, kernels: None) -> None:
    """In chunks of 1, 1, 2, 27 and the rest samples, the state carried: a batch, and one row
    as (time,), whose output and state equal its row of the batch."""
    atol, op = build(name)
    x = signal()
    with torch.no_grad():
        for xs in (x, x[1]):
            whole, last = op(xs)
            parts, state = [], None
            for chunk in xs.split([1, 1, 2, 27, x.shape[1] - 31], dim=-1):
                f, state = op(chunk, state)
                parts.append(f)
            assert_close(torch.cat(parts, xs.dim() - 1), whole, atol)
            assert_same_states(state, last, atol)
        row, row_last = op(x[1:])
    assert whole.shape == row.shape[1:]
    assert_close(whole, row[0], atol)
    assert_same_states(last, row_last, atol, flat=True)


@pytest.mark.parametrize("name", names("step"))
def test_the_step_equals_forward(name: str, kernels: None) -> None:
    atol, op = build(name)
    causal(op)
    x = signal()
    step = op.streaming_step(torch.float64)
    assert step.n_outputs == op.n_outputs
    with torch.no_grad():
        got = step.run(x)
        assert_close(got, op(x)[0].reshape(got.shape), atol)


@pytest.mark.parametrize("name", names("gradcheck"))
def test_gradcheck_of_forward_in_the_input(name: str, kernels: None) -> None:
    """On a short signal without ties (no repeated samples, none on a grid)."""
    if example_of(name).no_gradcheck is not None:
        pytest.skip(example_of(name).no_gradcheck)
    _, op = build(name)
    t = torch.arange(12, dtype=torch.float64)
    x = torch.stack([0.8 * torch.sin(0.61 * t + 0.3) + 0.05 * t ** 0.5,
                     0.7 * torch.cos(0.83 * t + 0.1) - 0.013 * t]).requires_grad_()
    assert torch.autograd.gradcheck(lambda v: op(v)[0], (x,))


@pytest.mark.parametrize("name", names("torchscript"))
def test_torchscript_equals_the_streaming_compensator(name: str, tmp_path) -> None:
    """The eager compensator equals the network (kernels on and off); the scripted one both."""
    _, op = build(name)
    causal(op)
    x = signal()
    net = network(op, x)
    eager = StreamingCompensator(net, limits=LIMITS, **RAW)(x)
    with torch.no_grad():
        for on in (True, False):
            with compiled(on):
                assert_close(eager, net(x)[0], EXPORT_ATOL)
        scripted = to_torchscript(net, tmp_path / "comp.pt", limits=LIMITS, **RAW)(x)
        assert_close(scripted, eager, EXPORT_ATOL)
        assert_close(scripted, net(x)[0], EXPORT_ATOL)


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


ONNX_MISSING = [m for m in ("onnx", "onnxscript", "onnxruntime")
                if importlib.util.find_spec(m) is None]
RTOL = {"float64": FLOAT64_RTOL, "float32": FLOAT32_RTOL}  # measured: tests/test_export_c.py


@pytest.fixture(scope="module")
def torchscript_runs(tmp_path_factory: pytest.TempPathFactory
                     ) -> Callable[[str, str], tuple[torch.nn.Module, np.ndarray, dict]]:
    """``(name, dtype) ->`` the example in a network fitted to follow a loop
    (``_helpers.loop_net``), a record around its training range (turning points, ties,
    signed zeros, samples 30 % beyond the range, NaN and inf: 1e4 samples, 3000 in float32)
    and the TorchScript file's run over it: computed once for the C and the ONNX checks."""
    runs: dict[tuple[str, str], tuple] = {}

    def run(name: str, dtype: str) -> tuple[torch.nn.Module, np.ndarray, dict]:
        if (name, dtype) not in runs:
            _, op = build(name)
            causal(op)
            net = loop_net([op])
            x = record(*training_range(net), **({"n": N32} if dtype == "float32" else {}))
            path = tmp_path_factory.mktemp(f"{name}-{dtype}") / "comp.pt"
            runs[name, dtype] = net, x, run_torchscript(net, x, path, getattr(torch, dtype))
        return runs[name, dtype]
    return run


def assert_as_torchscript(got: dict, x: np.ndarray, ts: dict, dtype: str) -> None:
    assert_equal_runs(got, ts, RTOL[dtype])
    assert got["nonfinite"] == int((~np.isfinite(x)).sum()) and got["out_of_range"] > 0


@pytest.mark.skipif(CC is None, reason=NO_CC)
@pytest.mark.parametrize("name, dtype", names("c", dict.fromkeys(NAMES, ["float64", "float32"])))
def test_c_equals_torchscript(name: str, dtype: str, torchscript_runs: Callable,
                              tmp_path: Path) -> None:
    """The C99 step (``to_c``, compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror
    -pedantic``): the commands and the final state (the struct's members) within RTOL of
    their scale, the counters equal."""
    from torchhys.deploy.c import to_c

    net, x, ts = torchscript_runs(name, dtype)
    to_c(net, tmp_path, dtype=getattr(torch, dtype))
    assert_as_torchscript(run_c(compile_harness(tmp_path, state=ts["state"]), x, ts["state"]),
                          x, ts, dtype)


@pytest.mark.skipif(bool(ONNX_MISSING), reason=f"{', '.join(ONNX_MISSING)} missing: pip "
                    'install "torchhys[onnx]"')
@pytest.mark.parametrize("name, dtype", names("onnx", dict.fromkeys(NAMES, ["float64", "float32"]),
                                              slow=("float32",)))
def test_onnx_equals_torchscript(name: str, dtype: str, torchscript_runs: Callable,
                                 tmp_path: Path) -> None:
    """The ONNX step under ONNX Runtime: the commands and the final state tensors within
    RTOL of their scale, the counters equal (float32: with the slow tests)."""
    net, x, ts = torchscript_runs(name, dtype)
    got = run_onnx(net, x, tmp_path / "comp.onnx", getattr(torch, dtype))
    assert_as_torchscript(got, x, ts, dtype)
    assert got["stepper"].metadata["dtype"] == dtype


@pytest.mark.parametrize("name", names("nan"))
def test_a_nan_sample_is_held(name: str) -> None:
    """The command before a NaN sample is repeated, the counter counts it, and the state is
    held: the samples after it get the commands they get without it."""
    _, op = build(name)
    causal(op)
    x = signal()[0]
    comp = StreamingCompensator(network(op, x[None]), limits=LIMITS, **RAW)
    ref, k = comp(x), 37
    got = torch.cat([comp.step(v.reshape(1)) for v in
                     torch.cat([x[:k], torch.tensor([float("nan")], dtype=x.dtype), x[k:]])])
    assert torch.equal(got[k], got[k - 1]) and comp.nonfinite_count().tolist() == [1]
    assert torch.equal(torch.cat([got[:k], got[k + 1:]]), ref)


@pytest.mark.parametrize("name", names("wrong_shape"))
def test_a_wrong_shape_in_a_state_dict_loads_nothing(name: str) -> None:
    """Other valid values (1% larger wherever that still loads), then a wrong shape in the
    last entry: nothing loads (all or nothing), and the error names the entry."""
    _, op = build(name)
    before = {k: v.clone() for k, v in op.state_dict().items()}
    other = {}
    for key, value in before.items():
        other[key] = value * 1.01 if value.is_floating_point() else value
        try:
            copy.deepcopy(op).load_state_dict({**before, key: other[key]})
        except (RuntimeError, ValueError):
            other[key] = value
    last = next(reversed(other))
    wrong = {**other, last: torch.zeros(other[last].numel() + 1, dtype=other[last].dtype)}
    with pytest.raises((RuntimeError, ValueError)) as error:
        op.load_state_dict(wrong)
    assert_same_states(dict(op.state_dict()), before, 0.0)
    op.load_state_dict(other)  # the valid values load
    assert_same_states(dict(op.state_dict()), other, 0.0)
    assert last in str(error.value)


@pytest.mark.parametrize("name, key", names("bad_value", {
    n: list(example_of(n).bad_values) for n in NAMES}) or [pytest.param(
        None, None, marks=pytest.mark.skip(reason="no example declares bad_values"))])
def test_a_value_breaking_a_constraint_is_rejected(name: str, key: str) -> None:
    """A state-dict entry filled with the example's bad value (a negative density, a zero
    threshold, ...): ``ValueError`` naming the entry, the module unchanged."""
    _, op = build(name)
    before = {k: v.clone() for k, v in op.state_dict().items()}
    bad = {**before, key: torch.full_like(before[key], example_of(name).bad_values[key])}
    with pytest.raises(ValueError, match=re.escape(key)):
        op.load_state_dict(bad)
    assert_same_states(dict(op.state_dict()), before, 0.0)


BAD_INPUTS = {  # case: (error, input, message)
    "text": (TypeError, lambda: "text", r"x must be a torch\.Tensor, got str"),
    "integer": (TypeError, lambda: torch.arange(5), r"x must have a floating-point dtype"),
    "3-d": (ValueError, lambda: torch.zeros(2, 3, 4, dtype=torch.float64),
            r"x must have shape \(time,\) or \(batch, time\), got shape \(2, 3, 4\)"),
    "nan": (ValueError, lambda: torch.tensor([[0.0, float("nan"), 0.5]], dtype=torch.float64),
            r"x must be finite, .* \(first at index \(0, 1\)\)"),
}


@pytest.mark.parametrize("name, case", names("bad_input", dict.fromkeys(NAMES, list(BAD_INPUTS))))
def test_bad_input_names_x(name: str, case: str) -> None:
    _, op = build(name)
    error, value, message = BAD_INPUTS[case]
    with pytest.raises(error, match="^" + message):
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
