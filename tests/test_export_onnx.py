"""torchhys.deploy.export_onnx: the ONNX step under ONNX Runtime against the TorchScript
compensator.

The ONNX file's step (:func:`~torchhys.deploy.export_onnx.load_onnx`, ONNX Runtime on the CPU) and
the TorchScript file's ``step`` run side by side over a record with nested turning points,
ties, runs of -0.0 and +0.0, samples outside the training range, NaN and inf
(tests/_export_helpers.py): the recommended compensator's network under several export
options, a Prandtl-Ishlinskii inverse, and a graded Preisach beside a stop-type PI (every
registered operator's example network: in tests/test_conformance.py, with the same bounds).
Compared: the commands (relative to their scale, at least 1), the final state tensors (the
stepper's against the TorchScript module's ``state``; float columns relative to their scale,
int64 and bool ones equal) and the two counters.

float64 (1e4 samples): within FLOAT64_RTOL = 1e-12 (measured with onnxruntime 1.32 on
x86-64, every operator's example: at most 1.2e-13, the EIHO and cascade examples; 1e-14 to 7e-14 for
the others). float32 (3000 samples): within FLOAT32_RTOL = 1e-4 (measured: at most 8.2e-5, the
cascade example; 9e-6 to 7.1e-5 for the others): both runtimes round the sums and ``exp`` in
float32, in another order, and the networks' output weights scale that up (the C step's bound).

Skipped without onnxruntime (and onnx, onnxscript): ``pip install "torchhys[onnx]"``.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from _export_helpers import (
    FLOAT32_RTOL,
    FLOAT64_RTOL,
    N32,
    N,
    assert_equal_runs,
    gap,
    recommended,
    record,
    run_onnx,
    run_torchscript,
    training_range,
)
from _helpers import loop_net as net_of

import torchhys
from torchhys import Backlash, PrandtlIshlinskii, PrandtlIshlinskiiInverse, Preisach
from torchhys.deploy.export import to_torchscript
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.testing import example_of

try:
    import onnx
    import onnxruntime  # noqa: F401
    import onnxscript  # noqa: F401
except ImportError:
    HAVE_ONNX = False
else:
    HAVE_ONNX = True

from torchhys.deploy.export_onnx import (
    ONNX_METADATA_KEYS,
    _quiet_exporter,
    load_onnx,
    onnx_metadata,
    to_onnx,
)

needs_onnx = pytest.mark.skipif(
    not HAVE_ONNX, reason='onnx, onnxscript or onnxruntime missing: pip install "torchhys[onnx]"'
)


def both(model: torch.nn.Module, folder: Path, x: np.ndarray,
         dtype: torch.dtype = torch.float64, **options) -> tuple[dict, dict]:
    """The ONNX and the TorchScript compensators of ``model`` in ``dtype`` on ``x``."""
    return (run_onnx(model, x, folder / "comp.onnx", dtype, **options),
            run_torchscript(model, x, folder / "comp.pt", dtype, **options))


# --- named models, options --------------------------------------------------------------------


@needs_onnx
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
    ox, ts = both(net, tmp_path, x, dtype, **options)
    assert_equal_runs(ox, ts, FLOAT64_RTOL if dtype == torch.float64 else FLOAT32_RTOL)
    low, high = options.get("limits", (float(net.out_min), float(net.out_max)))
    assert ox["u"].min() >= low - 1e-6 and ox["u"].max() <= high + 1e-6
    u0 = min(max(options.get("initial_command", 0.0), low), high)
    assert ox["u"][0] == pytest.approx(u0, rel=1e-6)  # the first sample is NaN


@needs_onnx
def test_a_prandtl_ishlinskii_inverse_model(tmp_path: Path) -> None:
    """A model with streaming steps that is not a network (an analytic inverse: no recorded
    range, so limits are given and the input is not clamped)."""
    pi = PrandtlIshlinskii(torch.tensor([0.2, 0.6, 1.2], dtype=torch.float64),
                           torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64),
                           linear_weight=1.0)
    model = PrandtlIshlinskiiInverse(pi)
    ox, ts = both(model, tmp_path, record(-1.5, 1.5), limits=(-3.0, 3.0))
    assert_equal_runs(ox, ts, FLOAT64_RTOL)
    assert ox["out_of_range"] == 0 and ox["stepper"].metadata["out_of_range"] == ""


@needs_onnx
def test_a_graded_preisach_beside_a_stop_pi(tmp_path: Path) -> None:
    """A network with a Preisach operator on a graded grid (asinh in its step) and a
    stop-type Prandtl-Ishlinskii operator."""
    preisach = Preisach(-1.6, 1.6, 5, scale=0.4).double()
    with torch.no_grad():
        preisach.weights.copy_(torch.linspace(0.05, 0.2, preisach.n_relays))
    net = net_of([preisach, example_of("stop_pi").build().double()], hidden=12)
    ox, ts = both(net, tmp_path, record(*training_range(net), seed=2))
    assert_equal_runs(ox, ts, FLOAT64_RTOL)


@needs_onnx
def test_a_batch_of_rows(tmp_path: Path) -> None:
    """batch=3: each row is its own compensator (its own first sample, holds, counters)."""
    net = recommended()
    x = np.stack([record(*training_range(net), n=1500, seed=s) for s in (3, 4, 5)])
    x[1, :40] = np.nan  # row 1 starts later
    to_onnx(net, tmp_path / "b.onnx", batch=3)
    stepper = load_onnx(tmp_path / "b.onnx")
    scripted = to_torchscript(net, tmp_path / "b.pt")
    xt = torch.tensor(x)
    u = torch.stack([stepper.step(xt[:, i]) for i in range(x.shape[1])], 1)
    v = torch.stack([scripted.step(xt[:, i]) for i in range(x.shape[1])], 1)
    assert gap(u, v) <= FLOAT64_RTOL
    assert torch.equal(stepper.nonfinite_count(), scripted.nonfinite_count())
    assert torch.equal(stepper.out_of_range_count(), scripted.out_of_range_count())
    assert stepper.metadata["batch"] == "3" and stepper.state[0].shape[0] == 3
    stepper.reset()
    assert all(not t.any() for t in stepper.state)
    with pytest.raises(ValueError, match=r"step expects shape \(3,\)"):
        stepper.step(torch.zeros(2, dtype=torch.float64))


@needs_onnx
def test_a_built_compensator_exports_as_it_is(tmp_path: Path) -> None:
    net = recommended()
    comp = StreamingCompensator(net, limits=(-1.0, 1.0), input_margin=None)
    to_onnx(comp, tmp_path / "c.onnx")
    meta = load_onnx(tmp_path / "c.onnx").metadata
    assert (meta["low"], meta["high"], meta["input_low"]) == ("-1.0", "1.0", "-inf")
    with pytest.raises(ValueError, match="limits: fixed when the StreamingCompensator"):
        to_onnx(comp, tmp_path / "d.onnx", limits=(0.0, 1.0))


# --- the file ---------------------------------------------------------------------------------


@needs_onnx
def test_the_file_keeps_the_contract(tmp_path: Path) -> None:
    """Inputs x then state_i, outputs u then new_state_i (names, dtypes, shapes); the
    metadata round-trips through onnx.load; the graph passes the ONNX checker."""
    net = net_of([example_of("zhao_tan").build().double()])  # a float64 state too
    net = net.float()
    path = to_onnx(net, tmp_path / "m.onnx", input_margin=0.1)
    assert path == str(tmp_path / "m.onnx")
    model = onnx.load(path)
    onnx.checker.check_model(model)
    comp = StreamingCompensator(net, input_margin=0.1)
    state = comp.initial_state(1)
    elem = {torch.float32: onnx.TensorProto.FLOAT, torch.float64: onnx.TensorProto.DOUBLE,
            torch.int64: onnx.TensorProto.INT64, torch.bool: onnx.TensorProto.BOOL}

    def signature(values) -> list[tuple[str, int, list[int]]]:
        return [(v.name, v.type.tensor_type.elem_type,
                 [d.dim_value for d in v.type.tensor_type.shape.dim]) for v in values]

    k = len(state)
    assert [t.dtype for t in state] == [torch.float32, torch.int64, torch.bool, torch.float64]
    assert signature(model.graph.input) == (
        [("x", onnx.TensorProto.FLOAT, [1])]
        + [(f"state_{i}", elem[t.dtype], list(t.shape)) for i, t in enumerate(state)])
    assert signature(model.graph.output) == (
        [("u", onnx.TensorProto.FLOAT, [1])]
        + [(f"new_state_{i}", elem[t.dtype], list(t.shape)) for i, t in enumerate(state)])
    meta = {p.key: p.value for p in model.metadata_props}
    assert set(meta) == set(ONNX_METADATA_KEYS)
    assert meta == onnx_metadata(comp)
    assert meta["torchhys_version"] == torchhys.__version__
    assert meta["n_state"] == str(k) and meta["dtype"] == "float32" and meta["batch"] == "1"
    assert meta["state_spec"] == ";".join(
        f"{n}:1,{t.shape[1]}" for n, t in zip(("float32", "int64", "bool", "float64"), state,
                                              strict=True))
    initial = json.loads(meta["initial_state"])
    assert [torch.tensor(v, dtype=t.dtype).tolist() for v, t in
            zip(initial, state, strict=True)] == [t.tolist() for t in state]
    assert initial[2] == [[False]]
    assert (meta["counter"], meta["held"]) == ("1:0", "0:0")
    assert meta["out_of_range"] == f"1:{state[1].shape[1] - 1}"
    assert float(meta["low"]) == pytest.approx(float(net.out_min))
    assert float(meta["input_low"]) == pytest.approx(
        float(net.in_min) - 0.1 * float(net.in_max - net.in_min), rel=1e-6)
    assert meta["direction"] == str(int(comp.direction)) != "0"
    assert load_onnx(path).metadata == meta


@needs_onnx
def test_the_state_is_the_callers(tmp_path: Path) -> None:
    """The file holds no state: the same inputs give the same outputs, and the state fed
    back reproduces the stepper."""
    path = to_onnx(recommended(), tmp_path / "s.onnx")
    session = onnxruntime.InferenceSession(path, providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    dtypes = {"float64": np.float64, "float32": np.float32, "int64": np.int64, "bool": np.bool_}
    fresh = [np.array(v, dtype=dtypes[part.split(":")[0]]) for v, part in
             zip(json.loads(meta["initial_state"]), meta["state_spec"].split(";"), strict=True)]
    state, xs = fresh, np.linspace(-1.0, 1.2, 50)
    stepper = load_onnx(path)
    for x in xs:
        feed = {"x": np.array([x]), **{f"state_{i}": s for i, s in enumerate(state)}}
        out = session.run(None, feed)
        again = session.run(None, feed)
        assert all(np.array_equal(a, b) for a, b in zip(out, again, strict=True))
        state = out[1:]
        assert float(out[0][0]) == float(stepper.step(torch.tensor([x])))
    assert all(np.array_equal(a, b.numpy()) for a, b in zip(state, stepper.state, strict=True))


@needs_onnx
def test_signed_zeros_and_special_values_in_the_translations(tmp_path: Path) -> None:
    """The operations written here against torch: sinh and asinh within a few ulp over a
    wide range, copysign, signbit and searchsorted exactly (the sign of zero included)."""
    from torchhys.deploy.export_onnx import _translations

    class Ops(torch.nn.Module):
        def forward(self, z, a, seq):
            return (torch.sinh(z), torch.asinh(z), torch.copysign(a, z), torch.signbit(z),
                    torch.searchsorted(seq, z), torch.searchsorted(seq, z, right=True),
                    z / (4e-7 * math.pi) + 1 / 3)

    special = [0.0, -0.0, 1e-310, -1e-310, 0.1, -0.1, np.nextafter(0.1, 0), 1.0, -1.0,
               np.inf, -np.inf, 700.0, -700.0, 1e200, -1e200, np.nan]
    z = torch.tensor(np.concatenate([special, np.linspace(-30, 30, 6001),
                                     np.logspace(-300, 300, 601), -np.logspace(-20, 2.8, 601)]))
    a = torch.tensor(np.resize([2.0, -2.0, 0.0, -0.0, np.inf], len(z)))
    seq = torch.tensor([-1.0, -0.0, 0.0, 0.5, 0.5, 2.0], dtype=torch.float64)
    session_of = {}
    for dtype in (torch.float64, torch.float32):
        args = (z.to(dtype), a.to(dtype), seq.to(dtype))
        with _quiet_exporter():
            program = torch.onnx.export(Ops().eval(), args, dynamo=True, verbose=False,
                                        custom_translation_table=_translations())
        session_of[dtype] = onnxruntime.InferenceSession(
            program.model_proto.SerializeToString(), providers=["CPUExecutionProvider"])
        session = session_of[dtype]
        names = [i.name for i in session.get_inputs()]
        got = session.run(None, {n: t.numpy() for n, t in zip(names, args, strict=True)})
        ref = [t.numpy() for t in Ops()(*args)]
        ulp = np.finfo(ref[0].dtype).eps
        with np.errstate(invalid="ignore", over="ignore"):
            for i, rtol in ((0, 16 * ulp), (1, 4 * ulp), (6, 2 * ulp)):
                fine = np.isfinite(ref[i]) & np.isfinite(got[i])
                err = np.abs(got[i][fine] - ref[i][fine]) / np.maximum(np.abs(ref[i][fine]),
                                                                       np.finfo(ulp.dtype).tiny)
                assert err.max() <= rtol, (i, dtype, err.max())
                # sinh overflows a little later than torch's vectorized sinh at +-710
                assert (np.isfinite(got[i]) | ~np.isfinite(ref[i])).all()
                assert np.array_equal(np.signbit(got[i][~np.isnan(ref[i])]),
                                      np.signbit(ref[i][~np.isnan(ref[i])]))
                assert np.array_equal(np.isnan(got[i]), np.isnan(ref[i]))
        for i in (2, 3, 4, 5):
            keep = ~np.isnan(z.numpy()) if i in (2, 3) else slice(None)
            assert np.array_equal(got[i][keep], ref[i][keep]), i
            if i == 2:
                assert np.array_equal(np.signbit(got[i][keep]), np.signbit(ref[i][keep]))
        assert got[4].dtype == np.int64


# --- errors -----------------------------------------------------------------------------------


@needs_onnx
def test_bad_arguments(tmp_path: Path) -> None:
    net = recommended()
    with pytest.raises(ValueError, match="batch must be an int >= 1"):
        to_onnx(net, tmp_path / "a.onnx", batch=0)
    with pytest.raises(ValueError, match="opset must be an int >= 1"):
        to_onnx(net, tmp_path / "a.onnx", opset=0)
    with pytest.raises(ValueError, match="does not exist"):
        to_onnx(net, tmp_path / "missing" / "a.onnx")
    with pytest.raises(ValueError, match="direction must be one of"):
        to_onnx(net, tmp_path / "a.onnx", direction="up")
    assert not (tmp_path / "a.onnx").exists()
    # an ONNX file without the metadata
    other = tmp_path / "other.onnx"
    with _quiet_exporter():
        torch.onnx.export(torch.nn.Linear(2, 1).eval(), (torch.zeros(1, 2),), other,
                          dynamo=True, verbose=False)
    with pytest.raises(ValueError, match="not a torchhys ONNX compensator"):
        load_onnx(other)




@needs_onnx
def test_an_operation_without_translation_is_named_with_its_step(erfinv_module, tmp_path: Path
                                                                ) -> None:
    net = net_of([erfinv_module.ErfinvZone(), Backlash([0.4])])
    with pytest.raises(ValueError, match=r"no ONNX translation for prims\.erf_inv\.default "
                       r"\(from comp\.slots\.0\.step \(erfinv_plugin\.ErfinvStep\) at "
                       r"erfinv_plugin\.py:\d+ in forward\)") as err:
        to_onnx(net, tmp_path / "e.onnx")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "e.onnx").exists()


@needs_onnx
def test_an_operation_onnx_runtime_cannot_run_is_refused_at_export(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Without its translation here, sinh (the Preisach inverse's graded map) exports as
    ONNX's Sinh, which ONNX Runtime runs in float32 only: refused when the file is written."""
    import torchhys.deploy.export_onnx as export_onnx

    full = export_onnx._translations

    def without_sinh():
        table = full()
        del table[torch.ops.aten.sinh.default]
        return table

    monkeypatch.setattr(export_onnx, "_translations", without_sinh)
    net = net_of([example_of("preisach_inverse").build().double()])
    with pytest.raises(ValueError, match=r"ONNX Runtime [\d.]+ cannot run the exported step: "
                       r".*Sinh\(9\)") as err:
        to_onnx(net, tmp_path / "s.onnx")
    assert "\n" not in str(err.value)
    assert not (tmp_path / "s.onnx").exists()


@pytest.mark.parametrize("missing", ["onnx", "onnxscript", "onnxruntime"])
def test_a_missing_package_names_the_extra(missing: str, tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, missing, None)  # import raises ImportError
    hint = r'need ' + missing + r': pip install "torchhys\[onnx\]"'
    if missing == "onnxruntime":
        with pytest.raises(ImportError, match=hint):
            load_onnx(tmp_path / "any.onnx")
    else:
        with pytest.raises(ImportError, match=hint):
            to_onnx(recommended(), tmp_path / "any.onnx")
