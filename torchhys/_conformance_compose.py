"""The checks of :func:`torchhys.testing.check_composed`, one function each: a composed model
(:class:`torchhys.compose.Composed`) through the checks of the operators' suite that apply
to it (loaded when the checks run). The comparisons, the signal and the export checks are
the operators' (:mod:`torchhys._conformance`)."""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from torchhys._conformance import (
    EXPORT_ATOL,
    FLOAT32_ATOL,
    LIMITS,
    PASSED,
    RAW,
    _assert_same_states,
    _raises,
    aoti_against,
    assert_close,
    nan_held,
    scripted_against,
    signal,
    smooth_signal,
)
from torchhys.compose import Composed, compose
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.step import check_step

FLOAT32_BOUND = 1e-4
"""The float32 compensator of a composed model against the float64 module, relative to the
output's scale (at least 1): ``docs/composing.md``, Precision."""
CHUNKS = (1, 1, 2, 27)
"""The first chunks' lengths of the chunked runs (the rest in one)."""


@dataclass(frozen=True)
class ComposedCase:
    """One composed model under the checks: how to build it, in which dtype, within what."""

    label: str
    build: Callable[[], nn.Module]
    atol: float
    no_gradcheck: str | None
    dtype: torch.dtype

    def model(self, dtype: torch.dtype | None = None) -> Composed:
        """A fresh :class:`Composed` (the seed 0 before building) in ``dtype`` (None: the
        case's), in eval mode (the step is the module in eval mode)."""
        torch.manual_seed(0)
        built = self.build()
        if not isinstance(built, nn.Module):
            raise TypeError(f"the model's builder returned a {type(built).__name__}, not an "
                            "nn.Module")
        model = built if isinstance(built, Composed) else compose(built)
        return model.to(self.dtype if dtype is None else dtype).eval()

    @property
    def tol(self) -> float:
        """The tolerance of the step against the module: the case's (float64), at least
        :data:`FLOAT32_ATOL` in float32."""
        return self.atol if self.dtype == torch.float64 else max(self.atol, FLOAT32_ATOL)

    @property
    def export_atol(self) -> float:
        return EXPORT_ATOL if self.dtype == torch.float64 else max(FLOAT32_ATOL, self.tol)

    def x(self, model: Composed, T: int = 90) -> Tensor:
        """The operators' signal (:func:`~torchhys._conformance.signal`, (2, T) in [-1, 1])
        mapped into the model's recorded input range where it records one."""
        return in_range(model, signal(T, torch.float64)).to(self.dtype)


def in_range(model: Composed, x: Tensor) -> Tensor:
    """``x`` in [-1, 1] mapped onto the model's recorded input range (where it records one)."""
    lo, hi = float(model.in_min), float(model.in_max)
    if math.isfinite(lo) and math.isfinite(hi) and lo < hi:
        return lo + (hi - lo) * (x + 1) / 2
    return x


def _compensator(model: Composed) -> StreamingCompensator:
    return StreamingCompensator(model, limits=LIMITS, **RAW)


def _steps(comp: StreamingCompensator, x: Tensor) -> Tensor:
    with torch.no_grad():
        return torch.stack([comp.step(v) for v in x.unbind(1)], 1)


def _output(model: Composed, x: Tensor) -> Tensor:
    with torch.no_grad():
        return model(x)


# --- the checks: each takes the case and returns None (held) or why it does not apply ---


def _protocol(case: ComposedCase) -> str | None:
    model = case.model()
    steps = model.streaming_steps(case.dtype)
    if len(steps) != 1:
        raise AssertionError(f"streaming_steps gives {len(steps)} steps, expected one")
    check_step(steps[0], "the composed step")
    bad = [b.name for b in steps[0].state_spec if "." not in b.name]
    if bad:
        raise AssertionError(f"state blocks {bad} are not named '<node>.<block>'")
    x = case.x(model)
    u = _compensator(model)(x)
    if u.dtype != case.dtype or tuple(u.shape) != tuple(x.shape):
        raise AssertionError(f"the compensator's commands have dtype {u.dtype} and shape "
                             f"{tuple(u.shape)}, expected {case.dtype} and {tuple(x.shape)}")
    return PASSED


def _chunked(case: ComposedCase) -> str | None:
    model = case.model()
    x = case.x(model)
    step = model.composed_step(case.dtype)
    with torch.no_grad():
        whole = step.run(x)
        state, parts = step.initial_state(x[:, :1]), []
        for chunk in x.split([*CHUNKS, x.shape[1] - sum(CHUNKS)], dim=1):
            state = [s.clone() for s in state]  # carried across calls as a saved copy
            for v in chunk.unbind(1):
                f, state = step(v[:, None], state)
                parts.append(f)
        assert_close(torch.stack(parts, 1), whole, 0.0,
                     "the composed step in chunks of 1, 1, 2, 27 and the rest against one run")
        assert_close(step.run(x[1:]), whole[1:], case.tol,
                     "the composed step on a row alone against its row of a batch")
    comp = _compensator(model)
    one = comp(x)
    parts = [_steps(comp, chunk) for chunk in x.split([*CHUNKS, x.shape[1] - sum(CHUNKS)], 1)]
    assert_close(torch.cat(parts, 1), one, 0.0,
                 "the compensator's step in chunks of 1, 1, 2, 27 and the rest against one call")
    return PASSED


def _step(case: ComposedCase) -> str | None:
    model = case.model()
    x = case.x(model)
    step = model.composed_step(case.dtype)
    with torch.no_grad():
        got = step.run(x)[..., 0]
    if got.dtype != case.dtype:
        raise AssertionError(f"the step's output dtype {got.dtype} is not {case.dtype}")
    assert_close(got, _output(model, x), case.tol,
                 "the composed step sample by sample against the module on the sequence")
    assert_close(_compensator(model)(x), got, 0.0,
                 "the compensator's commands against the composed step")
    return PASSED


def _state(case: ComposedCase) -> str | None:
    model = case.model()
    x, k = case.x(model), 40
    comp = _compensator(model)
    first = _steps(comp, x[:, :k])
    saved = [t.clone() for t in comp.state]
    rest = _steps(comp, x[:, k:])
    comp.state = saved
    assert_close(_steps(comp, x[:, k:]), rest, 0.0, "the steps after the state was restored")
    comp.reset()
    assert_close(_steps(comp, x[:, :k]), first, 0.0, "the steps after reset()")
    state, explicit = comp.initial_state(x.shape[0]), []
    with torch.no_grad():
        for v in x.unbind(1):
            u, state = comp.step_explicit(v, state)
            explicit.append(u)
    assert_close(torch.stack(explicit, 1), torch.cat([first, rest], 1), 0.0,
                 "step_explicit against step")
    comp.reset()
    _steps(comp, x)
    _assert_same_states(state, list(comp.state), 0.0, "step_explicit's state against step's")
    step = model.composed_step(case.dtype)
    start = step.initial_state(x[:, :1])
    if not start:
        return PASSED
    block = step.state_spec[0]
    wrong = [torch.zeros(x.shape[0], block.size + 1, dtype=case.dtype), *start[1:]]
    _raises(ValueError, re.escape(f"(block {block.name!r})"),
            lambda: step(x[:, :1], wrong), "a state whose first block has a wrong width")
    return PASSED


def _gradcheck(case: ComposedCase) -> str | None:
    if case.no_gradcheck is not None:
        return case.no_gradcheck
    if case.dtype != torch.float64:
        return "gradcheck runs in float64"
    model = case.model()
    step = model.composed_step(torch.float64)
    x = in_range(model, smooth_signal()).requires_grad_()
    torch.autograd.gradcheck(lambda v: step.run(v), (x,), raise_exception=True)
    with torch.no_grad():  # one step in the input and a state reached after 6 samples
        state = step.initial_state(x[:, :1])
        for v in x[:, :6].unbind(1):
            _, state = step(v[:, None], state)
    state = [s.detach().clone().requires_grad_() for s in state]

    def one(v: Tensor, *s: Tensor) -> tuple[Tensor, ...]:
        y, new = step(v, list(s))
        return (y, *new)
    torch.autograd.gradcheck(one, (x[:, 6:7].detach().clone().requires_grad_(), *state),
                             raise_exception=True)
    return PASSED


def _nan(case: ComposedCase) -> str | None:
    model = case.model()
    nan_held(_compensator(model), case.x(model)[0])
    return PASSED


def _torchscript(case: ComposedCase) -> str | None:
    model = case.model()
    x = case.x(model)
    eager, reference = _compensator(model)(x), _output(model, x)
    assert_close(eager, reference, case.export_atol, "the eager compensator against the module")
    scripted_against(model, x, eager, reference, case.export_atol, "the module")
    return PASSED


def _aoti(case: ComposedCase) -> str | None:
    model = case.model()
    x = case.x(model, 40)[1]
    aoti_against(model, x, _output(model, x[None])[0], case.export_atol, "the module")
    return PASSED


def _float32(case: ComposedCase) -> str | None:
    model = case.model(torch.float64)
    x = case.x(model).double()
    u = _compensator(case.model(torch.float32))(x.float())
    if u.dtype != torch.float32:
        raise AssertionError(f"the float32 compensator's commands are {u.dtype}")
    assert_close(u.double(), _output(model, x), FLOAT32_BOUND,
                 "the float32 compensator against the float64 module")
    return PASSED


RUNS: dict[str, Callable[[ComposedCase], str | None]] = {
    "protocol": _protocol,
    "chunked": _chunked,
    "step": _step,
    "state": _state,
    "gradcheck": _gradcheck,
    "nan": _nan,
    "torchscript": _torchscript,
    "aoti": _aoti,
    "float32": _float32,
}
"""The check of each name of :data:`torchhys.testing.COMPOSED_CHECKS`."""
