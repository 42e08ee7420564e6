"""A conditioned compensator as C99 (torchhys.deploy.c.to_c): the step takes the conditions
(``NAME_step(s, x, conditions)``, ``NAME_N_CONDITIONS``, the ranges as macros) and its
commands and counters equal the torch compensator's, compiled and run; the TorchScript,
ONNX and AOTI (slow) files step with the conditions too."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from torchhys.deploy.c import to_c
from torchhys.deploy.streaming import StreamingCompensator

sys.path.insert(0, str(Path(__file__).parent))
from _export_helpers import CC, NO_CC, run_driver  # noqa: E402
from test_conditions import _model, _record  # noqa: E402

DRIVER = r"""
#include <stdio.h>
#include "torchhys_comp.h"
int main(void) {
    static const torchhys_comp_real clamp[torchhys_comp_N_CONDITIONS][2] =
        torchhys_comp_CONDITION_CLAMP;
    static const torchhys_comp_real ranges[torchhys_comp_N_CONDITIONS][2] =
        torchhys_comp_CONDITION_RANGES;
    torchhys_comp_state s;
    double x, c;
    torchhys_comp_real cs[torchhys_comp_N_CONDITIONS];
    torchhys_comp_init(&s);
    printf("%.17g %.17g %.17g %.17g\n", (double)ranges[0][0], (double)ranges[0][1],
           (double)clamp[0][0], (double)clamp[0][1]);
    while (scanf("%lf %lf", &x, &c) == 2) {
        cs[0] = (torchhys_comp_real)c;
        printf("%.17g\n", (double)torchhys_comp_step(&s, (torchhys_comp_real)x, cs));
    }
    printf("%lld %lld\n", (long long)torchhys_comp_nonfinite_count(&s),
           (long long)torchhys_comp_out_of_range_count(&s));
    return 0;
}
"""


@pytest.mark.skipif(CC is None, reason=NO_CC)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_c_step_takes_the_conditions(tmp_path: Path, dtype: torch.dtype) -> None:
    x, c, y = _record()
    m = _model().fit(x, c, y)
    h, src = to_c(m, tmp_path, direction="none", dtype=dtype)
    assert "const torchhys_comp_real *conditions);" in h.read_text()
    # one row at the middle condition, with a NaN condition and one far out of range
    xs, cs = x[1].clone(), c[1, :, 0].clone()
    cs[50], cs[80] = float("nan"), 10.0
    out = run_driver(tmp_path, DRIVER, src, zip(xs, cs, strict=True))
    lo, hi, clo, chi = (float(v) for v in out[0].split())
    assert (lo, hi) == (0.0, 2.0)
    assert clo == pytest.approx(-0.1, abs=1e-7) and chi == pytest.approx(2.1, abs=1e-7)
    u_c = torch.tensor([float(v) for v in out[1:1 + len(xs)]], dtype=torch.float64)
    comp = StreamingCompensator(m.to(dtype), direction="none")
    u = torch.stack([comp.step(xs[k:k + 1].to(dtype), cs[k].view(1, 1).to(dtype))
                     for k in range(len(xs))], 1)[0].double()
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    assert float((u_c - u).abs().max()) <= tol
    held, outside = (int(v) for v in out[1 + len(xs)].split())
    assert (held, outside) == (int(comp.nonfinite_count()), int(comp.out_of_range_count()))
    assert (held, outside) == (1, 1)


def _fitted() -> tuple[torch.Tensor, torch.Tensor, object]:
    x, c, y = _record()
    return x, c, _model().fit(x, c, y)


def test_torchscript_file_steps_with_conditions_and_carries_them(tmp_path: Path) -> None:
    from torchhys.deploy.export import load_torchscript, to_torchscript
    x, c, m = _fitted()
    to_torchscript(m, tmp_path / "comp.pt", direction="none")
    loaded = load_torchscript(tmp_path / "comp.pt")
    comp = StreamingCompensator(m, direction="none")
    want = torch.stack([comp.step(x[:, k], c[:, k]) for k in range(40)], 1)
    got = torch.stack([loaded.step(x[:, k], c[:, k]) for k in range(40)], 1)
    assert torch.equal(got, want)
    meta = loaded.torchhys_metadata
    assert meta["n_conditions"] == "1"
    assert float(meta["condition_low"]) == pytest.approx(-0.1)
    assert float(meta["condition_high"]) == pytest.approx(2.1)
    with pytest.raises(Exception, match=r"takes 1 condition"):
        loaded.step(x[:, 0])


def _both_stepped(m: object, stepper: object, x: torch.Tensor, c: torch.Tensor) -> tuple:
    """The torch compensator and a loaded file's stepper, each stepped 60 samples on rows
    with a NaN condition (row 1, sample 7) and one far out of range (row 2, sample 9):
    ``(comp, its commands, the stepper's)``."""
    comp = StreamingCompensator(m, direction="none")
    cs = c.clone()
    cs[1, 7, 0] = float("nan")
    cs[2, 9, 0] = 7.0
    want = torch.stack([comp.step(x[:, k], cs[:, k]) for k in range(60)], 1)
    got = torch.stack([stepper.step(x[:, k], cs[:, k]) for k in range(60)], 1)
    return comp, want, got


def test_onnx_file_steps_with_conditions(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    from torchhys.deploy.export_onnx import load_onnx, to_onnx
    x, c, m = _fitted()
    path = to_onnx(m, tmp_path / "comp.onnx", direction="none", batch=3)
    stepper = load_onnx(path)
    assert stepper.metadata["n_conditions"] == "1"
    comp, want, got = _both_stepped(m, stepper, x, c)
    assert float((got - want).abs().max()) <= 1e-12
    assert stepper.nonfinite_count().tolist() == comp.nonfinite_count().tolist() == [0, 1, 0]
    assert stepper.out_of_range_count().tolist() == comp.out_of_range_count().tolist()
    with pytest.raises(ValueError, match=r"this file takes 1 condition"):
        stepper.step(x[:, 0])
    with pytest.raises(ValueError, match=r"conditions must have shape \(3, 1\)"):
        stepper.step(x[:, 0], c[:, 0, 0])


@pytest.mark.slow
def test_aoti_package_steps_with_conditions_and_carries_them(tmp_path: Path) -> None:
    """One compile (float64, batch 3): the package's step equals the torch compensator's
    within 1e-12 on rows with a NaN condition and one far out of range, the counters equal
    too; the metadata carries the conditions; a missing or wrong-shaped conditions argument
    is a one-line error."""
    from torchhys.deploy.export import load_aoti, to_aoti
    x, c, m = _fitted()
    path = to_aoti(m, tmp_path / "comp.pt2", direction="none", batch=3)
    stepper = load_aoti(path)
    meta = stepper.metadata
    assert meta["n_conditions"] == "1"
    assert float(meta["condition_low"]) == pytest.approx(-0.1)
    assert float(meta["condition_high"]) == pytest.approx(2.1)
    comp, want, got = _both_stepped(m, stepper, x, c)
    assert float((got - want).abs().max()) <= 1e-12
    assert float(got[1, 7]) == float(got[1, 6])  # held
    assert stepper.nonfinite_count().tolist() == comp.nonfinite_count().tolist() == [0, 1, 0]
    assert stepper.out_of_range_count().tolist() == comp.out_of_range_count().tolist()
    assert stepper.out_of_range_count().tolist() == [0, 0, 1]
    for call, message in [(lambda: stepper.step(x[:, 0]), r"^step: this package takes 1 "
                           r"condition\(s\): pass conditions of shape \(3, 1\)$"),
                          (lambda: stepper.step(x[:, 0], c[:, 0, 0]),
                           r"^step: conditions must have shape \(3, 1\), got \(3,\)$")]:
        with pytest.raises(ValueError, match=message) as info:
            call()
        assert "\n" not in str(info.value)
