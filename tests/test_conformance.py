"""Every registered operator through the conformance checks of the operator protocol.

The names are read from ``torchhys.registry.OPERATORS`` at import (entry points included): an
operator registered later is covered without editing this file. Each check is
:func:`torchhys.testing.check_conformance` of one name and one check of
:data:`torchhys.testing.CHECKS` (the compiling checks, AOTInductor, ``torch.compile`` and
``torch.export``, with the slow tests but for a representative): the suite and the function a
plugin author runs are one code; ``docs/torch_integration.md`` lists the checks under torch's
own tools. Each builds the operator's
:class:`~torchhys.testing.Example` in float64 and compares within its ``atol`` (0: bit for
bit), relative to the output's scale. Here besides: the C99 step (compiled) and the ONNX step
(ONNX Runtime) against the TorchScript file's, output and state. The compositions of
``tests/_compose_models.CONFORMANCE`` (every layer kind and the compositions of issue 46)
go through :func:`torchhys.testing.check_composed`, one test a check and a composition, and
through the same C99 and ONNX checks. Family-specific maths
(references, analytic values, ties at turning points, other settings, float32) stay in the
families' test files.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from _compose_models import CONFORMANCE as COMPOSITIONS
from _compose_models import MODELS as NAMED_COMPOSITIONS
from _compose_models import with_ranges
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
from _helpers import loop_net

from torchhys.registry import OPERATORS, load_entry_points
from torchhys.testing import (
    CHECKS,
    COMPILE_CHECKS,
    COMPOSED_CHECKS,
    COMPOSED_COMPILE_CHECKS,
    check_composed,
    check_conformance,
    example_of,
)

load_entry_points()
NAMES = sorted(OPERATORS)
KNOWN_DEFECTS: dict[tuple[str, str, str | None], str] = {
    ("vmap_params", "jiles_atherton", None): (
        "JilesAtherton reads its saved_mu0 and saved_substeps buffers into Python numbers "
        "when they are set or loaded (after_load): functional_call with other buffers, and "
        "so vmap over stacked ones, runs with the loaded values"),
    ("vmap_params", "preisach_inverse", None): (
        "PreisachInverse reads its grading buffer into Python floats (center, scale) when "
        "it is built or loaded (after_load): functional_call with other buffers, and so "
        "vmap over stacked ones, runs with the loaded grading"),
    **dict.fromkeys((("export", "eiho", None), ("export", "cascade", None)), (
        "the EIHO operator's 'dominant' rule updates its stack of nested loops in a Python "
        "loop over the confirmed turning points (functional/_branch.py, _dominant_stacks; "
        "every sample under tracing), which torch.export unrolls: the program is "
        "specialized to the traced length (time = 24), not a dynamic time dimension (the "
        "cascade's example holds an EIHO stage)")),
    **dict.fromkeys((("export", "duhem", None), ("export", "play_hysteresis", None)), (
        "the feedback element (operators/feedback_element.py) integrates its ODE in a "
        "Python loop over samples that torch.export unrolls: the program is specialized "
        "to the traced length (time = 24), not a dynamic time dimension")),
    ("export", "jiles_atherton", None): (
        "functional/jiles_atherton.py steps the model in a Python loop over samples that "
        "torch.export unrolls: the program is specialized to the traced length (time = 24), "
        "not a dynamic time dimension"),
    ("export", "preisach_inverse", None): (
        "functional/preisach_inverse.py inverts sample by sample in a Python loop where the "
        "values cannot be read (tracing), which torch.export unrolls: the program is "
        "specialized to the traced length (time = 24), not a dynamic time dimension"),
    ("export", "stop_pi_inverse", None): (
        "functional/stop_pi.py's stop_pi_inverse inverts sample by sample in a Python loop "
        "that torch.export unrolls: the program is specialized to the traced length "
        "(time = 24), not a dynamic time dimension"),
}
"""``(check, name, case)`` -> the defect that makes an operator fail a check (xfail, strict:
the mark goes when the defect is fixed)."""
FAST_COMPILES = {"compile": ("backlash",), "export": ("backlash",)}
"""The operators that the compiling checks (torch.compile, torch.export) run on in the default
run, a representative each; every other name runs them with the slow tests (as AOTInductor's
compile for every name)."""


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


def checks() -> list:
    """``(check, name)`` for every check of torchhys.testing.CHECKS and every name; the
    compiling checks (COMPILE_CHECKS: AOTInductor, torch.compile, torch.export) run with the
    slow tests but on the names of FAST_COMPILES."""
    def slow(check: str, name: str) -> bool:
        return check in COMPILE_CHECKS and name not in FAST_COMPILES.get(check, ())
    return [pytest.param(check, *p.values, id=f"{check}-{p.id}",
                         marks=[*p.marks, *[pytest.mark.slow] * slow(check, p.values[0])])
            for check in CHECKS for p in names(check)]


@pytest.mark.parametrize("check, name", checks())
def test_conformance(check: str, name: str) -> None:
    """The check on the registered example (torchhys.testing.CHECKS says what each holds);
    one that does not apply (a non-causal operator, no bad values, no state) is skipped
    with its reason."""
    why = check_conformance(name, checks=[check])[check]
    if why is not None:
        pytest.skip(why)


@pytest.mark.parametrize("check, name", [
    pytest.param(check, name, id=f"{check}-{name}",
                 marks=[pytest.mark.slow] * (check in COMPOSED_COMPILE_CHECKS))
    for check in COMPOSED_CHECKS for name in COMPOSITIONS])
def test_composed_conformance(check: str, name: str) -> None:
    """The check of a composed model (torchhys.testing.COMPOSED_CHECKS) on each composition
    of tests/_compose_models.CONFORMANCE: every layer kind and the three compositions
    (AOTInductor with the slow tests)."""
    why = check_composed(COMPOSITIONS[name], checks=[check])[check]
    if why is not None:
        pytest.skip(why)


COMPOSED = "composed:"
"""The prefix of a composition's name in the C and ONNX checks (beside the operators')."""


def composed_names(dtypes: dict[str, tuple]) -> list:
    """``(COMPOSED + name, dtype)`` for every composition of CONFORMANCE and every dtype of
    ``dtypes``: those of ``dtypes[name]`` in the default run (a named composition's), the
    others with the slow tests."""
    return [pytest.param(COMPOSED + name, dtype, id=f"composed-{name}-{dtype}",
                         marks=[pytest.mark.slow] * (dtype not in dtypes.get(name, ())))
            for name in COMPOSITIONS for dtype in ("float64", "float32")]


def deployable(name: str) -> torch.nn.Module:
    """The model of a name of the C and ONNX checks: a composition with its ranges recorded
    (``COMPOSED + name``), else the operator's example in a network fitted to follow a loop
    (``_helpers.loop_net``)."""
    if name.startswith(COMPOSED):
        return with_ranges(COMPOSITIONS[name[len(COMPOSED):]])
    return loop_net([build(name)])


def build(name: str) -> torch.nn.Module:
    """The example in float64; a non-causal operator (its forward needs the target) cannot
    stream or be exported: skipped, with the reason."""
    torch.manual_seed(0)
    op = example_of(name).build().to(torch.float64)
    if not op.causal:
        pytest.skip(f"{type(op).__name__} is not causal: it cannot stream or be exported")
    return op


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
            net = deployable(name)
            x = record(*training_range(net), **({"n": N32} if dtype == "float32" else {}))
            path = tmp_path_factory.mktemp(f"{name}-{dtype}") / "comp.pt"
            runs[name, dtype] = net, x, run_torchscript(net, x, path, getattr(torch, dtype))
        return runs[name, dtype]
    return run


def assert_as_torchscript(got: dict, x: np.ndarray, ts: dict, dtype: str) -> None:
    assert_equal_runs(got, ts, RTOL[dtype])
    assert got["nonfinite"] == int((~np.isfinite(x)).sum()) and got["out_of_range"] > 0


@pytest.mark.skipif(CC is None, reason=NO_CC)
@pytest.mark.parametrize("name, dtype", [
    *names("c", dict.fromkeys(NAMES, ["float64", "float32"])),
    *composed_names(dict.fromkeys(NAMED_COMPOSITIONS, ("float64", "float32")))])
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


FMU_FAST = ("backlash",)
"""The operators that the FMU check runs on in the default run; the others with the slow
tests."""


@pytest.mark.skipif(CC is None or importlib.util.find_spec("fmpy") is None,
                    reason='no C compiler, or FMPy missing: pip install "torchhys[fmu]"')
@pytest.mark.parametrize("name", [pytest.param(*p.values, id=p.id, marks=[
    *p.marks, *[pytest.mark.slow] * (p.values[0] not in FMU_FAST)]) for p in names("fmu")])
def test_fmu_equals_torchscript(name: str, torchscript_runs: Callable, tmp_path: Path) -> None:
    """The FMI 2.0 co-simulation FMU (``to_fmu``, float64), stepped one sample a
    communication step through FMPy: the commands within RTOL of their scale, the counters
    equal."""
    from test_export_fmu import run_fmu

    from torchhys.deploy.export_fmu import to_fmu

    net, x, ts = torchscript_runs(name, "float64")
    got = run_fmu(to_fmu(net, tmp_path / "comp.fmu"), x)
    assert_as_torchscript(got, x, ts, "float64")


@pytest.mark.skipif(bool(ONNX_MISSING), reason=f"{', '.join(ONNX_MISSING)} missing: pip "
                    'install "torchhys[onnx]"')
@pytest.mark.parametrize("name, dtype", [
    *names("onnx", dict.fromkeys(NAMES, ["float64", "float32"]), slow=("float32",)),
    *composed_names({"backlash_lstm": ("float64",)})])
def test_onnx_equals_torchscript(name: str, dtype: str, torchscript_runs: Callable,
                                 tmp_path: Path) -> None:
    """The ONNX step under ONNX Runtime: the commands and the final state tensors within
    RTOL of their scale, the counters equal (float32: with the slow tests)."""
    net, x, ts = torchscript_runs(name, dtype)
    got = run_onnx(net, x, tmp_path / "comp.onnx", getattr(torch, dtype))
    assert_as_torchscript(got, x, ts, dtype)
    assert got["stepper"].metadata["dtype"] == dtype
