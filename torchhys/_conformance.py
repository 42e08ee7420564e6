"""The checks of :func:`torchhys.testing.check_conformance`, one function each (loaded when
the checks run: ``import torchhys`` does not load the exporters for them)."""

import contextlib
import copy
import re
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.utils._pytree import tree_flatten

from torchhys.deploy.export import load_aoti, to_aoti, to_torchscript
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.functional import _filter_kernel, _kernel
from torchhys.networks import InverseHysteresisNet
from torchhys.operator import HysteresisOperator, check_operator
from torchhys.signals import nested_reversals

PASSED = None
"""The value of a check that ran and held, in the result of :func:`check_conformance`."""


@dataclass(frozen=True)
class Case:
    """One operator under the checks: how to build it, in which dtype, within what."""

    label: str
    example: Any  # a torchhys.testing.Example
    dtype: torch.dtype
    factory: object = None

    @property
    def atol(self) -> float:
        """The tolerance between the paths that compute the same output: the example's
        (float64), at least :data:`FLOAT32_ATOL` in float32."""
        return self.example.atol if self.dtype == torch.float64 else max(self.example.atol,
                                                                        FLOAT32_ATOL)

    @property
    def export_atol(self) -> float:
        return EXPORT_ATOL if self.dtype == torch.float64 else max(FLOAT32_ATOL, self.atol)

    def build(self) -> HysteresisOperator:
        torch.manual_seed(0)
        return self.example.build().to(self.dtype)


EXPORT_ATOL = 1e-12
"""The compensators against each other and the network (float64): the head's step,
TorchScript's graph passes and AOTInductor's kernels round differently."""
FLOAT32_ATOL = 1e-4
"""The least tolerance of the checks in float32, relative to the output's scale."""
LIMITS = (-1e6, 1e6)
"""Command limits that never act."""
RAW = {"direction": "none", "input_margin": None}
"""A compensator without its direction guard and input clamp: the model's own streaming path."""


def signal(T: int = 90, dtype: torch.dtype = torch.float64) -> Tensor:
    """(2, T) in [-1, 1]: nested reversals, and a walk on a grid of 1/8 with flat stretches
    (ties with thresholds, repeated samples)."""
    t = torch.linspace(0.0, 1.0, T, dtype=torch.float64)
    g = torch.Generator().manual_seed(3)
    steps = torch.randn(T, generator=g, dtype=torch.float64) * 0.25
    steps[torch.rand(T, generator=g) < 0.2] = 0.0
    return torch.stack([nested_reversals(t, amplitude=0.9, n_reversals=9, ratio=0.8),
                        (steps.cumsum(0).clamp(-1.0, 1.0) * 8).round() / 8]).to(dtype)


def smooth_signal(T: int = 12) -> Tensor:
    """(2, T) float64 in about [-1, 1]: two smooth waves without ties (gradcheck's input)."""
    t = torch.arange(T, dtype=torch.float64)
    return torch.stack([0.8 * torch.sin(0.61 * t + 0.3) + 0.05 * t ** 0.5,
                        0.7 * torch.cos(0.83 * t + 0.1) - 0.013 * t])


def assert_close(got: Tensor, ref: Tensor, atol: float, what: str) -> None:
    """Equal within ``atol`` relative to ``ref``'s scale (at least 1); 0: bit for bit."""
    atol = atol and atol * max(1.0, float(ref.abs().max()))
    torch.testing.assert_close(got, ref, rtol=0, atol=atol, msg=lambda m: f"{what}: {m}")


def _assert_same_states(got: object, ref: object, atol: float, what: str,
                        flat: bool = False) -> None:
    """Equal states (tensors, or tuples and lists of them) leaf by leaf; ``flat``: the
    leaves' values, whatever their shapes."""
    (leaves, spec), (ref_leaves, ref_spec) = tree_flatten(got), tree_flatten(ref)
    if not flat and spec != ref_spec:
        raise AssertionError(f"{what}: the state's structure {spec} differs from {ref_spec}")
    if len(leaves) != len(ref_leaves):
        raise AssertionError(f"{what}: {len(leaves)} state tensors, expected {len(ref_leaves)}")
    for i, (a, b) in enumerate(zip(leaves, ref_leaves, strict=True)):
        if not isinstance(a, Tensor):  # None: no state
            if a != b:
                raise AssertionError(f"{what}: state leaf {i} is {a!r}, expected {b!r}")
            continue
        a, b = (a.reshape(-1), b.reshape(-1)) if flat else (a, b)
        assert_close(a, b, atol if a.is_floating_point() else 0.0, f"{what}, state leaf {i}")


@contextlib.contextmanager
def compiled(on: bool) -> Iterator[None]:
    """The compiled play and filter kernels on (where they run) or off (the scans)."""
    with _kernel.kernel_enabled(on), _filter_kernel.filter_kernel_enabled(on):
        yield


def modes() -> list[tuple[bool, str]]:
    """The kernel modes to run a check in: the compiled kernels where one runs, the scans."""
    reasons = (_kernel.kernel_unavailable_reason(),
               _filter_kernel.filter_kernel_unavailable_reason())
    scans = (False, "the scans")
    return [(True, "the compiled kernels"), scans] if None in reasons else [scans]


def _raises(error: type[BaseException] | tuple, pattern: str, call: Callable[[], object],
            what: str) -> BaseException:
    """The exception ``call()`` raises, checked to be ``error`` with a message matching
    ``pattern`` (``re.search``)."""
    try:
        call()
    except error as e:
        if not re.search(pattern, str(e)):
            raise AssertionError(f"{what}: the message {str(e)!r} does not match "
                                 f"{pattern!r}") from e
        return e
    raise AssertionError(f"{what}: no {getattr(error, '__name__', error)} raised")


def _network(op: HysteresisOperator, x: Tensor) -> InverseHysteresisNet:
    torch.manual_seed(0)
    net = InverseHysteresisNet([op], hidden=3).to(x.dtype)
    net.fit_normalization(x, torch.tanh(2 * x) + 0.3 * x)
    return net


# --- the checks: each takes the case and returns None (held) or why it does not apply ---


def _protocol(case: Case) -> str | None:
    op = case.build()
    check_operator(op, case.label)
    if isinstance(case.factory, type) and not isinstance(op, case.factory):
        raise AssertionError(f"the example builds a {type(op).__name__}, not a "
                             f"{case.factory.__name__} (the registered class)")
    return PASSED


def _chunked(case: Case) -> str | None:
    op, x = case.build(), signal(dtype=case.dtype)
    with torch.no_grad():
        for xs in (x, x[1]):
            whole, last = op(xs)
            if whole.dtype != case.dtype:
                raise AssertionError(f"the output's dtype {whole.dtype} is not the input's "
                                     f"{case.dtype}")
            parts, state = [], None
            for chunk in xs.split([1, 1, 2, 27, x.shape[1] - 31], dim=-1):
                f, state = op(chunk, state)
                parts.append(f)
            shape = "(batch, time)" if xs.dim() == 2 else "(time,)"
            assert_close(torch.cat(parts, xs.dim() - 1), whole, case.atol,
                         f"x {shape} in chunks of 1, 1, 2, 27 and the rest")
            _assert_same_states(state, last, case.atol, f"the chunks' last state, x {shape}")
        row, row_last = op(x[1:])
    if whole.shape != row.shape[1:]:
        raise AssertionError(f"x (time,) gives shape {tuple(whole.shape)}, its row of a batch "
                             f"{tuple(row.shape[1:])}")
    assert_close(whole, row[0], case.atol, "x (time,) against its row of a batch")
    _assert_same_states(last, row_last, case.atol, "x (time,)'s state against its row's",
                        flat=True)
    return PASSED


def _step(case: Case) -> str | None:
    op, x = case.build(), signal(dtype=case.dtype)
    step = op.streaming_step(case.dtype)
    if step.n_outputs != op.n_outputs:
        raise AssertionError(f"the step's n_outputs {step.n_outputs} differs from the "
                             f"operator's {op.n_outputs}")
    with torch.no_grad():
        got = step.run(x)
        assert_close(got, op(x)[0].reshape(got.shape), case.atol,
                     "the step run sample by sample against forward")
    return PASSED


def _gradcheck(case: Case) -> str | None:
    if case.example.no_gradcheck is not None:
        return case.example.no_gradcheck
    if case.dtype != torch.float64:
        return "gradcheck runs in float64"
    op, x = case.build(), smooth_signal().requires_grad_()
    torch.autograd.gradcheck(lambda v: op(v)[0], (x,), raise_exception=True)
    return PASSED


def _torchscript(case: Case) -> str | None:
    x = signal(dtype=case.dtype)
    net = _network(case.build(), x)
    eager = StreamingCompensator(net, limits=LIMITS, **RAW)(x)
    with torch.no_grad():
        for on, mode in modes():
            with compiled(on):
                assert_close(eager, net(x)[0], case.export_atol,
                             f"the eager compensator against the network (with {mode})")
        scripted_against(net, x, eager, net(x)[0], case.export_atol, "the network")
    return PASSED


def scripted_against(model: Any, x: Tensor, eager: Tensor, reference: Tensor, atol: float,
                     what: str) -> None:
    """The TorchScript compensator of ``model`` (limits that never act, no guard or clamp)
    on ``x`` against the eager compensator's commands ``eager`` and ``reference`` (the
    model's own output, named ``what``), within ``atol`` of their scale."""
    with torch.no_grad(), tempfile.TemporaryDirectory() as folder:
        scripted = to_torchscript(model, Path(folder) / "comp.pt", limits=LIMITS, **RAW)(x)
    assert_close(scripted, eager, atol, "the TorchScript compensator against the eager one")
    assert_close(scripted, reference, atol, f"the TorchScript compensator against {what}")


def _aoti(case: Case) -> str | None:
    x = signal(40, case.dtype)[1]
    net = _network(case.build(), x[None])
    with torch.no_grad():
        reference = net(x)[0]
    aoti_against(net, x, reference, case.export_atol, "the network")
    return PASSED


def aoti_against(model: Any, x: Tensor, reference: Tensor, atol: float, what: str) -> None:
    """The AOTInductor compensator of ``model`` stepped over ``x`` (time,) against the eager
    compensator and ``reference`` (named ``what``), within ``atol``; a NaN sample then held
    and counted."""
    eager = StreamingCompensator(model, limits=LIMITS, **RAW)(x)
    with tempfile.TemporaryDirectory() as folder:
        stepper = load_aoti(to_aoti(model, Path(folder) / "comp.pt2", limits=LIMITS, **RAW))
        got = torch.cat([stepper.step(v.reshape(1)) for v in x])
        assert_close(got, eager, atol, "the AOTI compensator against the eager one")
        assert_close(got, reference, atol, f"the AOTI compensator against {what}")
        held = stepper.step(torch.tensor([float("nan")], dtype=x.dtype))
        if not (torch.equal(held, got[-1:]) and int(stepper.nonfinite_count()) == 1):
            raise AssertionError("the AOTI compensator does not hold and count a NaN sample")


def _nan(case: Case) -> str | None:
    x = signal(dtype=case.dtype)[0]
    nan_held(StreamingCompensator(_network(case.build(), x[None]), limits=LIMITS, **RAW), x)
    return PASSED


def nan_held(comp: StreamingCompensator, x: Tensor, k: int = 37) -> None:
    """A NaN sample inserted at ``k`` into ``x`` (time,): ``comp`` holds the command before
    it, counts it, and the commands after it are those without it (the state held)."""
    ref = comp(x)
    nan = torch.tensor([float("nan")], dtype=x.dtype)
    got = torch.cat([comp.step(v.reshape(1)) for v in torch.cat([x[:k], nan, x[k:]])])
    if not torch.equal(got[k], got[k - 1]) or comp.nonfinite_count().tolist() != [1]:
        raise AssertionError("the command before a NaN sample is not held, or the sample "
                             f"not counted (count {comp.nonfinite_count().tolist()})")
    if not torch.equal(torch.cat([got[:k], got[k + 1:]]), ref):
        raise AssertionError("the commands after a NaN sample differ from those without it: "
                             "the state was not held")


def _wrong_shape(case: Case) -> str | None:
    op = case.build()
    before = {k: v.clone() for k, v in op.state_dict().items()}
    if not before:
        return "the operator has no state dict entries"
    other = {}
    for key, value in before.items():  # other valid values: 1% larger where that loads
        other[key] = value * 1.01 if value.is_floating_point() else value
        try:
            copy.deepcopy(op).load_state_dict({**before, key: other[key]})
        except (RuntimeError, ValueError):
            other[key] = value
    last = next(reversed(other))
    wrong = {**other, last: torch.zeros(other[last].numel() + 1, dtype=other[last].dtype)}
    what = f"a state dict whose last entry {last!r} has a wrong shape"
    _raises((RuntimeError, ValueError), re.escape(last), lambda: op.load_state_dict(wrong), what)
    _assert_same_states(dict(op.state_dict()), before, 0.0, f"{what}: the module after it")
    op.load_state_dict(other)
    _assert_same_states(dict(op.state_dict()), other, 0.0, "the valid values loaded")
    return PASSED


def _bad_value(case: Case) -> str | None:
    if not case.example.bad_values:
        return "the example declares no bad_values"
    for key, value in case.example.bad_values.items():
        op = case.build()
        before = {k: v.clone() for k, v in op.state_dict().items()}
        bad = {**before, key: torch.full_like(before[key], value)}
        what = f"a state dict with {key!r} filled with {value!r}"
        _raises(ValueError, re.escape(key), lambda op=op, bad=bad: op.load_state_dict(bad), what)
        _assert_same_states(dict(op.state_dict()), before, 0.0, f"{what}: the module after it")
    return PASSED


BAD_INPUTS = {  # case: (error, input, message)
    "text": (TypeError, lambda dtype: "text", r"x must be a torch\.Tensor, got str"),
    "integer": (TypeError, lambda dtype: torch.arange(5), r"x must have a floating-point dtype"),
    "3-d": (ValueError, lambda dtype: torch.zeros(2, 3, 4, dtype=dtype),
            r"x must have shape \(time,\) or \(batch, time\), got shape \(2, 3, 4\)"),
    "nan": (ValueError, lambda dtype: torch.tensor([[0.0, float("nan"), 0.5]], dtype=dtype),
            r"x must be finite, .* \(first at index \(0, 1\)\)"),
}
"""The bad inputs of ``forward``: the error and the start of its message."""


def _bad_input(case: Case) -> str | None:
    op = case.build()
    for name, (error, value, message) in BAD_INPUTS.items():
        _raises(error, "^" + message, lambda value=value: op(value(case.dtype)),
                f"a bad input x ({name})")
    return PASSED


def _bad_state(case: Case) -> str | None:
    op, x = case.build(), signal(20, case.dtype)
    with torch.no_grad():
        _, state = op(x)
        if state is None:
            return f"{type(op).__name__} has no state"
        _raises(ValueError, r"^state\W", lambda: op(torch.cat([x, x[:1]]), state),
                "a state of another batch size")
        if isinstance(state, Tensor) and state.is_floating_point():
            _raises(ValueError, r"^state\W", lambda: op(x, torch.full_like(state, float("nan"))),
                    "a NaN in the state")
    return PASSED


RUNS: dict[str, tuple[Callable[[Case], str | None], bool]] = {
    "protocol": (_protocol, False),
    "chunked": (_chunked, True),
    "step": (_step, True),
    "gradcheck": (_gradcheck, True),
    "torchscript": (_torchscript, False),
    "aoti": (_aoti, False),
    "nan": (_nan, False),
    "wrong_shape": (_wrong_shape, False),
    "bad_value": (_bad_value, False),
    "bad_input": (_bad_input, False),
    "bad_state": (_bad_state, False),
}
"""The check of each name of :data:`torchhys.testing.CHECKS`, and whether it runs with the
compiled kernels and with the scans (:func:`modes`)."""


def run(case: Case, name: str, runs: dict | None = None
        ) -> list[tuple[str, Callable[[], str | None]]]:
    """The runs of check ``name`` of ``runs`` (None: :data:`RUNS`) on ``case``:
    ``(where, call)``, one per kernel mode for the checks that depend on the kernels
    (``where``: " with the scans", ...), else one."""
    check, in_modes = (RUNS if runs is None else runs)[name]
    if not in_modes:
        return [("", lambda: check(case))]

    def in_mode(on: bool) -> str | None:
        with compiled(on):
            return check(case)
    return [(f" with {mode}", lambda on=on: in_mode(on)) for on, mode in modes()]
