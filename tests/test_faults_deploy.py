"""Faults of the deployed compensator: the generated C compiled with ``-ffast-math`` (refused
by an ``#error``; with the check bypassed, NaN still held and ``exp`` still rounded), one
compensator stepped from several threads, and a wrong state handed to ``step_explicit``."""

from __future__ import annotations

import copy
import shutil
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from _export_helpers import (
    CC,
    FLAGS,
    FLOAT32_RTOL,
    FLOAT64_RTOL,
    NO_CC,
    compile_harness,
    gap,
    recommended,
    record,
    run_c,
    run_torchscript,
    training_range,
)
from _helpers import loop_net
from torch import Tensor

from torchhys import Backlash
from torchhys.deploy.c import to_c
from torchhys.deploy.c._files import FAST_MATH_ERROR
from torchhys.deploy.c._writer import Writer
from torchhys.deploy.export import to_torchscript
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.operator import HysteresisOperator
from torchhys.step import OperatorStep, StateBlock

needs_cc = pytest.mark.skipif(CC is None, reason=NO_CC)

# ------------------------------------------------------------------------------------------
# 1. the generated C under -ffast-math
# ------------------------------------------------------------------------------------------

#: -ffast-math with its macro undefined: the #error bypassed, every unsafe optimisation on
FAST_BYPASSED = ["-std=c99", "-O3", "-ffast-math", "-U__FAST_MATH__"]
DTYPES = {"float64": (torch.float64, FLOAT64_RTOL), "float32": (torch.float32, FLOAT32_RTOL)}


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The recommended network's C (both dtypes) and the TorchScript file's run over a
    record with NaN, inf and samples out of the training range."""
    net = recommended()
    x = record(*training_range(net), n=2000)
    out = {}
    for name, (dtype, _) in DTYPES.items():
        folder = tmp_path_factory.mktemp(f"c_{name}")
        to_c(net, folder, dtype=dtype)
        out[name] = (folder, run_torchscript(net, x, folder / "comp.pt", dtype=dtype))
    return {"x": x, **out}


@needs_cc
@pytest.mark.parametrize("flags", [["-O3", "-ffast-math"], ["-Ofast"]])
def test_generated_c_refuses_to_compile_under_fast_math(exported: dict, flags: list[str]) -> None:
    folder, _ = exported["float64"]
    done = subprocess.run([CC, "-std=c99", *flags, "-c", str(folder / "torchhys_comp.c"),
                           "-o", str(folder / "fast.o")], capture_output=True, text=True)
    assert done.returncode != 0
    assert "#error" in done.stderr and FAST_MATH_ERROR in done.stderr, done.stderr
    assert "compile without -ffast-math or -Ofast" in FAST_MATH_ERROR


@needs_cc
@pytest.mark.parametrize("dtype", list(DTYPES))
@pytest.mark.parametrize("flags", [FLAGS, FAST_BYPASSED, ["-std=c99", "-O2", "-ffinite-math-only"]],
                         ids=["O2", "fast-math-bypassed", "finite-math-only"])
def test_generated_c_holds_nan_and_agrees_under_every_flag(exported: dict, dtype: str,
                                                           flags: list[str]) -> None:
    """At -O2, under -O3 -ffast-math with the #error bypassed and under -ffinite-math-only
    alone (no #error: __FAST_MATH__ is not defined): every NaN and inf sample
    held and counted, the commands within the conformance bound of the TorchScript file's
    (before: NaN drove the command to a limit, uncounted, and exp's rounding was folded
    away, a gap of 2 on this record)."""
    folder, ref = exported[dtype]
    got = run_c(compile_harness(folder, flags=flags), exported["x"])
    x = exported["x"]
    assert got["nonfinite"] == ref["nonfinite"] == int((~np.isfinite(x)).sum())
    assert got["out_of_range"] == ref["out_of_range"] > 0
    assert gap(got["u"], ref["u"]) <= DTYPES[dtype][1]


EXP_HARNESS = r"""
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <string.h>

HELPERS

int main(void)
{
    double x, y[2];
    while (fread(&x, sizeof x, 1, stdin) == 1) {
        y[0] = NAME(x);
        y[1] = exp(x);
        fwrite(y, sizeof y[0], 2, stdout);
    }
    return 0;
}
"""


@needs_cc
def test_the_exp_helper_keeps_its_rounding_under_fast_math(tmp_path: Path) -> None:
    """The double exp of the generated C compiled with -O3 -ffast-math (macro undefined)
    against libm's exp compiled alike: within 1e-12 relative over the normal results (before:
    a relative error of up to 1, its k ln2 reduction folded away)."""
    w = Writer("t")
    name = w.helper("exp", torch.float64)
    src = tmp_path / "exp.c"
    src.write_text(EXP_HARNESS.replace("HELPERS", "\n\n".join(w.helpers.values()))
                   .replace("NAME", name))
    exe = tmp_path / "exp"
    done = subprocess.run([CC, *FAST_BYPASSED, "-o", str(exe), str(src), "-lm"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    g = np.random.default_rng(0)
    x = np.concatenate([g.uniform(-700.0, 709.0, 20_000), g.uniform(-5.0, 5.0, 20_000)])
    y = np.frombuffer(subprocess.run([str(exe)], input=x.tobytes(), capture_output=True,
                                     check=True).stdout, dtype=np.float64).reshape(-1, 2)
    normal = (y[:, 1] > 1e-300) & np.isfinite(y[:, 1])
    assert normal.mean() > 0.99
    assert np.max(np.abs(y[normal, 0] / y[normal, 1] - 1.0)) <= 1e-12


@needs_cc
@pytest.mark.skipif(shutil.which("clang") is None, reason="no clang on PATH")
def test_clang_too_refuses_fast_math(exported: dict) -> None:
    folder, _ = exported["float32"]
    done = subprocess.run(["clang", "-std=c99", "-O2", "-ffast-math", "-c",
                           str(folder / "torchhys_comp.c"), "-o", str(folder / "fast.o")],
                          capture_output=True, text=True)
    assert done.returncode != 0 and FAST_MATH_ERROR in done.stderr


class _TestsStep(OperatorStep):
    """Features that are NaN and inf tests of z = x - (the last sample): log z is NaN where
    the input falls, 1 / z inf where it repeats."""

    def __init__(self) -> None:
        super().__init__()
        self.n_outputs = 4
        self.state_spec = [StateBlock("last", 1, from_sample=[1.0])]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        z = x - state[0]
        log = torch.log(z)
        tests = [torch.isnan(log), torch.isinf(1.0 / z), torch.isfinite(log)]
        return torch.cat([t.to(x.dtype) for t in tests] + [x], 1), [x]


class _Tests(HysteresisOperator):
    n_outputs = 4

    def forward(self, x: Tensor, state: object = None) -> tuple[Tensor, None]:
        xb = x if x.dim() == 2 else x[None]
        f = _TestsStep().to(xb.dtype).run(xb)
        return (f if x.dim() == 2 else f[0]), None

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return _TestsStep().to(dtype)


@needs_cc
@pytest.mark.parametrize("dtype", list(DTYPES))
def test_isnan_isinf_isfinite_hold_under_fast_math(dtype: str, tmp_path: Path) -> None:
    """A step whose features are isnan, isinf and isfinite of values that are NaN and inf
    at some samples, compiled with -O3 -ffast-math (macro undefined): the commands those of
    the TorchScript file (before: x != x and x - x == 0 were folded, the tests constant)."""
    torch_dtype, rtol = DTYPES[dtype]
    net = loop_net([_Tests(), Backlash([0.4])])
    x = record(*training_range(net), n=1000)
    to_c(net, tmp_path, dtype=torch_dtype)
    ref = run_torchscript(net, x, tmp_path / "comp.pt", torch_dtype)
    got = run_c(compile_harness(tmp_path, flags=FAST_BYPASSED), x)
    assert got["nonfinite"] == ref["nonfinite"]
    assert gap(got["u"], ref["u"]) <= rtol


# ------------------------------------------------------------------------------------------
# 2. one compensator stepped from several threads
# ------------------------------------------------------------------------------------------

THREADS, STEPS = 4, 100


def scripted_of(comp: StreamingCompensator) -> torch.jit.ScriptModule:
    with warnings.catch_warnings():  # torch.jit.script's deprecation (as to_torchscript)
        warnings.simplefilter("ignore", DeprecationWarning)
        return torch.jit.script(comp)


def small_net() -> torch.nn.Module:
    return loop_net([Backlash([0.2, 0.4])], hidden=4)


def thread_inputs(k: int) -> torch.Tensor:
    """Thread ``k``'s samples: distinct finite values, every third one NaN."""
    g = torch.Generator().manual_seed(k)
    x = torch.rand(STEPS, generator=g, dtype=torch.float64) * 2.0 - 1.0
    x[::3] = float("nan")
    return x


def hammer(step) -> list[list[tuple[float, float]]]:
    """``step`` called from THREADS threads at once, each over its own samples: per thread
    the (sample, command) pairs it saw."""
    seen: list[list[tuple[float, float]]] = [[] for _ in range(THREADS)]
    start = threading.Barrier(THREADS)

    def run(k: int) -> None:
        start.wait()
        for v in thread_inputs(k):
            seen[k].append((float(v), float(step(v.reshape(1))[0])))

    threads = [threading.Thread(target=run, args=(k,)) for k in range(THREADS)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return seen


def assert_serialised(seen: list, order: list[tuple[float, float]], replay) -> None:
    """Every call's command is the one a serial run in the recorded order gives."""
    assert len(order) == THREADS * STEPS
    serial = [float(replay(torch.tensor([x], dtype=torch.float64))[0]) for x, _ in order]
    assert np.array_equal([u for _, u in order], serial)
    def key(pairs: list) -> np.ndarray:  # the pairs in one order (NaN samples last)
        return np.array(sorted(pairs, key=lambda p: (np.isnan(p[0]), np.nan_to_num(p[0]),
                                                     p[1])))

    assert np.array_equal(key([p for s in seen for p in s]), key(order), equal_nan=True)


def test_a_python_compensator_steps_one_thread_at_a_time() -> None:
    """4 threads x 100 samples into one StreamingCompensator: every NaN counted (before: the
    counter lost updates), and the commands those of a serial run in the order the steps
    took the lock."""
    comp = StreamingCompensator(small_net())
    order: list[tuple[float, float]] = []
    advance = comp._advance

    def recorded(x: Tensor, state: list[Tensor], conditions: Tensor
                 ) -> tuple[Tensor, list[Tensor]]:
        u, new = advance(x, state, conditions)
        order.append((float(x[0]), float(u[0])))  # inside the lock: the serial order
        return u, new

    comp._advance = recorded
    seen = hammer(comp.step)
    nans = sum(int(thread_inputs(k).isnan().sum()) for k in range(THREADS))
    assert int(comp.nonfinite_count()) == nans and comp.n_steps == THREADS * STEPS
    fresh = StreamingCompensator(small_net())
    assert_serialised(seen, order, fresh.step)
    assert all(torch.equal(a, b) for a, b in zip(comp.state, fresh.state, strict=True))


def test_a_copy_of_a_compensator_has_a_lock_of_its_own() -> None:
    comp = StreamingCompensator(small_net())
    twin = copy.deepcopy(comp)
    with comp._step_lock:  # held: the copy still steps
        assert torch.isfinite(twin.step(torch.tensor([0.1], dtype=torch.float64))).all()
    assert comp.step(torch.tensor([0.1], dtype=torch.float64)).shape == (1,)


@pytest.mark.slow
def test_an_onnx_stepper_steps_one_thread_at_a_time(tmp_path: Path) -> None:
    """The same through ONNXStepper (before: 1466 of 4000 NaN counted)."""
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from torchhys.deploy.export_onnx import load_onnx, to_onnx

    to_onnx(small_net(), tmp_path / "comp.onnx")
    stepper = load_onnx(tmp_path / "comp.onnx")
    order: list[tuple[float, float]] = []

    class Recorded:
        def __init__(self, session) -> None:
            self.session = session

        def run(self, names, feed):
            out = self.session.run(names, feed)
            order.append((float(feed["x"][0]), float(out[0][0])))
            return out

    stepper.session = Recorded(stepper.session)
    seen = hammer(stepper.step)
    nans = sum(int(thread_inputs(k).isnan().sum()) for k in range(THREADS))
    assert int(stepper.nonfinite_count()) == nans
    assert_serialised(seen, order, load_onnx(tmp_path / "comp.onnx").step)


@pytest.mark.slow
def test_an_aoti_stepper_steps_one_thread_at_a_time(tmp_path: Path) -> None:
    """The same through AOTIStepper (a compile of a minute or more)."""
    from torchhys.deploy.export import load_aoti, to_aoti

    to_aoti(small_net(), tmp_path / "comp.pt2")
    stepper = load_aoti(tmp_path / "comp.pt2")
    order: list[tuple[float, float]] = []
    runner = stepper.runner

    def recorded(x: Tensor, *state: Tensor) -> list[Tensor]:
        out = runner(x, *state)
        order.append((float(x[0]), float(out[0][0])))
        return out

    stepper.runner = recorded
    seen = hammer(stepper.step)
    nans = sum(int(thread_inputs(k).isnan().sum()) for k in range(THREADS))
    assert int(stepper.nonfinite_count()) == nans
    assert_serialised(seen, order, load_aoti(tmp_path / "comp.pt2").step)


TORCHSCRIPT_THREADS = r"""
import sys, threading, torch
m = torch.jit.load(sys.argv[1])
nan = torch.tensor([float("nan")], dtype=torch.float64)
done, refused, other = [], [], []
start = threading.Barrier(4)
def run():
    start.wait()
    for _ in range(100):
        try:
            m.step(nan)
            done.append(1)
        except torch.jit.Error as e:
            (refused if "another step of this compensator is running" in str(e)
             else other).append(str(e))
threads = [threading.Thread(target=run) for _ in range(4)]
for t in threads:
    t.start()
for t in threads:
    t.join()
print(len(done), len(refused), int(m.nonfinite_count()), m.n_steps, len(other))
"""


def test_a_torchscript_compensator_refuses_a_step_from_a_second_thread(tmp_path: Path) -> None:
    """4 threads x 100 NaN samples into one scripted compensator (in a child process: before,
    it crashed with a corrupted heap or lost updates): no crash, a step that overlaps another
    is refused with a RuntimeError that says so, and the counter counts the steps that ran.
    The check is a diagnosis, not a lock (docs/deployment.md, "Threads"): two steps that
    pass it at the same instant both run, and one of them may be lost, so the count may
    fall short of the steps by the few such overlaps (the code before lost 25-60 % of them
    and refused none)."""
    to_torchscript(small_net(), tmp_path / "comp.pt")
    done = subprocess.run([sys.executable, "-c", TORCHSCRIPT_THREADS, str(tmp_path / "comp.pt")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, (done.returncode, done.stderr[-2000:])
    ran, refused, count, n_steps, other = map(int, done.stdout.split())
    assert other == 0 and ran + refused == 400 and ran >= 1
    # overlapping steps are refused (how many overlap depends on the scheduler: the message
    # itself is asserted by the next test); the code before refused none and lost 25-60 %
    assert count <= n_steps <= ran and ran - count <= max(2, ran // 50), (count, n_steps, ran)


def test_a_torchscript_compensator_after_a_refused_step_goes_on() -> None:
    """The flag that tells a running step: cleared by the step, and by reset() (after a step
    that failed part-way)."""
    scripted = scripted_of(StreamingCompensator(small_net()))
    x = torch.tensor([0.2], dtype=torch.float64)
    scripted.stepping = True  # as while another thread's step runs
    with pytest.raises(torch.jit.Error, match="another step of this compensator is running"):
        scripted.step(x)
    scripted.reset()
    scripted.step(x)
    assert not scripted.stepping and scripted.n_steps == 1


# ------------------------------------------------------------------------------------------
# 3. a state of the wrong dtype handed to step_explicit
# ------------------------------------------------------------------------------------------


def wrong_states(comp: StreamingCompensator) -> list[tuple[list[Tensor], str]]:
    F, I, started = comp.initial_state(1)
    return [
        ([F, I.double(), started], r"state\[1\], I \(the int64 counters\), has dtype "
                                   r"float64, expected int64"),
        ([F.float(), I, started], r"state\[0\], F \(the float columns\), has dtype float32, "
                                  r"expected float64"),
        ([F, I, started.long()], r"state\[2\], started, has dtype int64, expected bool"),
        ([F, I], r"state has 2 tensors, expected 3 \(initial_state\)"),
    ]


@pytest.mark.parametrize("case", range(4))
def test_step_explicit_refuses_a_state_of_another_dtype(case: int) -> None:
    """A float64 counter (and any other dtype or number of tensors) is refused naming the
    entry and the dtype expected (before: the float64 counter was accepted and came back
    float64), in Python and in the scripted module."""
    comp = StreamingCompensator(small_net())
    state, message = wrong_states(comp)[case]
    x = torch.tensor([0.1], dtype=torch.float64)
    with pytest.raises(ValueError, match="^step_explicit: " + message + "$"):
        comp.step_explicit(x, state)
    scripted = scripted_of(comp)
    with pytest.raises(torch.jit.Error, match=message):
        scripted.step_explicit(x, state)
    u, new = comp.step_explicit(x, comp.initial_state(1))  # the right state still steps
    assert [t.dtype for t in new] == [torch.float64, torch.int64, torch.bool]


def test_a_python_compensator_steps_on_after_a_failed_step() -> None:
    """A step that fails part-way (here a meta tensor, which the step cannot compute on)
    leaves the Python compensator usable: the next step from the same thread runs and is
    the fresh state's first, not "another step of this compensator is running"."""
    comp = StreamingCompensator(small_net())
    x = torch.tensor([0.2], dtype=torch.float64)
    with pytest.raises(Exception) as failed:
        comp.step(torch.empty(1, dtype=torch.float64, device="meta"))
    assert "another step" not in str(failed.value)
    assert not comp.stepping
    fresh = StreamingCompensator(small_net())
    fresh.load_state_dict(comp.state_dict())
    torch.testing.assert_close(comp.step(x), fresh.step(x), rtol=0, atol=0)
