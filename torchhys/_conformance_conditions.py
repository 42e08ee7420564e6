"""The checks of :func:`torchhys.testing.check_conditioned`, one function each: a fitted model
with operating conditions (``n_conditions > 0``, ``docs/conditions.md``) through the checks
of :data:`torchhys.testing.CONDITIONED_CHECKS` (loaded when the checks run). The comparisons
are the operators' (:mod:`torchhys._conformance`); the inputs are the caller's x (batch,
time) and conditions (batch, time, n)."""

from __future__ import annotations

import inspect
import re
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor, nn

from torchhys._conformance import (
    EXPORT_ATOL,
    LIMITS,
    PASSED,
    RAW,
    _assert_same_states,
    _raises,
    assert_close,
)
from torchhys.deploy.streaming import StreamingCompensator

CHUNKS = (1, 1, 2, 27)
"""The first chunks' lengths of the chunked runs (the rest in one)."""
EXPORT = {"limits": LIMITS, "direction": "none"}
"""The exported compensators' options: limits that never act, no direction guard, the input
and condition clamp of the defaults (the training ranges widened by 5 %)."""
C_FLAGS = ["-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-pedantic"]
"""How the C step is compiled (``cc``, else ``gcc``)."""
GRAD_T = 24
"""Samples of the first row that gradcheck differentiates."""


@dataclass(frozen=True)
class ConditionedCase:
    """One conditioned model under the checks: how to build it, its inputs, within what."""

    label: str
    build: Callable[[], nn.Module]
    x: Tensor
    conditions: Tensor
    atol: float
    no_gradcheck_x: str | None

    def model(self) -> nn.Module:
        """A fresh copy in eval mode (the seed 0 before building)."""
        torch.manual_seed(0)
        built = self.build()
        if not isinstance(built, nn.Module):
            raise TypeError(f"the model's builder returned a {type(built).__name__}, not an "
                            "nn.Module")
        return built.eval()

    @property
    def n(self) -> int:
        return int(self.conditions.shape[-1])


def output(model: nn.Module, x: Tensor, c: Tensor) -> Tensor:
    """The model's sequence output ``model(x, conditions=c)`` (the first member of a tuple)."""
    out = model(x, conditions=c)
    return out[0] if isinstance(out, (tuple, list)) else out


def takes_state(model: nn.Module) -> bool:
    """Whether the model's forward continues from a state (a parameter named ``state``)."""
    return "state" in inspect.signature(model.forward).parameters


def hard_inputs(case: ConditionedCase, model: nn.Module) -> tuple[Tensor, Tensor]:
    """The case's inputs with, in the first row, a NaN condition (a third in) and a condition
    far above its recorded range (half way); in the last row a NaN input sample (a quarter
    in): what the exported steps must hold, clamp and count as the torch compensator does."""
    x, c = case.x.clone(), case.conditions.clone()
    T = x.shape[1]
    lo, hi = model.cond_min.to(c.dtype), model.cond_max.to(c.dtype)
    c[0, T // 3, 0] = float("nan")
    c[0, T // 2, -1] = hi[-1] + 10 * (hi[-1] - lo[-1])
    x[-1, T // 4] = float("nan")
    return x, c


def stepped(stepper: object, x: Tensor, c: Tensor) -> tuple[Tensor, list[int], list[int]]:
    """``stepper.step(x_t, c_t)`` over the columns: commands (batch, time) and the counters."""
    with torch.no_grad():
        u = torch.stack([stepper.step(x[:, t].contiguous(), c[:, t].contiguous())
                         for t in range(x.shape[1])], 1)
    return (u, stepper.nonfinite_count().tolist(), stepper.out_of_range_count().tolist())


def _one_line(error: type[BaseException] | tuple, pattern: str, call: Callable[[], object],
              what: str) -> None:
    e = _raises(error, pattern, call, what)
    if "\n" in str(e):
        raise AssertionError(f"{what}: the message is not one line: {str(e)!r}")


# --- the checks: each takes the case and returns None (held) or why it does not apply ---


def _protocol(case: ConditionedCase) -> str | None:
    model = case.model()
    n = getattr(model, "n_conditions", None)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise AssertionError(f"n_conditions is {n!r}, expected an int >= 1")
    if n != case.n:
        raise AssertionError(f"n_conditions is {n}, the conditions have {case.n} columns")
    for name in ("cond_min", "cond_max"):
        v = getattr(model, name, None)
        if not isinstance(v, Tensor) or tuple(v.shape) != (n,) or not bool(
                torch.isfinite(v).all()):
            raise AssertionError(f"{name} must be a finite tensor of shape ({n},) (the "
                                 f"recorded training range), got {v!r}")
    lo, hi = model.cond_min.double(), model.cond_max.double()
    if not bool((hi > lo).all()):
        raise AssertionError(f"cond_min {lo.tolist()} is not below cond_max {hi.tolist()}")
    comp = StreamingCompensator(model, **EXPORT)
    if comp.n_conditions != n:
        raise AssertionError(f"the compensator takes {comp.n_conditions} conditions, not {n}")
    width = hi - lo
    assert_close(comp.cond_low.double(), lo - 0.05 * width, 1e-15,
                 "the condition clamp's low bounds against cond_min widened by 5 %")
    assert_close(comp.cond_high.double(), hi + 0.05 * width, 1e-15,
                 "the condition clamp's high bounds against cond_max widened by 5 %")
    u = comp(case.x, case.conditions)
    if u.dtype != case.x.dtype or u.shape != case.x.shape:
        raise AssertionError(f"the compensator's commands have dtype {u.dtype} and shape "
                             f"{tuple(u.shape)}, expected {case.x.dtype} and "
                             f"{tuple(case.x.shape)}")
    return PASSED


def _chunked(case: ConditionedCase) -> str | None:
    model, x, c = case.model(), case.x, case.conditions
    sizes = [*CHUNKS, x.shape[1] - sum(CHUNKS)]
    with torch.no_grad():
        if takes_state(model):
            whole, last = model(x, conditions=c)
            parts, state = [], None
            for xs, cs in zip(x.split(sizes, 1), c.split(sizes, 1), strict=True):
                y, state = model(xs, state, conditions=cs)
                parts.append(y)
            assert_close(torch.cat(parts, 1), whole, case.atol,
                         "the model's forward in chunks of 1, 1, 2, 27 and the rest (the "
                         "state carried) against one call")
            _assert_same_states(state, last, case.atol, "the chunks' last state")
        whole = output(model, x, c)
        assert_close(output(model, x[1], c[1]), whole[1], case.atol,
                     "the model on a row alone ((time,), (time, n)) against its row of a batch")
    comp = StreamingCompensator(model, **EXPORT)
    one = comp(x, c)
    got, state = [], comp.initial_state(x.shape[0])
    with torch.no_grad():
        for xs, cs in zip(x.split(sizes, 1), c.split(sizes, 1), strict=True):
            state = [s.clone() for s in state]  # carried across calls as a saved copy
            for t in range(xs.shape[1]):
                u, state = comp.step_explicit(xs[:, t], state, cs[:, t])
                got.append(u)
    assert_close(torch.stack(got, 1), one, 0.0, "the compensator's step_explicit in chunks of "
                 "1, 1, 2, 27 and the rest against its forward in one call")
    assert_close(comp(x[1], c[1]), one[1], case.atol,
                 "the compensator on a row alone against its row of a batch")
    return PASSED


def _step(case: ConditionedCase) -> str | None:
    model, x, c = case.model(), case.x, case.conditions
    comp = StreamingCompensator(model, limits=LIMITS, **RAW)  # no clamp: the model's own path
    u, nonfinite, _ = stepped(comp, x, c)
    with torch.no_grad():
        want = output(model, x, c)
    assert_close(u, want, case.atol, "the compensator's step (no clamp, limits that never act) "
                 "sample by sample against the model's sequence output")
    if any(nonfinite):
        raise AssertionError(f"finite samples counted as held: {nonfinite}")
    state, explicit = comp.initial_state(x.shape[0]), []
    with torch.no_grad():
        for t in range(x.shape[1]):
            v, state = comp.step_explicit(x[:, t], state, c[:, t])
            explicit.append(v)
    assert_close(torch.stack(explicit, 1), u, 0.0, "step_explicit against step")
    _assert_same_states(state, list(comp.state), 0.0, "step_explicit's state against step's")
    return PASSED


def _gradcheck(case: ConditionedCase) -> str | None:
    model = case.model()
    x = case.x[:1, :GRAD_T].detach().clone()
    c = case.conditions[:1, :GRAD_T].detach().clone().requires_grad_()
    torch.autograd.gradcheck(lambda b: output(model, x, b), (c,), raise_exception=True)
    if case.no_gradcheck_x is not None:
        return f"gradcheck in the conditions only: {case.no_gradcheck_x}"
    xg = x.requires_grad_()
    torch.autograd.gradcheck(lambda a, b: output(model, a, b), (xg, c), raise_exception=True)
    return PASSED


def _held(comp: StreamingCompensator, x: Tensor, c: Tensor, k: int, what: str) -> None:
    """Sample ``k`` of ``x`` (time,), ``c`` (time, n) is non-finite: its command is the one
    before, it is counted, and the commands after it are those without it."""
    keep = [t for t in range(x.shape[0]) if t != k]
    ref = comp(x[keep], c[keep])
    comp.reset()
    got = torch.cat([comp.step(x[t:t + 1], c[t:t + 1]) for t in range(x.shape[0])])
    if not torch.equal(got[k], got[k - 1]) or comp.nonfinite_count().tolist() != [1]:
        raise AssertionError(f"{what}: the command before it is not held, or the sample not "
                             f"counted (count {comp.nonfinite_count().tolist()})")
    if not torch.equal(got[keep], ref):
        raise AssertionError(f"{what}: the commands after it differ from those without it "
                             "(the state was not held)")


def _nan(case: ConditionedCase) -> str | None:
    model = case.model()
    comp = StreamingCompensator(model, **EXPORT)
    x, T = case.x[0], case.x.shape[1]
    for col in sorted({0, case.n - 1}):
        c = case.conditions[0].clone()
        c[T // 3, col] = float("nan")
        _held(comp, x, c, T // 3, f"a NaN in condition column {col}")
    c = case.conditions[0].clone()
    c[T // 3 + 1, 0] = float("inf")
    _held(comp, x, c, T // 3 + 1, "an inf condition")
    xs = x.clone()
    xs[T // 2] = float("nan")
    _held(comp, xs, case.conditions[0], T // 2, "a NaN input sample")
    return PASSED


def _bad_state(case: ConditionedCase) -> str | None:
    model, x, c = case.model(), case.x, case.conditions
    comp = StreamingCompensator(model, **EXPORT)
    state = comp.initial_state(x.shape[0])
    _one_line(ValueError, r"^step_explicit: state has \d+ tensors, expected",
              lambda: comp.step_explicit(x[:, 0], state[:-1], c[:, 0]),
              "a compensator state with a tensor too few")
    wrong = [state[0].to(torch.float32 if state[0].dtype == torch.float64 else torch.float64),
             *state[1:]]
    _one_line(ValueError, r"^step_explicit: state\[0\]",
              lambda: comp.step_explicit(x[:, 0], wrong, c[:, 0]),
              "a compensator state whose first tensor has another dtype")
    if takes_state(model):
        with torch.no_grad():
            _, states = model(x[:, :5], conditions=c[:, :5])
        _one_line((ValueError, TypeError), r"\bstate", lambda: model(
            x[:, 5:], [*states, *states], conditions=c[:, 5:]),
            "a model state with a block too many")
    before = {k: v.clone() for k, v in model.state_dict().items()}
    key = next((k for k in before if k.endswith("cond_min")), next(reversed(before)))
    bad = {**before, key: torch.zeros(before[key].numel() + 1, dtype=before[key].dtype)}
    _raises((RuntimeError, ValueError), re.escape(key.rsplit(".", 1)[-1]),
            lambda: model.load_state_dict(bad), f"a state dict whose {key!r} has a wrong shape")
    _assert_same_states(dict(model.state_dict()), before, 0.0,
                        f"the model after a state dict whose {key!r} has a wrong shape")
    return PASSED


def _conditions(case: ConditionedCase) -> str | None:
    model, x, c, n = case.model(), case.x, case.conditions, case.n
    more = torch.cat([c, c[..., :1]], -1)
    comp = StreamingCompensator(model, **EXPORT)
    cases = [
        (lambda: comp.step(x[:, 0]), rf"^step: this compensator takes {n} condition",
         "the compensator's step without conditions"),
        (lambda: comp.step(x[:, 0], more[:, 0]), r"^step: conditions must have shape",
         f"the compensator's step with {n + 1} conditions"),
        (lambda: comp(x, more), r"^forward: conditions must have shape",
         f"the compensator's forward with {n + 1} conditions"),
    ]
    for call, pattern, what in cases:
        _one_line(ValueError, pattern, call, what)
    with torch.no_grad():
        _one_line((ValueError, TypeError), r"condition", lambda: output(model, x, more),
                  f"the model with {n + 1} conditions")
        _one_line((ValueError, TypeError), r"condition", lambda: model(x),
                  "the model without conditions")
    return PASSED


# --- the exports against the torch compensator ---


def _against(case: ConditionedCase, model: nn.Module, run: Callable[[Tensor, Tensor], tuple],
             what: str, meta: dict | None = None) -> None:
    """``run(x, c)`` -> (commands, nonfinite, out_of_range[, state]) on the hard inputs
    against the torch compensator of the same options: commands within EXPORT_ATOL of
    their scale, the counters equal (and each path exercised), the state where given, and
    the metadata's conditions (``meta``)."""
    x, c = hard_inputs(case, model)
    comp = StreamingCompensator(model, **EXPORT)
    want, held, clamped = stepped(comp, x, c)
    got = run(x, c)
    assert_close(got[0].to(want.dtype), want, EXPORT_ATOL, f"{what} against the torch "
                 "compensator")
    if (list(got[1]), list(got[2])) != (held, clamped):
        raise AssertionError(f"{what}: counters held {list(got[1])}, clamped {list(got[2])}; "
                             f"the torch compensator's {held}, {clamped}")
    if held[0] < 1 or held[-1] < 1 or clamped[0] < 1:
        raise AssertionError(f"the hard inputs were not held or clamped (held {held}, "
                             f"clamped {clamped})")
    if len(got) > 3:
        _assert_same_states(list(got[3]), list(comp.state), EXPORT_ATOL, f"{what}'s state")
    if meta is not None:
        expect = {"n_conditions": str(case.n),
                  "condition_low": ",".join(repr(float(v)) for v in comp.cond_low),
                  "condition_high": ",".join(repr(float(v)) for v in comp.cond_high)}
        found = {k: meta.get(k) for k in expect}
        if found != expect:
            raise AssertionError(f"{what}'s metadata {found}, expected {expect}")


def _torchscript(case: ConditionedCase) -> str | None:
    from torchhys.deploy.export import load_torchscript, to_torchscript

    model = case.model()
    with tempfile.TemporaryDirectory() as folder:
        to_torchscript(model, Path(folder) / "comp.pt", **EXPORT)
        loaded = load_torchscript(Path(folder) / "comp.pt")

    def run(x: Tensor, c: Tensor) -> tuple:
        u, held, clamped = stepped(loaded, x, c)
        assert_close(loaded(x, c), u, 0.0, "the TorchScript file's forward against its step")
        return u, held, clamped, loaded.state
    _against(case, model, run, "the TorchScript file's step", loaded.torchhys_metadata)
    _raises(Exception, r"conditions must have shape", lambda: loaded.step(
        case.x[:, 0], torch.cat([case.conditions[:, 0], case.conditions[:, 0, :1]], -1)),
        f"the TorchScript file's step with {case.n + 1} conditions")
    return PASSED


def _stepper_errors(stepper: object, case: ConditionedCase, what: str) -> None:
    B, n = case.x.shape[0], case.n
    _one_line(ValueError, rf"^step: this (file|package) takes {n} condition",
              lambda: stepper.step(case.x[:, 0]), f"{what} without conditions")
    _one_line(ValueError, re.escape(f"step: conditions must have shape ({B}, {n})"),
              lambda: stepper.step(case.x[:, 0], torch.zeros(B, n + 1, dtype=case.x.dtype)),
              f"{what} with {n + 1} conditions")


def _onnx(case: ConditionedCase) -> str | None:
    import importlib.util
    missing = [m for m in ("onnx", "onnxscript", "onnxruntime")
               if importlib.util.find_spec(m) is None]
    if missing:
        return f"ONNX Runtime parity needs {', '.join(missing)} (torchhys[onnx])"
    from torchhys.deploy.export_onnx import load_onnx, to_onnx

    return _file_step(case, to_onnx, load_onnx, "comp.onnx", "the ONNX file's step",
                      " (ONNX Runtime)")


def _aoti(case: ConditionedCase) -> str | None:
    from torchhys.deploy.export import load_aoti, to_aoti

    return _file_step(case, to_aoti, load_aoti, "comp.pt2", "the AOTI package's step")


def _file_step(case: ConditionedCase, export: Callable, load: Callable, name: str, what: str,
               runner: str = "") -> str | None:
    """The model exported (``export``, to ``name`` in a temporary folder) and loaded
    (``load``): its stepper against the torch compensator, and its bad conditions refused."""
    model = case.model()
    with tempfile.TemporaryDirectory() as folder:
        stepper = load(export(model, Path(folder) / name, batch=case.x.shape[0], **EXPORT))
        _against(case, model, lambda x, c: (*stepped(stepper, x, c), stepper.state),
                 what + runner, stepper.metadata)
        _stepper_errors(stepper, case, what)
    return PASSED


DRIVER = r"""
#include <stdio.h>
#include "torchhys_comp.h"
/* B T N, then per row T lines "x c_0 ... c_N-1": each row from NAME_init, its commands, then
   its two counters */
int main(void) {
    torchhys_comp_state s;
    torchhys_comp_real cs[torchhys_comp_N_CONDITIONS];
    double x, c;
    long b, t, k, B, T, N;
    if (scanf("%ld %ld %ld", &B, &T, &N) != 3 || N != torchhys_comp_N_CONDITIONS)
        return 2;
    for (b = 0; b < B; ++b) {
        torchhys_comp_init(&s);
        for (t = 0; t < T; ++t) {
            if (scanf("%lf", &x) != 1)
                return 3;
            for (k = 0; k < N; ++k) {
                if (scanf("%lf", &c) != 1)
                    return 3;
                cs[k] = (torchhys_comp_real)c;
            }
            printf("%.17g\n", (double)torchhys_comp_step(&s, (torchhys_comp_real)x, cs));
        }
        printf("%lld %lld\n", (long long)torchhys_comp_nonfinite_count(&s),
               (long long)torchhys_comp_out_of_range_count(&s));
    }
    return 0;
}
"""


def _c(case: ConditionedCase) -> str | None:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return "no C compiler (cc or gcc) on PATH"
    from torchhys.deploy.c import to_c

    model = case.model()

    def run(x: Tensor, c: Tensor) -> tuple:
        B, T = x.shape
        with tempfile.TemporaryDirectory() as folder:
            _, src = to_c(model, folder, **EXPORT)
            (Path(folder) / "main.c").write_text(DRIVER)
            exe = Path(folder) / "run"
            done = subprocess.run([cc, *C_FLAGS, "-I", folder, "-o", str(exe),
                                   str(Path(folder) / "main.c"), str(src), "-lm"],
                                  capture_output=True, text=True)
            if done.returncode != 0:
                raise AssertionError(f"the C step does not compile: {done.stderr[-2000:]}")
            rows = [f"{B} {T} {case.n}"] + [
                " ".join(repr(float(v)) for v in [x[b, t], *c[b, t]])
                for b in range(B) for t in range(T)]
            out = subprocess.run([str(exe)], input="\n".join(rows), capture_output=True,
                                 text=True, check=True).stdout.split()
        u, held, clamped = [], [], []
        for b in range(B):
            part = out[b * (T + 2):(b + 1) * (T + 2)]
            u.append([float(v) for v in part[:T]])
            held.append(int(part[T]))
            clamped.append(int(part[T + 1]))
        return torch.tensor(u, dtype=torch.float64), held, clamped
    _against(case, model, run, "the C step (compiled)")
    return PASSED


RUNS: dict[str, Callable[[ConditionedCase], str | None]] = {
    "protocol": _protocol,
    "chunked": _chunked,
    "step": _step,
    "gradcheck": _gradcheck,
    "nan": _nan,
    "bad_state": _bad_state,
    "conditions": _conditions,
    "torchscript": _torchscript,
    "c": _c,
    "onnx": _onnx,
    "aoti": _aoti,
}
"""The check of each name of :data:`torchhys.testing.CONDITIONED_CHECKS`."""


def check_inputs(x: object, conditions: object) -> tuple[Tensor, Tensor]:
    """x (batch, time) and conditions (batch, time, n), float64, finite, at least 40 samples
    and 1 row (a ValueError or TypeError naming the argument otherwise)."""
    for name, v, dims in (("x", x, 2), ("conditions", conditions, 3)):
        if not isinstance(v, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(v).__name__}")
        if v.dtype != torch.float64:
            raise TypeError(f"{name} must be float64 (the checks' tolerances), got {v.dtype}")
        if v.dim() != dims or not bool(torch.isfinite(v).all()):
            raise ValueError(f"{name} must be finite of shape "
                             f"{'(batch, time)' if dims == 2 else '(batch, time, n)'}, got "
                             f"shape {tuple(v.shape)}")
    if tuple(conditions.shape[:2]) != tuple(x.shape) or x.shape[1] < 40:
        raise ValueError(f"conditions must have shape (batch, time, n) with x's (batch, time) "
                         f"{tuple(x.shape)} and time >= 40, got {tuple(conditions.shape)}")
    if conditions.shape[-1] < 1:
        raise ValueError("conditions must have at least one column")
    return x, conditions
