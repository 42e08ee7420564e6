"""The adaptive compensator (torchhys.deploy.adaptive) in the Python-loaded exports: the
TorchScript file, ONNX Runtime and (slow) the AOTI package step with the last sample's pair
(measured_prev, applied_prev) equal to the eager AdaptiveCompensator over a drifting plant
response with noise, NaN bursts, outliers and non-finite inputs (float64 within 1e-12; the
counters and the adapted weights, read from the state at the metadata's ``weights`` index,
equal); reset back to the offline weights; the metadata; ``torchhys export --adapt``; bad
options refused in one line naming them."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from torchhys.cli.export import main
from torchhys.deploy.adaptive import AdaptiveCompensator
from torchhys.deploy.export import ADAPT_KEYS, load_torchscript, to_torchscript
from torchhys.deploy.streaming import StreamingCompensator

sys.path.insert(0, str(Path(__file__).parent))
from test_adaptive_compensator import conditioned_net, identity_net, pi_inverse, signal  # noqa: E402
from test_export_cli import lightning_ckpt, trained  # noqa: E402

D = torch.float64
KW = {"limits": (-10.0, 10.0), "direction": "increasing", "input_range": (-2.5, 2.5)}
MODELS = {"pi_inverse": pi_inverse, "identity_net": identity_net, "conditioned": conditioned_net}
#: (model, method): the PI inverse's affine form, a network's folded readout, a conditioned one
CASES = [("pi_inverse", "rls"), ("identity_net", "nlms"), ("conditioned", "rls")]
TOL = 1e-12


def run_data(n: int, conditioned: bool, seed: int = 0) -> dict[str, torch.Tensor]:
    """Desired outputs and the pairs a drifting device gives: the applied command is the
    offline inverse's, the measured response drifts in gain (+40 % over the run) and offset,
    with noise, NaN bursts in either member, outliers, an inf, and NaN/out-of-range desired
    samples; the conditions (one, on [0, 1]) ramp with NaN among them."""
    g = torch.Generator().manual_seed(seed)
    x = signal(n, seed=seed + 7)
    applied = pi_inverse()(x)[0]
    t = torch.arange(n, dtype=D) / n
    measured = x * (1.0 + 0.4 * t) + 0.05 * t + 0.01 * torch.randn(n, generator=g, dtype=D)
    for start in range(n // 7, n, n // 5):  # NaN bursts
        measured[start:start + 15] = math.nan
        applied[start + 40:start + 47] = math.nan
    spikes = torch.randint(0, n, (max(n // 200, 3),), generator=g)
    measured[spikes] += 30.0  # outliers (clamped to the input range)
    measured[n // 3] = math.inf
    applied[n // 2] = -math.inf
    x = x.clone()
    x[n // 4:n // 4 + 3] = math.nan
    x[n // 6] = 9.0  # out of range: clamped and counted
    out = {"x": x, "measured": torch.cat([measured[:1] * math.nan, measured[:-1]]),
           "applied": torch.cat([applied[:1] * math.nan, applied[:-1]])}
    if conditioned:
        c = torch.linspace(0.0, 1.0, n, dtype=D).unsqueeze(1)
        c[n // 5] = math.nan
        out["c"] = c
    return out


def compensator(name: str, method: str) -> AdaptiveCompensator:
    return AdaptiveCompensator(MODELS[name](), adapt=method, **KW)


def steps(stepper, data: dict[str, torch.Tensor], n: int | None = None) -> torch.Tensor:
    """The commands of ``stepper.step`` over ``data`` (batch 1)."""
    c = data.get("c")
    out = []
    for t in range(data["x"].numel() if n is None else n):
        cond = None if c is None else c[t:t + 1]
        out.append(stepper.step(data["x"][t:t + 1], cond, data["measured"][t:t + 1],
                                data["applied"][t:t + 1]))
    return torch.cat(out).double()


def counters(stepper) -> list[int]:
    return [int(f()[0]) for f in (stepper.nonfinite_count, stepper.out_of_range_count,
                                  stepper.updates_count, stepper.skipped_count,
                                  stepper.refused_count)]


def check_parity(eager: AdaptiveCompensator, stepper, data, meta: dict[str, str],
                 tol: float = TOL) -> float:
    """Steps both over ``data``: commands within ``tol``, equal counters, equal weights (from
    the stepper's state at the metadata's ``weights`` index). Returns the largest gap."""
    want = steps(eager, data)
    got = steps(stepper, data)
    gap = float((want - got).abs().max())
    assert gap <= tol, gap
    counts = counters(eager)
    assert counters(stepper) == counts
    assert counts[2] > 100 and counts[3] > 20 and counts[0] > 0 and counts[1] > 0
    w = int(meta["weights"])
    assert float((stepper.state[w] - eager.state[w]).abs().max()) <= tol
    assert float((stepper.adapted_weights() - eager.adapted_weights()).abs().max()) <= tol
    moved = float((eager.adapted_weights()[0] - eager.offline_weights()).abs().max())
    assert moved > 1e-3  # the weights did adapt
    return gap


@pytest.mark.parametrize("name, method", CASES)
def test_torchscript_file_steps_as_the_eager_compensator(tmp_path, name, method) -> None:
    comp = compensator(name, method)
    to_torchscript(comp, tmp_path / "a.pt")
    module = load_torchscript(tmp_path / "a.pt")
    data = run_data(2000, name == "conditioned")
    check_parity(compensator(name, method), module, data, module.torchhys_metadata)


@pytest.mark.parametrize("name, method", CASES)
def test_onnx_runtime_steps_as_the_eager_compensator(tmp_path, name, method) -> None:
    pytest.importorskip("onnxruntime", reason="the onnx extra (pip install 'torchhys[onnx]')")
    from torchhys.deploy.export_onnx import load_onnx, to_onnx

    to_onnx(MODELS[name](), tmp_path / "a.onnx", adapt=method, **KW)
    stepper = load_onnx(tmp_path / "a.onnx")
    names = [i.name for i in stepper.session.get_inputs()]
    pair = ["measured_prev", "applied_prev"]
    assert names[:4] == ["x", "conditions", *pair] if name == "conditioned" else names[:3] == [
        "x", *pair]
    data = run_data(1000, name == "conditioned")  # the export takes most of the time
    check_parity(compensator(name, method), stepper, data, stepper.metadata)


@pytest.mark.slow
@pytest.mark.parametrize("name, method", CASES)
def test_1e4_samples_torchscript_and_onnx(tmp_path, name, method) -> None:
    pytest.importorskip("onnxruntime", reason="the onnx extra (pip install 'torchhys[onnx]')")
    from torchhys.deploy.export_onnx import load_onnx, to_onnx

    comp = compensator(name, method)
    to_torchscript(comp, tmp_path / "a.pt")
    to_onnx(comp, tmp_path / "a.onnx")
    data = run_data(10_000, name == "conditioned", seed=3)
    module = load_torchscript(tmp_path / "a.pt")
    check_parity(compensator(name, method), module, data, module.torchhys_metadata)
    stepper = load_onnx(tmp_path / "a.onnx")
    # ONNX Runtime's sums round otherwise than torch's, and RLS's gain amplifies that where
    # the covariance is ill-conditioned: the conditioned RLS reached 3.0e-12 at one sample
    # of 1e4 (|u| 1.35, the covariance's condition number 5e4); the others stay below 4e-14
    tol = 1e-11 if name == "conditioned" else TOL
    check_parity(compensator(name, method), stepper, data, stepper.metadata, tol)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["rls", "nlms"])
def test_aoti_package_steps_as_the_eager_compensator(tmp_path, method) -> None:
    from torchhys.deploy.export import load_aoti, to_aoti

    to_aoti(pi_inverse(), tmp_path / "a.pt2", adapt=method, **KW)
    stepper = load_aoti(tmp_path / "a.pt2")
    assert stepper.metadata["adapt"] == method
    data = run_data(2000, False)
    check_parity(compensator("pi_inverse", method), stepper, data, stepper.metadata)
    with pytest.raises(ValueError, match=r"step: measured_prev must have shape \(1,\)"):
        stepper.step(torch.zeros(1, dtype=D), None, torch.zeros(2, dtype=D))


def test_scripted_reset_returns_to_the_offline_weights(tmp_path) -> None:
    comp = compensator("identity_net", "rls")
    to_torchscript(comp, tmp_path / "a.pt")
    module = load_torchscript(tmp_path / "a.pt")
    offline = module.adapted_weights().clone()
    assert torch.equal(offline[0], comp.offline_weights())
    assert torch.equal(module.offline_weights(), comp.offline_weights())
    data = run_data(400, False)
    first = steps(module, data)
    assert not torch.equal(module.adapted_weights(), offline)
    module.reset()
    assert torch.equal(module.adapted_weights(), offline)  # bit for bit
    assert int(module.updates_count()[0]) == 0 and int(module.skipped_count()[0]) == 0
    assert torch.equal(steps(module, data), first)  # a fresh run again
    # a missing pair (None) is no update, counted as skipped
    module.reset()
    module.step(data["x"][10:11])
    module.step(data["x"][11:12], None, data["x"][10:11])
    assert int(module.skipped_count()[0]) == 2 and int(module.updates_count()[0]) == 0


def test_metadata_names_the_adaptation(tmp_path) -> None:
    comp = compensator("pi_inverse", "rls")
    to_torchscript(comp, tmp_path / "a.pt")
    meta = load_torchscript(tmp_path / "a.pt").torchhys_metadata
    k, m = comp.k, comp.m
    assert set(ADAPT_KEYS) <= set(meta)
    assert meta["adapt"] == "rls" and meta["n_weights"] == str(m)
    assert meta["weights"] == str(2 * k) and meta["covariance"] == str(2 * k + 1)
    assert meta["adapt_counts"] == str(len(comp.initial_state(1)) - 1)
    assert (meta["forgetting"], meta["adapt_bound"]) == ("0.995", "0.5")
    state = comp.initial_state(1)
    assert int(meta["n_state"]) == len(state)
    assert state[int(meta["weights"])].shape == (1, m)
    assert state[int(meta["covariance"])].shape == (1, m * m)
    w0 = torch.tensor([float(v) for v in meta["w0"].split(",")], dtype=D)
    scale = torch.tensor([float(v) for v in meta["inv_scale"].split(",")], dtype=D)
    assert torch.equal(w0 * scale, comp.offline_weights())
    nlms = AdaptiveCompensator(pi_inverse(), adapt="nlms", adapt_bound=0.3, nlms_step=0.2, **KW)
    to_torchscript(nlms, tmp_path / "n.pt")
    meta = load_torchscript(tmp_path / "n.pt").torchhys_metadata
    assert (meta["adapt"], meta["adapt_bound"], meta["nlms_step"]) == ("nlms", "0.3", "0.2")
    assert "covariance" not in meta  # empty for NLMS: left out as the empty condition keys
    to_torchscript(pi_inverse(), tmp_path / "s.pt", **KW)
    assert not set(ADAPT_KEYS) & set(load_torchscript(tmp_path / "s.pt").torchhys_metadata)


def test_steppers_refuse_bad_pairs(tmp_path) -> None:
    pytest.importorskip("onnxruntime", reason="the onnx extra (pip install 'torchhys[onnx]')")
    from torchhys.deploy.export_onnx import load_onnx, to_onnx

    to_onnx(pi_inverse(), tmp_path / "s.onnx", **KW)
    static = load_onnx(tmp_path / "s.onnx")
    one = torch.zeros(1, dtype=D)
    with pytest.raises(ValueError, match=r"^step: applied_prev given, but the file does not "
                                         r"adapt \(exported with adapt='none'\)$"):
        static.step(one, applied_prev=one)
    with pytest.raises(ValueError, match="static.*no adapted weights|does not adapt"):
        static.adapted_weights()
    to_onnx(pi_inverse(), tmp_path / "a.onnx", adapt="nlms", **KW)
    stepper = load_onnx(tmp_path / "a.onnx")
    with pytest.raises(ValueError, match=r"^step: measured_prev must have shape \(1,\), got "
                                         r"\(2,\)$"):
        stepper.step(one, None, torch.zeros(2, dtype=D), one)
    with pytest.raises(ValueError, match="conditions given, but the file takes none"):
        stepper.step(one, torch.zeros(1, 1, dtype=D), one, one)
    stepper.step(one)  # no pair: NaN, skipped
    stepper.step(one, applied_prev=one)
    assert int(stepper.skipped_count()[0]) == 2


def test_python_exports_refuse_bad_options(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"^forgetting must be in \(0, 1\], got 1.5$"):
        to_torchscript(pi_inverse(), tmp_path / "a.pt", adapt="rls", forgetting=1.5, **KW)
    with pytest.raises(ValueError, match="adapt must be one of"):
        to_torchscript(pi_inverse(), tmp_path / "a.pt", adapt="lms", **KW)
    comp = StreamingCompensator(pi_inverse(), **KW)
    with pytest.raises(ValueError, match="adapt: fixed when the StreamingCompensator is built"):
        to_torchscript(comp, tmp_path / "a.pt", adapt="rls")
    assert not (tmp_path / "a.pt").exists()


# ---- the command line


def _ckpt(tmp_path: Path) -> tuple[Path, torch.nn.Module]:
    """The CLI tests' network with its readout fitted to u = 0.5 x (least squares)."""
    from torchhys.selection.candidates import solve_readout
    from torchhys.selection.folds import Batch

    net = trained().double()
    x = 3 * torch.sin(torch.linspace(0, 20, 400, dtype=D))
    solve_readout(net, Batch(x[None], 0.5 * x[None], torch.ones(1, 400, dtype=torch.bool)))
    torch.save(lightning_ckpt(net), tmp_path / "m.ckpt")
    return tmp_path / "m.ckpt", net


def test_cli_adapt_rls_writes_the_adaptive_torchscript_file(tmp_path, capsys) -> None:
    ckpt, net = _ckpt(tmp_path)
    out = tmp_path / "m.pt"
    rc = main(["--ckpt", str(ckpt), "--format", "torchscript", "--out", str(out),
               "--limits", "-2", "2", "--adapt", "rls", "--forgetting", "0.995",
               "--adapt-bound", "0.3"])
    report = capsys.readouterr().out
    assert rc == 0 and "adaptation rls (forgetting 0.995, bound 0.3)" in report
    module = load_torchscript(out)
    assert module.torchhys_metadata["adapt"] == "rls"
    eager = AdaptiveCompensator(net, adapt="rls", forgetting=0.995, adapt_bound=0.3,
                                limits=(-2.0, 2.0))
    x = 2 * torch.sin(torch.linspace(0, 30, 500, dtype=D))
    u = 0.6 * x  # a device with another gain than the fit's (0.5)
    gap = 0.0
    for t in range(1, 500):
        args = (x[t:t + 1], None, x[t - 1:t], u[t - 1:t])
        gap = max(gap, float((module.step(*args) - eager.step(*args)).abs().max()))
    assert gap <= TOL
    assert int(module.updates_count()[0]) == int(eager.updates_count()[0]) > 100
    assert float((module.adapted_weights() - eager.adapted_weights()).abs().max()) <= TOL


def test_cli_adapt_nlms_onnx_and_c(tmp_path, capsys) -> None:
    pytest.importorskip("onnxruntime", reason="the onnx extra (pip install 'torchhys[onnx]')")
    from torchhys.deploy.export_onnx import load_onnx

    ckpt, _ = _ckpt(tmp_path)
    rc = main(["--ckpt", str(ckpt), "--format", "onnx", "--out", str(tmp_path / "m.onnx"),
               "--adapt", "nlms", "--nlms-step", "0.25"])
    assert rc == 0 and "adaptation nlms (step 0.25, bound 0.5)" in capsys.readouterr().out
    meta = load_onnx(tmp_path / "m.onnx").metadata
    assert (meta["adapt"], meta["nlms_step"]) == ("nlms", "0.25")
    rc = main(["--ckpt", str(ckpt), "--format", "c", "--out", str(tmp_path), "--adapt", "nlms"])
    assert rc == 0
    assert "torchhys_comp_step_adapt" in (tmp_path / "torchhys_comp.h").read_text()


@pytest.mark.parametrize("extra, message", [
    (["--adapt", "rls", "--forgetting", "1.5"],
     r"--forgetting must be in \(0, 1\], got 1.5"),
    (["--adapt", "nlms", "--adapt-bound", "-1"],
     r"--adapt-bound must be a finite number >= 0, got -1.0"),
    (["--adapt", "nlms", "--nlms-step", "0"], r"--nlms-step must be in \(0, 1\]"),
])
def test_cli_bad_adaptive_options(tmp_path, capsys, extra, message) -> None:
    ckpt, _ = _ckpt(tmp_path)
    rc = main(["--ckpt", str(ckpt), "--format", "torchscript", "--out",
               str(tmp_path / "m.pt"), *extra])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert err.startswith("torchhys export: error: ") and __import__("re").search(message, err)
    assert not (tmp_path / "m.pt").exists()


def test_cli_adapt_on_a_composed_model(tmp_path, capsys) -> None:
    from test_compose_training_spec import SPEC, _trained

    model = _trained()
    state = {f"net.{k}": v for k, v in model.state_dict().items()}
    torch.save({"state_dict": state, "hyper_parameters": {"net": SPEC}}, tmp_path / "c.ckpt")
    rc = main(["--ckpt", str(tmp_path / "c.ckpt"), "--format", "torchscript", "--out",
               str(tmp_path / "m.pt"), "--adapt", "rls"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1
    assert "error: --adapt rls: the checkpoint's model: its compensator head" in err
    assert "no affine readout" in err
    with pytest.raises(ValueError, match="^model: its compensator head .* no affine readout"):
        to_torchscript(model, tmp_path / "m.pt", adapt="nlms")
