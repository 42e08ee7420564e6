"""torchhys.deploy.c: the generated C99 step, compiled, against the TorchScript compensator.

The two files are compiled with ``cc -std=c99 -O2 -Wall -Wextra -Werror -pedantic`` into a
harness that uses only the contract's names (``NAME_real``, ``NAME_state``, ``NAME_init``,
``NAME_step``, the two counters, ``NAME_LOW``, ``NAME_HIGH``, ``NAME_STATE_BYTES``;
tests/_export_helpers.py) and run over a record (nested turning points, ties, signed zeros,
samples outside the training range, NaN and inf) beside the TorchScript file's ``step``:
the recommended compensator's network under several export options, an analytic inverse,
the B-H compensator, a step of many aten operations, a step of the splits and activations
of recurrent and MLP layers (against the eager compensator), and a checkpoint of the
``torchhys`` command. Every registered operator's example network (output and state): in
tests/test_conformance.py, with the same bounds.

float64 (1e4 samples): the commands (and in the conformance suite the final state) within
1e-12 of their scale, the counters equal (measured with gcc 12 and glibc on x86-64, every
operator's example: at most 1.4e-13, the EIHO and cascade examples; 1.5e-14 to 1e-13 for
the others).
float32 (3000 samples): within FLOAT32_RTOL = 1e-4 of their scale, the counters equal
(measured: at most 5.9e-5, the EIHO and cascade networks; 6e-6 the least). That is the
size of float32's own error on these networks (the float32 TorchScript file against the
float64 one: 6e-6 to 8e-5, and 1.3 for the cascade example, whose turning-point threshold
float32 rounding crosses at other samples: there both float32 files agree within 4.7e-5
and both differ from float64). The differences come from the order of the sums (BLAS) and
from ``exp`` and ``tanh`` (torch's vectorized kernels against the generated libm-free ones,
torchhys.deploy.c._libm), scaled up by the networks' output weights. Skipped without a C compiler.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from _export_helpers import (
    CC,
    FLAGS,
    FLOAT32_RTOL,
    FLOAT64_RTOL,
    N32,
    NO_CC,
    N,
    assert_equal_runs,
    compile_harness,
    recommended,
    record,
    run_c,
    run_torchscript,
    stepped,
    training_range,
)
from _helpers import loop_net as net_of
from torch import Tensor

import torchhys
from torchhys import Backlash, InverseHysteresisNet
from torchhys.deploy.c import to_c
from torchhys.operator import HysteresisOperator
from torchhys.step import OperatorStep, StateBlock

needs_cc = pytest.mark.skipif(CC is None, reason=NO_CC)


def both(model: torch.nn.Module, folder: Path, x: np.ndarray, dtype: torch.dtype = torch.float64,
         **options) -> tuple[dict, dict]:
    """The C and the TorchScript compensators of ``model`` in ``dtype`` on ``x``."""
    to_c(model, folder, dtype=dtype, **options)
    c = run_c(compile_harness(folder), x)
    ts = run_torchscript(model, x, folder / "comp.pt", dtype, **options)
    return c, ts


def test_the_earlier_path_gives_the_same_objects_with_a_warning() -> None:
    import torchhys.deploy.c as package
    import torchhys.deploy.export_c as earlier

    assert not hasattr(earlier, "__all__")
    for name in package.__all__:
        with pytest.warns(DeprecationWarning, match=f"use torchhys.deploy.c.{name} "):
            assert getattr(earlier, name) is getattr(package, name)


# --- the recommended compensator, options -----------------------------------------------------


@needs_cc
@pytest.mark.parametrize("options", [
    {},
    {"initial_command": 0.3, "direction": "decreasing", "input_margin": 0.2},
    {"limits": (-0.5, 0.7), "input_margin": None, "direction": "none", "initial_command": -2.0},
])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_recommended_compensator_with_options(options: dict, dtype: torch.dtype,
                                              tmp_path: Path) -> None:
    net = recommended()
    x = record(*training_range(net), n=N if dtype == torch.float64 else N32, seed=1)
    c, ts = both(net, tmp_path, x, dtype, **options)
    assert_equal_runs(c, ts, FLOAT64_RTOL if dtype == torch.float64 else FLOAT32_RTOL)
    low, high = options.get("limits", (float(net.out_min), float(net.out_max)))
    assert c["low"] == pytest.approx(low, rel=1e-6) and c["high"] == pytest.approx(high, rel=1e-6)
    assert c["u"].min() >= c["low"] and c["u"].max() <= c["high"]
    assert c["u"][0] == pytest.approx(min(max(options.get("initial_command", 0.0), low), high),
                                      rel=1e-6)  # the first sample is NaN


@needs_cc
def test_a_prandtl_ishlinskii_inverse_model(tmp_path: Path) -> None:
    """A model with streaming steps that is not a network (an analytic inverse: no recorded
    range, so limits are given and the input is not clamped)."""
    pi = torchhys.PrandtlIshlinskii(torch.tensor([0.2, 0.6, 1.2], dtype=torch.float64),
                                    torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64),
                                    linear_weight=1.0)
    model = torchhys.PrandtlIshlinskiiInverse(pi)
    x = record(-1.5, 1.5)
    c, ts = both(model, tmp_path, x, limits=(-3.0, 3.0))
    assert_equal_runs(c, ts, FLOAT64_RTOL)


def bh_compensator(n: int = 40) -> InverseHysteresisNet:
    """The B-H compensator that configs/measured.yaml chooses on two-loop B-H records (as
    benchmarks/latency.py builds it): 40 stops through 4-segment characteristics beside the
    exact inverse of an ``n``-level graded Preisach model, one affine readout."""
    model = torchhys.Preisach(-70.0, 70.0, n, scale=7.0)
    with torch.no_grad():
        model.linear.fill_(1.0)
    stops = torchhys.StopPrandtlIshlinskii(torch.linspace(1.75, 70.0, 40),
                                           torch.full((40, 4), 0.01))
    net = InverseHysteresisNet([stops, model.inverse()], hidden=1,
                               activation="identity").double()
    t = torch.linspace(0, 60, 2000, dtype=torch.float64)
    y = 70 * torch.sin(t) * torch.exp(-t / 60)
    net.fit_normalization(y, y / 12)
    return net


@needs_cc
@pytest.mark.parametrize(("n", "code"), [(40, "acc += 0.0012195121962577105 * ("),
                                         (80, "bins[")])
def test_the_bh_compensator(n: int, code: str, tmp_path: Path) -> None:
    """The Preisach inverse's jumps (a constant 820 x 41 table for 40 levels, 3240 x 81 for
    80) multiplied through their column differences: written out (40 levels, pairwise
    sums), or through index tables (80 levels); the relays' update in one fused loop; the
    stops' 160 terms summed in 4 lanes; the new state (held or not) stored from a pointer
    to the old or the new one."""
    net = bh_compensator(n)
    x = record(*training_range(net), n=N if n == 40 else 3000, seed=3)
    c, ts = both(net, tmp_path, x)
    assert_equal_runs(c, ts, FLOAT64_RTOL)
    source = (tmp_path / "torchhys_comp.c").read_text()
    assert code in source and "double lane[4] = {0.0, 0.0, 0.0, 0.0};" in source
    assert re.search(r"const double \*p0 = a\d+\[0\] \? s->F : a\d+;", source)
    assert "if (p0 != s->F) memcpy(s->F, p0, sizeof s->F);" in source


class ZooStep(OperatorStep):
    """A step that runs many aten operations (their templates against TorchScript): a state
    s that follows x, and features of z = x - s."""

    def __init__(self) -> None:
        super().__init__()
        self.n_outputs = 8
        self.state_spec = [StateBlock("s", 4, from_sample=[1.0, 0.5, 0.0, -1.0])]
        self.register_buffer("grid", torch.linspace(-1.0, 1.0, 9, dtype=torch.float64))
        self.register_buffer("table", torch.arange(40, dtype=torch.float64).reshape(10, 4) / 7)

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        s = state[0]
        z = x - s
        a = torch.relu(z) + F.gelu(z) * 0.5 + torch.tanh(z).abs() + torch.sinh(z) / 9
        b = torch.floor(z * 3.0) + torch.round(z * 2.0) - torch.trunc(z) + torch.ceil(z)
        c = torch.remainder(z, 0.7) + torch.fmod(z, 0.3) + torch.div(z, 0.4, rounding_mode="floor")
        d = (torch.cumsum(z, 1) - z.sum(1, keepdim=True) / 4 + z.mean(1, keepdim=True)
             - z.amax(1, keepdim=True) + z.amin(1, keepdim=True)  # long sums: in lanes
             + z[:, :, None].expand(-1, 4, 5).sum((1, 2))[:, None] - torch.cat([z] * 5, 1).mean(
                 1, keepdim=True))
        srt, order = torch.sort(z, 1)
        g = torch.gather(z, 1, order) - srt + srt.flip(1) * 0.1
        pos = torch.searchsorted(self.grid, x.squeeze(1).contiguous(), right=True)
        h = self.table.index_select(0, pos.clamp(0, 9)).to(z.dtype)
        t = z.reshape(-1, 2, 2).transpose(1, 2).reshape(z.shape[0], 4)
        e = torch.stack([z, t], 2).sum(2) + z.unsqueeze(2).expand(-1, 4, 3).sum(2)
        m = (torch.where(z > 0, z, 0.5) + torch.clamp(z, min=-0.2) + torch.clamp(z, max=0.3)
             + torch.pow(z, 2) + torch.pow(z.abs() + 1, 0.5) + torch.pow(z.abs() + 1, 1.7)
             + torch.atan2(z, x + 2) + torch.pow(z.abs() + 1, -1) + torch.pow(z, 3))
        k = ((z > 0) & (z < 1)) | ~(z > -1)
        p = torch.sigmoid(z) * k.to(z.dtype) + torch.isfinite(z).to(z.dtype) - torch.isnan(z).to(
            z.dtype)
        q = torch.expm1(-z.abs()) + torch.log1p(z.abs()) + torch.sign(z) + torch.exp2(-z.abs())
        new = torch.clamp(s + 0.3 * (x - s), -5.0, 5.0)
        out = a + b + c + d + g + h + e + m + p + q + t
        return torch.cat([out, new], 1), [new]


class Zoo(HysteresisOperator):
    """The operator of :class:`ZooStep` (its forward runs the step)."""

    n_outputs = 8

    def forward(self, x: Tensor, state: object = None) -> tuple[Tensor, None]:
        xb = x if x.dim() == 2 else x[None]
        f = ZooStep().to(xb.dtype).run(xb)
        return (f if x.dim() == 2 else f[0]), None

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return ZooStep().to(dtype)


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_many_operations_in_one_step(dtype: torch.dtype, tmp_path: Path) -> None:
    net = net_of([Zoo(), Backlash([0.4])])
    x = record(*training_range(net), n=1000)
    c, ts = both(net, tmp_path, x, dtype)
    assert_equal_runs(c, ts, FLOAT64_RTOL if dtype == torch.float64 else FLOAT32_RTOL)


@needs_cc
@pytest.mark.parametrize("activation", ["tanh", "relu", "gelu", "identity"])
def test_the_network_activations(activation: str, tmp_path: Path) -> None:
    net = net_of([Backlash([0.3, 0.9])], hidden=6, activation=activation)
    x = record(*training_range(net), n=N32)
    c, ts = both(net, tmp_path, x)
    assert_equal_runs(c, ts, FLOAT64_RTOL)


# --- the contract -----------------------------------------------------------------------------


def test_the_files_keep_the_contract(tmp_path: Path) -> None:
    net = recommended()
    h, c = to_c(net, tmp_path, prefix="comp_a", dtype=torch.float32, input_margin=0.1)
    assert (h, c) == (tmp_path / "comp_a.h", tmp_path / "comp_a.c")
    header, source = h.read_text(), c.read_text()
    includes = set(re.findall(r"#include\s*[<\"]([^>\"]+)", header + source))
    assert includes == {"stdint.h", "math.h", "string.h", "comp_a.h"}
    for name in ("typedef float comp_a_real;", "} comp_a_state;",
                 "void comp_a_init(comp_a_state *s);",
                 "comp_a_real comp_a_step(comp_a_state *s, comp_a_real x);",
                 "int64_t comp_a_nonfinite_count(const comp_a_state *s);",
                 "int64_t comp_a_out_of_range_count(const comp_a_state *s);",
                 "#define comp_a_LOW", "#define comp_a_HIGH", "#define comp_a_STATE_BYTES"):
        assert name in header
    assert f"torchhys {torchhys.__version__}" in header
    assert "model: InverseHysteresisNet, operators [EIHO, Backlash], hidden 64, sigmoid" in header
    assert "input_margin=0.1" in header and "training range: input [" in header
    # no allocation, no mutable global (file-scope data is static const), no recursion
    assert not re.search(r"\b(malloc|calloc|realloc|free|alloca)\s*\(", source)
    data = re.findall(r"^(?!typedef)\w[\w ]*?\w+(?:\[\d*\])?\s*(?:=|;)", source, re.M)
    assert data and all(d.startswith("static const ") for d in data), data
    step = source[source.index("comp_a_step(comp_a_state *s"):]
    assert "comp_a_step(" not in step[step.index("{"):]


@needs_cc
def test_the_state_is_the_callers(tmp_path: Path) -> None:
    """Two states of one compensator run independently, and a copied state continues as the
    original (no hidden state in the C file)."""
    net = recommended()
    to_c(net, tmp_path, prefix="two")
    main = tmp_path / "main.c"
    main.write_text(r"""
#include <stdio.h>
#include "two.h"
int main(void)
{
    two_state a, b, c;
    int i;
    two_real ua = 0, ub = 0, uc = 0, ref = 0;
    two_init(&a);
    two_init(&b);
    for (i = 0; i < 200; ++i) {
        ua = two_step(&a, (two_real)(0.01 * i));
        if (i == 99)
            c = a;
        if (i >= 100)
            uc = two_step(&c, (two_real)(0.01 * i));
    }
    for (i = 0; i < 200; ++i)
        ub = two_step(&b, (two_real)(0.01 * i));
    two_init(&c);
    for (i = 0; i < 200; ++i)
        ref = two_step(&c, (two_real)(0.01 * i));
    printf("%d\n", ua == ub && ua == uc && ua == ref);
    return 0;
}
""")
    exe = tmp_path / "main"
    subprocess.run([CC, *FLAGS, "-o", str(exe), str(main), str(tmp_path / "two.c"), "-lm"],
                   check=True)
    assert subprocess.run([str(exe)], capture_output=True, text=True).stdout.strip() == "1"


# --- errors -----------------------------------------------------------------------------------




def test_an_operation_without_template_is_named_with_its_step(erfinv_module, tmp_path: Path
                                                              ) -> None:
    net = net_of([erfinv_module.ErfinvZone(), Backlash([0.4])])
    out = tmp_path / "out"
    out.mkdir()
    with pytest.raises(ValueError, match=r"no C template for aten\.erfinv\.default \(from "
                       r"comp\.slots\.0\.step \(erfinv_plugin\.ErfinvStep\) at "
                       r"erfinv_plugin\.py:\d+ in forward\)") as err:
        to_c(net, out)
    assert "\n" not in str(err.value)
    assert not list(out.iterdir())  # nothing written


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"prefix": "1comp"}, "prefix must be a C identifier"),
    ({"prefix": "my-comp"}, "prefix must be a C identifier"),
    ({"prefix": "double"}, "prefix must be a C identifier"),
    ({"dtype": torch.float16}, "dtype must be torch.float32 or torch.float64"),
])
def test_bad_arguments(kwargs: dict, message: str, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=message):
        to_c(net_of([Backlash([0.4])], hidden=2), tmp_path, **kwargs)


def test_a_missing_folder_and_a_compensator_of_another_dtype(tmp_path: Path) -> None:
    from torchhys.deploy.streaming import StreamingCompensator

    net = net_of([Backlash([0.4])], hidden=2)
    with pytest.raises(ValueError, match="is not an existing folder"):
        to_c(net, tmp_path / "missing")
    with pytest.raises(ValueError, match="differs from the StreamingCompensator's"):
        to_c(StreamingCompensator(net), tmp_path, dtype=torch.float32)
    with pytest.raises(ValueError, match="limits: fixed when the StreamingCompensator"):
        to_c(StreamingCompensator(net), tmp_path, limits=(-1.0, 1.0))


# --- the command line -------------------------------------------------------------------------


@needs_cc
def test_fit_then_export_c_from_the_command_line(monkeypatch: pytest.MonkeyPatch,
                                                 tmp_path: Path, capsys) -> None:
    pytest.importorskip("lightning")
    from _training_helpers import DROP, cli, small_config

    from torchhys.cli.export import main as export_main

    # a re-based EIHO operator and 4 plays by L-BFGS
    config = small_config(tmp_path, "tiny.yaml", model={
        "operator": [{"name": "eiho", "a": 1.0, "rule": "recent", "output": "branch"},
                     {"fit": "plays", "n": 4, "span_fraction": 0.4}],
        "operator_kwargs": DROP, "optimizer": "lbfgs", "optimizer_kwargs": {"max_iter": 5}})
    cli(monkeypatch, "fit", "--config", str(config), f"--trainer.default_root_dir={tmp_path}")
    ckpt = tmp_path / "logs/version_0/checkpoints/last.ckpt"
    out = tmp_path / "c"
    out.mkdir()
    for dtype in ("float64", "float32"):
        assert export_main(["--ckpt", str(ckpt), "--format", "c", "--out", str(out),
                            "--dtype", dtype, "--prefix", "comp_" + dtype]) == 0
        assert f"comp_{dtype}.c (c, {dtype})" in capsys.readouterr().out
        assert export_main(["--ckpt", str(ckpt), "--format", "torchscript", "--out",
                            str(out / f"{dtype}.pt"), "--dtype", dtype]) == 0
        scripted = torchhys.deploy.export.load_torchscript(out / f"{dtype}.pt")
        x = record(float(scripted.in_low), float(scripted.in_high), n=3000, seed=2)
        c = run_c(compile_harness(out, "comp_" + dtype), x)
        assert_equal_runs(c, stepped(scripted, x, scripted.low.dtype),
                          FLOAT64_RTOL if dtype == "float64" else FLOAT32_RTOL)


@pytest.mark.parametrize(("argv", "message"), [
    (["--format", "cc"], "argument --format: invalid choice: 'cc'"),
    (["--format", "c", "--dtype", "float16"], "argument --dtype: invalid choice: 'float16'"),
    (["--format", "c", "--prefix", "9lives"], "argument --prefix: prefix must be a C "
                                               "identifier"),
])
def test_bad_options_of_the_command_name_the_argument(argv: list, message: str,
                                                      tmp_path: Path, capsys) -> None:
    pytest.importorskip("lightning")
    from torchhys.cli.export import main as export_main

    with pytest.raises(SystemExit) as exit_:
        export_main(["--ckpt", str(tmp_path / "x.ckpt"), "--out", str(tmp_path), *argv])
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err


def test_bad_inputs_of_the_command_are_one_line(erfinv_module, tmp_path: Path,
                                                monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    pytest.importorskip("lightning")
    from torchhys.cli.export import main as export_main

    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    net = net_of(["erfinv_zone"], hidden=2)
    weights = tmp_path / "net.pt"
    torch.save(net.state_dict(), weights)
    plain = ["--ckpt", str(weights), "--operator", "erfinv_zone", "--hidden", "2",
             "--import", "erfinv_plugin", "--format"]
    cases = [
        (plain + ["c", "--out", str(tmp_path / "missing")],
         f"--out {tmp_path / 'missing'}: the folder does not exist"),
        (plain + ["torchscript", "--out", str(tmp_path / "a.pt"), "--prefix", "p"],
         "--prefix applies to --format c only"),
        (plain + ["c", "--out", str(tmp_path)],
         "no C template for aten.erfinv.default (from comp.slots.0.step "
         "(erfinv_plugin.ErfinvStep)"),
    ]
    for argv, message in cases:
        assert export_main(argv) == 2
        err = capsys.readouterr().err
        assert err.startswith("torchhys export: error: ") and message in err, err
        assert err.count("\n") == 1


class ActivationsStep(OperatorStep):
    """The templates a recurrent or MLP layer's step uses (against the eager compensator):
    the gates' splits (``chunk``, ``tensor_split``, unsafe splits), ``view_as``,
    ``expand_as``, ``unflatten``, ``movedim``, eval-mode dropout and the activations, on a
    state s that follows x."""

    def __init__(self) -> None:
        super().__init__()
        self.n_outputs = 1
        self.state_spec = [StateBlock("s", 6, from_sample=[1.0, 0.5, -0.5, 2.0, -3.0, 0.1])]
        self.register_buffer("w", torch.linspace(-2.0, 2.0, 36, dtype=torch.float64)
                             .reshape(6, 6) / 3)

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        s = state[0]
        z = F.linear(x - s, self.w) * 4.0  # wide: both sides of every activation's knee
        a, b, c = z.chunk(3, 1)
        d, e = z.tensor_split(2, 1)
        f, g = torch.tensor_split(z, [2], 1)
        p, q = z.unsafe_chunk(2, 1)
        acts = (F.silu(z) + F.elu(z) + F.elu(z, 0.5) + F.selu(z) + F.celu(z, 1.5)
                + F.leaky_relu(z, 0.1) + F.softplus(z) + F.softplus(z, 2.0, 3.0)
                + F.hardtanh(z) + F.hardtanh(z, -0.5, 2.0) + F.relu6(z) + F.hardsigmoid(z)
                + F.hardswish(z) + F.mish(z) + F.logsigmoid(z) + torch.tanh(z)
                + F.dropout(z, 0.3, training=False))
        mixed = (torch.cat([a * b, c, a - c], 1) + torch.cat([d, e * 0.5], 1)
                 + torch.cat([f, g.tanh()], 1) + torch.cat([p, q.sigmoid()], 1))
        r = z.unflatten(1, (2, 3)).movedim(2, 1).flatten(1) + s.view_as(z)
        out = (acts + mixed + r + x.expand_as(z)).sum(1, keepdim=True)
        new = torch.clamp(s + 0.3 * (x - s), -5.0, 5.0)
        return out, [new]


@needs_cc
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_templates_of_recurrent_and_mlp_layers(dtype: torch.dtype, tmp_path: Path) -> None:
    from _recurrent_models import StepModel

    from torchhys.deploy.streaming import StreamingCompensator

    model = StepModel(ActivationsStep())
    options = {"limits": (-1e3, 1e3), "input_range": (-1.0, 1.0)}
    x = record(-1.0, 1.0, n=N32)
    to_c(model, tmp_path, dtype=dtype, **options)
    c = run_c(compile_harness(tmp_path), x)
    ref = stepped(StreamingCompensator(model.to(dtype), **options), x, dtype)
    assert_equal_runs(c, ref, FLOAT64_RTOL if dtype == torch.float64 else FLOAT32_RTOL)
