"""Config family operators (``pi_nonneg``, ``gpi``, ``preisach``, ``stop_pi``,
``jiles_atherton``): each
identifies its model on the training split (recovering a plant of its own family), is saved
in the checkpoint, streams and exports like any operator; a family that cannot be fitted is
skipped by model selection; bad options are clear errors."""

from __future__ import annotations

import csv
import math
import sys
import warnings
from pathlib import Path

import pytest
import torch
from _helpers import RAW, sine_loops
from _training_helpers import DROP, LINE, small_config, trainer

from torchhys import (
    Drift,
    GeneralizedPIInverse,
    GeneralizedPrandtlIshlinskii,
    InverseHysteresisNet,
    JilesAtherton,
    PrandtlIshlinskii,
    Preisach,
    StopPrandtlIshlinskii,
)
from torchhys.cli.main import main
from torchhys.deploy.export import load_torchscript, to_torchscript
from torchhys.identification.errors import FitError
from torchhys.identification.jiles_atherton import _substeps
from torchhys.identification.specs import build_operators, fit_data_dependent
from torchhys.selection import run as selection_run
from torchhys.training import HysteresisDataModule, InverseHysteresisModule

F64 = torch.float64
torch.set_num_threads(1)


def signal(T: int = 600, rows: int = 1) -> torch.Tensor:
    """Decaying and growing sine sweeps: major loops with minor loops inside, (rows, T)."""
    t = torch.linspace(0, 1, T, dtype=F64)
    out = [(1.0 + 0.5 * r) * torch.sin(2 * math.pi * 6 * t) * (0.3 + 0.7 * torch.abs(
        torch.cos(2 * math.pi * (1.5 + r) * t))) for r in range(rows)]
    return torch.stack(out)


def pi_plant(x: torch.Tensor) -> torch.Tensor:
    return PrandtlIshlinskii(torch.tensor([0.2, 0.6, 1.2], dtype=F64),
                             torch.tensor([0.5, 0.3, 0.4], dtype=F64), linear_weight=0.6)(x)[0]


def gpi_plant(x: torch.Tensor) -> torch.Tensor:
    """A saturating, asymmetric loop: tanh of a PI output with an offset."""
    return torch.tanh(0.8 * pi_plant(x) + 0.4)


def fitted(spec: dict, x: torch.Tensor, y: torch.Tensor, warmup: int = 0,
           mask: torch.Tensor | None = None) -> torch.nn.Module:
    (op,), fitters = build_operators(spec)
    op = op.double()
    fit_data_dependent(torch.nn.ModuleList([op]), fitters, x, y, warmup=warmup, mask=mask)
    return op


def affine_rmse(feature: torch.Tensor, y: torch.Tensor) -> float:
    """RMS error of the best affine map of the feature to y (what the readout learns)."""
    a = torch.stack([feature.reshape(-1), torch.ones(feature.numel(), dtype=F64)], 1)
    coef = torch.linalg.lstsq(a, y.reshape(-1, 1)).solution
    return float((a @ coef - y.reshape(-1, 1)).square().mean().sqrt())


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_pi_nonneg_direct_recovers_a_pi_plant_of_either_sign(sign):
    x = signal()
    y = 3.0 * sign * pi_plant(x) + 2.0  # scaled, shifted, maybe negated
    op = fitted({"fit": "pi_nonneg", "n_widths": 12, "ridge": 0.0}, x, y)
    assert isinstance(op, PrandtlIshlinskii) and op.n_operators == 12
    assert affine_rmse(op(x)[0], y) < 0.01 * float(y.std())


def test_pi_nonneg_inverse_recovers_the_inverse_of_a_pi_plant():
    x = signal()
    y = pi_plant(x)
    # the target is the input of the plant: the inverse direction
    op = fitted({"fit": "pi_nonneg", "n_widths": 12, "direction": "inverse"}, y, x)
    assert affine_rmse(op(y)[0], x) < 0.01 * float(x.std())
    # a non-negative PI model of x from y draws loops of the wrong orientation: no better
    # than a straight line, which the fit reports
    with pytest.raises(FitError, match="no better than a straight line"):
        fitted({"fit": "pi_nonneg", "n_widths": 12, "direction": "direct"}, y, x)


def test_gpi_both_directions_recover_a_generalized_pi_plant():
    x = 1.5 * signal()
    y = gpi_plant(x)
    op = fitted({"fit": "gpi", "n_widths": 10, "units": 4, "epochs": 150}, x, y)
    assert isinstance(op, GeneralizedPrandtlIshlinskii)
    # well below the straight line (fit_generalized_pi stops at a local optimum here)
    assert affine_rmse(op(x)[0], y) < 0.3 * affine_rmse(x, y)
    inv = fitted({"fit": "gpi", "n_widths": 10, "units": 4, "epochs": 150,
                  "direction": "inverse"}, y, x)
    assert isinstance(inv, GeneralizedPIInverse)
    assert affine_rmse(inv(y)[0], x) < 0.3 * affine_rmse(y, x)
    assert not any(p.requires_grad for p in inv.parameters())


@pytest.mark.parametrize("samples, work, expected", [
    (400, None, 150),  # a short record: every epoch
    (400, 400 * 60, 60),  # a long one (here: a small bound): fewer
    (400, 400, 20),  # at least 20
])
def test_gpi_iterations_bounded_by_sample_iterations(monkeypatch, samples, work, expected):
    import torchhys.identification.generalized_pi as generalized_pi
    from torchhys.identification import _fit_cache as fit_cache

    fit_cache.clear()  # fitted here, not taken from an earlier test's fit
    seen = []
    real = generalized_pi.fit_generalized_pi
    monkeypatch.setattr(generalized_pi, "fit_generalized_pi",
                        lambda *a, **k: seen.append(k["lbfgs_epochs"]) or real(*a, **k))
    x = 1.5 * signal(samples)
    spec = {"fit": "gpi", "n_widths": 6, "units": 2, "epochs": 150}
    if work is not None:
        spec["sample_iterations"] = work
    fitted(spec, x, gpi_plant(x))
    assert seen and seen[0] == expected


def test_preisach_recovers_a_preisach_plant():
    x = signal(rows=2)
    plant = Preisach(float(x.min()), float(x.max()), 8).double()  # the grid the fit uses
    with torch.no_grad():
        plant.weights.copy_(torch.rand(plant.n_relays, generator=torch.Generator().manual_seed(0),
                                       dtype=F64))
        plant.linear.fill_(0.2)
    y = -plant(x)[0].detach()  # the other orientation: the negated fit wins
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        op = fitted({"fit": "preisach", "n": 8, "smoothness": 0.0}, x, y)
    assert affine_rmse(op(x)[0], y) < 0.1 * float(y.std())


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_stop_pi_recovers_a_stop_plant_of_either_sign(sign):
    """A friction element in series with a stiffening spring (non-negative slopes, clockwise
    loops) and its negation (anticlockwise: the negated fit wins), in physical units: the
    family's model of the standardized target is mapped back to the input's units."""
    x = 3.0 * signal(rows=2) + 1.0
    plant = StopPrandtlIshlinskii(torch.tensor([0.5, 1.5, 4.0], dtype=F64),
                                  torch.tensor([[0.2, 0.1, 0.3, 0.6], [0.0, 0.4, 0.4, 0.1],
                                                [0.1, 0.2, 0.2, 0.5]], dtype=F64),
                                  center=1.0, linear_weight=0.1, offset=2.0)
    y = sign * plant(x)[0].detach()
    op = fitted({"fit": "stop_pi", "n_widths": 10, "segments": 4, "ridge": 0.0}, x, y)
    assert isinstance(op, StopPrandtlIshlinskii)
    assert affine_rmse(op(x)[0], y) < 0.05 * float(y.std())
    # the family's output is a model of the standardized target: a positive multiple
    t = (y - y.mean()) / y.std()
    assert float(torch.corrcoef(torch.stack([op(x)[0].flatten(), t.flatten()]))[0, 1]) > 0.99


def ratcheting_plant(x: torch.Tensor) -> torch.Tensor:
    """A PI loop whose level climbs with the input's accumulated variation and slows down
    (a shape-memory alloy's ratcheting)."""
    drift = Drift(torch.tensor([15.0, 60.0], dtype=F64), torch.tensor([0.8, 1.2], dtype=F64))
    return pi_plant(x) + drift(x)[0]


def test_drift_beside_stop_pi_follows_a_ratcheting_plant():
    """Fitted on the first two thirds of the record, one affine readout of the stop-type
    model and the drift predicts the last third (where the level has climbed further) far
    better than the stop-type model alone; each family's output is a fitted model."""
    x = signal(T=900)
    y = ratcheting_plant(x)
    cut = 600
    (stop, drift), fitters = build_operators([{"fit": "stop_pi", "n_widths": 8},
                                              {"fit": "drift"}])
    ops = torch.nn.ModuleList([stop.double(), drift.double()])
    fit_data_dependent(ops, fitters, x[:, :cut], y[:, :cut])
    assert isinstance(ops[1], Drift) and bool((ops[1].weights >= 0).all())
    feats = [op(x)[0].reshape(-1) for op in ops]

    def held_out(columns):
        a = torch.stack(columns + [x.reshape(-1), torch.ones(x.numel(), dtype=F64)], 1)
        coef = torch.linalg.lstsq(a[:cut], y.reshape(-1, 1)[:cut]).solution
        return float((a[cut:] @ coef - y.reshape(-1, 1)[cut:]).square().mean().sqrt())

    alone, both = held_out(feats[:1]), held_out(feats)
    assert both < 0.3 * alone, (both, alone)


def test_a_family_that_cannot_fit_raises_fit_error():
    x = signal()
    with pytest.raises(FitError, match="must vary"):
        fitted({"fit": "gpi"}, x, torch.zeros_like(x))
    with pytest.raises(FitError, match="no better than a straight line"):
        # noise unrelated to the input: nothing to fit
        noise = torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=F64)
        fitted({"fit": "pi_nonneg", "n_widths": 3, "direction": "inverse", "ridge": 1.0},
               x, noise.cumsum(1))


@pytest.mark.parametrize("spec, match", [
    ({"fit": "pi_nonneg", "direction": "sideways"}, "direction must be one of"),
    ({"fit": "pi_nonneg", "ridge": -1.0}, "ridge must be 'auto' or a finite number >= 0"),
    ({"fit": "gpi", "ridge": float("inf")}, "ridge must be 'auto' or a finite number >= 0"),
    ({"fit": "gpi", "unit": 3}, r"unknown option\(s\) \['unit'\]"),
    ({"fit": "gpi", "power": 0}, "power must be a finite number > 0"),
    ({"fit": "pi_nonneg", "power": float("inf")}, "power must be a finite number > 0"),
    ({"fit": "gpi", "power": True}, "power must be a finite number > 0"),
    ({"fit": "gpi", "sample_iterations": 0}, "sample_iterations must be a finite number > 0"),
    ({"fit": "preisach", "n": 1}, "n must be"),
    ({"fit": "preisach", "smoothness": "big"}, "smoothness must be 'auto'"),
    ({"fit": "stop_pi", "segments": 0}, "segments must be"),
    ({"fit": "stop_pi", "n": 5}, r"unknown option\(s\) \['n'\]"),
    ({"fit": "stop_pi", "ridge": -1e-3}, "ridge must be 'auto' or a finite number >= 0"),
    ({"fit": "drift", "scales": []}, "scales must be a non-empty list"),
    ({"fit": "drift", "scales": [1.0, -2.0]}, r"scales\[\] must be a finite number > 0"),
    ({"fit": "drift", "n": 3}, r"unknown option\(s\) \['n'\]"),
])
def test_bad_options(spec, match):
    with pytest.raises(ValueError, match=match):
        build_operators(spec)


def test_stop_pi_flag_must_be_a_bool():
    with pytest.raises(TypeError, match="'stop_pi': nonnegative must be True or False"):
        build_operators({"fit": "stop_pi", "nonnegative": "yes"})


@pytest.mark.parametrize("spec", [
    {"fit": "pi_nonneg", "n_widths": 6, "direction": "inverse"},
    {"fit": "gpi", "n_widths": 6, "units": 2, "epochs": 30, "direction": "inverse"},
    {"fit": "preisach", "n": 6, "smoothness": 1e-4},
    {"fit": "stop_pi", "n_widths": 6, "segments": 3},
    [{"fit": "stop_pi", "n_widths": 6, "segments": 3}, {"fit": "drift"}],
])
def test_fitted_in_training_saved_and_exported(tmp_path, spec):
    """Through the Lightning module: fitted on the training split, restored from the
    checkpoint bit for bit, and the TorchScript compensator equals the module."""
    torch.manual_seed(0)
    dm = HysteresisDataModule(t_end=2 * math.pi, split=[0.6, 0.2, 0.2])
    module = InverseHysteresisModule(operator=spec if isinstance(spec, list) else [spec],
                                     hidden=1, activation="identity", optimizer="lbfgs",
                                     lr=1.0)
    t = trainer(max_epochs=3, enable_checkpointing=True, default_root_dir=tmp_path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        t.fit(module, dm)
    path = tmp_path / "m.ckpt"
    t.save_checkpoint(path)
    loaded = InverseHysteresisModule.load_from_checkpoint(path)
    for a, b in zip(module.net.state_dict().values(), loaded.net.state_dict().values(),
                    strict=True):
        assert torch.equal(a, b)
    x = dm.x
    with torch.no_grad():
        expected = module(x)
    assert float((expected - dm.y).square().mean()) < float(dm.y.var())  # it learned something
    out = tmp_path / "comp.pt"
    # no saturation at the training range, no clamp or guard
    to_torchscript(loaded.net, out, limits=(-1e6, 1e6), **RAW)
    torch.testing.assert_close(load_torchscript(out)(x).double(), expected, rtol=0, atol=1e-9)


def line_or_gpi(tmp_path, select_cv: int | None = None,
                split: tuple[float, ...] = (0.5, 0.25, 0.25)):
    """A config choosing between the straight line and a small generalized PI model."""
    return small_config(
        tmp_path, "c.yaml",
        trainer={"check_val_every_n_epoch": DROP, "default_root_dir": tmp_path / "run"},
        model={**LINE, "lr": 1.0, "select": [
            {"operator": None},
            {"operator": [{"fit": "gpi", "n_widths": 4, "units": 2, "epochs": 5}]}],
            "select_cv": DROP if select_cv is None else select_cv},
        data={"simulation": DROP, "dt": 0.05, "t_end": 12.6, "split": list(split)})


def test_selection_skips_a_candidate_that_cannot_be_fitted(monkeypatch, tmp_path, capsys):
    """A candidate whose family raises FitError scores NaN, with a warning; the line wins."""
    cfg = line_or_gpi(tmp_path)

    def refuse(*args, **kwargs):
        raise FitError("gpi: refused for the test")

    monkeypatch.setattr("torchhys.identification.generalized_pi.fit_generalized_pi", refuse)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    with pytest.warns(RuntimeWarning, match="candidate 1 skipped: gpi .*refused"):
        main(["fit", "--config", str(cfg)])
    text = capsys.readouterr().out
    assert "nan" in text and "selected candidate 0" in text
    # the progress line, the table and selection.csv say why (each ridge tried: the
    # order of the ridges is that of their hold-out scores)
    with (Path(tmp_path) / "run/logs/version_0/selection.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    why = rows[1]["error"]
    assert rows[0]["error"] == "" and why.startswith("FitError: gpi (direct): ridge ")
    assert why.count("gpi: refused for the test") == 3
    assert f"candidate 1 (2 of 2): val_mse nan (failed: {why})" in text
    assert f"error: {why}" in text


def test_a_candidate_that_fails_a_fold_is_not_trained_on_the_others(monkeypatch, tmp_path,
                                                                    capsys):
    """Under cross-validation a candidate that cannot be fitted on one fold scores NaN
    (pooled over the folds it would be NaN anyway): one warning, no fits on later folds,
    NaN in every fold column of its row; the other candidates run every fold."""
    cfg = line_or_gpi(tmp_path, 3, (0.6, 0.0, 0.4))

    def refuse(*args, **kwargs):
        raise FitError("gpi: refused for the test")

    runs = []
    fit = selection_run.fit_candidate

    def watched(spec, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003
        runs.append("gpi" if spec["operator"] else "line")
        return fit(spec, *args, **kwargs)

    monkeypatch.setattr("torchhys.identification.generalized_pi.fit_generalized_pi", refuse)
    monkeypatch.setattr(selection_run, "fit_candidate", watched)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    with pytest.warns(RuntimeWarning, match="skipped") as record:
        main(["fit", "--config", str(cfg)])
    skipped = [str(w.message) for w in record if "skipped" in str(w.message)]
    assert len(skipped) == 1 and "candidate 1, fold 1 of 3 skipped: gpi" in skipped[0]
    # the line on its three folds, the family on its first only, then the line's final fit
    assert runs == ["line"] * 3 + ["gpi", "line"]
    with (tmp_path / "run/logs/version_0/selection.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    folds = [[float(r[f"fold_{j}"]) for j in (1, 2, 3)] for r in rows]
    assert all(math.isfinite(v) for v in folds[0])
    assert all(math.isnan(v) for v in folds[1]) and math.isnan(float(rows[1]["val_mse"]))
    assert rows[0]["error"] == ""
    assert rows[1]["error"].startswith("fold 1 of 3: FitError: gpi (direct): ridge")
    assert rows[1]["error"].endswith("refused for the test (folds 2-3 not run)")
    assert f"candidate 1 (2 of 2): val_mse nan (failed: {rows[1]['error']}), 3 folds" in (
        capsys.readouterr().out)


def test_identity_readout_is_affine():
    net = InverseHysteresisNet(None, 1, activation="identity").double()
    x = torch.linspace(-2, 2, 9, dtype=F64)
    y, _ = net(x)
    second = torch.diff(y, n=2)
    torch.testing.assert_close(second, torch.zeros_like(second), rtol=0, atol=1e-12)


# --- jiles_atherton -----------------------------------------------------------------------
CORE = dict(ms=3e5, a=18.0, k=13.0, alpha=1.2e-4, c=0.8)
"""A MnZn ferrite core (B in T, H in A/m)."""
JA_FAST = {"fit": "jiles_atherton", "starts": 2, "iterations": 20}


def bh_loops(n: int = 64, scale: float = 1.0, mu0: float = 4e-7 * math.pi
             ) -> tuple[torch.Tensor, torch.Tensor]:
    """B-H loops of CORE: cosines of flux density of 0.12 and 0.36 T (times ``scale``, the
    input unit) from the positive tip, 3 periods of n samples, and the fields; (2, 3 n)."""
    b = sine_loops([0.12 * scale, 0.36 * scale], n=n)
    with torch.no_grad():
        h, _ = JilesAtherton(**CORE, mu0=mu0, substeps=8)(b)
    return b, h


def test_jiles_atherton_recovers_a_jiles_atherton_core():
    """Fitted to the field itself (physical units): far better than a line, near the core."""
    b, h = bh_loops()
    op = fitted(JA_FAST, b, h, warmup=64)
    assert isinstance(op, JilesAtherton) and not any(p.requires_grad for p in op.parameters())
    assert op.substeps == _substeps(b) and op.mu0 == 4e-7 * math.pi
    with torch.no_grad():
        out = op(b)[0]
    rmse = float((out - h)[:, 64:].square().mean().sqrt())
    assert rmse < 0.05 * affine_rmse(b[:, 64:], h[:, 64:]), rmse
    # (k, the most sensitive, absorbs part of the Euler error: 2 steps a sample, the core 8)
    ms, a, _, alpha, _ = (float(v) for v in op.parameters_effective())
    assert ms == pytest.approx(3e5, rel=0.02) and a == pytest.approx(18.0, rel=0.1)
    assert alpha == pytest.approx(1.2e-4, rel=0.1)


def test_jiles_atherton_in_other_units_keeps_mu0_and_substeps():
    """B in mT (mu0 4 pi 1e-4), 32 samples a period, substeps given: the placeholder takes
    the fitted model's mu0 and substeps (saved in its state dict), not its defaults."""
    b, h = bh_loops(n=32, scale=1e3, mu0=4e-4 * math.pi)
    op = fitted({**JA_FAST, "mu0": 4e-4 * math.pi, "substeps": 5}, b, h, warmup=32)
    assert op.substeps == 5 and op.mu0 == 4e-4 * math.pi
    with torch.no_grad():
        out = op(b)[0]
    assert float((out - h)[:, 32:].square().mean().sqrt()) < 0.1 * affine_rmse(b, h)


def test_jiles_atherton_that_cannot_fit_raises_fit_error():
    b, h = bh_loops(n=16)
    with pytest.raises(FitError, match="must vary"):
        fitted(JA_FAST, b, torch.full_like(b, 3.0))
    # a field offset no core shows in steady state from a demagnetised start: the fit stays
    # about the loop, the line takes the offset
    with pytest.raises(FitError, match="jiles_atherton: the fitted model is no better than a "
                                       "straight line"):
        fitted(JA_FAST, b, h + 100.0, warmup=16)
    # the field falling as the flux density rises: no core draws that loop
    with pytest.raises(FitError, match="jiles_atherton: "):
        fitted(JA_FAST, b, -h, warmup=16)
    # fields of 1e160 A/m: every start's squared error overflows (fit_jiles_atherton's
    # ValueError, as a FitError)
    with pytest.raises(FitError, match="jiles_atherton: no Jiles-Atherton fit with a finite"):
        fitted(JA_FAST, b, 1e160 * h, warmup=16)


@pytest.mark.parametrize("spec, match", [
    ({"fit": "jiles_atherton", "mu": 1.0}, r"unknown option\(s\) \['mu'\]"),
    ({"fit": "jiles_atherton", "mu0": 0.0}, "'jiles_atherton': mu0 must be a finite number > 0"),
    ({"fit": "jiles_atherton", "mu0": "4e-7"}, "'jiles_atherton': mu0 must be a finite"),
    ({"fit": "jiles_atherton", "mu0": float("inf")}, "mu0 must be a finite number > 0"),
    ({"fit": "jiles_atherton", "starts": 0}, "'jiles_atherton': starts must be"),
    ({"fit": "jiles_atherton", "iterations": 1.5}, "'jiles_atherton': iterations must be"),
    ({"fit": "jiles_atherton", "substeps": 0}, "'jiles_atherton': substeps must be"),
])
def test_jiles_atherton_bad_options(spec, match):
    with pytest.raises(ValueError, match=match):
        build_operators(spec)


def test_jiles_atherton_fitted_in_training_saved_and_exported(tmp_path):
    """Through the data module and the Lightning module: fitted on the training split,
    restored from the checkpoint into a default placeholder bit for bit (mu0 and substeps
    included), and the TorchScript compensator equals the module."""
    b, h = bh_loops(n=32)
    x, y = b.flatten(), h.flatten()  # one recording: the small loops, then the large ones
    path = tmp_path / "bh.csv"
    path.write_text("B_T,H_Apm\n" + "".join(f"{u!r},{v!r}\n" for u, v in
                                             zip(x.tolist(), y.tolist(), strict=True)))
    dm = HysteresisDataModule(path=str(path), input_column="B_T", target_column="H_Apm",
                              split=[0.7, 0.15, 0.15], warmup=16)
    module = InverseHysteresisModule(operator=[{**JA_FAST, "substeps": 3}], hidden=1,
                                     activation="identity", optimizer="lbfgs", lr=1.0)
    t = trainer(max_epochs=3, enable_checkpointing=True, default_root_dir=tmp_path)
    t.fit(module, dm)
    ckpt = tmp_path / "m.ckpt"
    t.save_checkpoint(ckpt)
    loaded = InverseHysteresisModule.load_from_checkpoint(ckpt)
    assert loaded.net.operators[0].substeps == 3
    for a, b_ in zip(module.net.state_dict().values(), loaded.net.state_dict().values(),
                     strict=True):
        assert torch.equal(a, b_)
    with torch.no_grad():
        expected = module(x)
        assert torch.equal(loaded(x), expected)
    assert float((expected - y).square().mean()) < 0.01 * float(y.var())
    out = tmp_path / "comp.pt"
    to_torchscript(loaded.net, out, limits=(-1e6, 1e6), **RAW)
    torch.testing.assert_close(load_torchscript(out)(x).double(), expected, rtol=0, atol=1e-9)


DIRECT = [
    {"fit": "pi_nonneg", "n_widths": 8},
    {"fit": "gpi", "n_widths": 8, "units": 2, "epochs": 40},
    {"fit": "preisach", "n": 10},
    {"fit": "stop_pi", "n_widths": 8},
    {"fit": "drift"},
]


@pytest.mark.parametrize("spec", DIRECT, ids=lambda s: s["fit"])
def test_family_fits_leave_the_warm_up_targets_out(spec):
    """The warm-up samples only run the states: targets spoiled there (the loop's initial
    curve from the zero state, here a jump and a ramp) change nothing in a model fitted in
    the direct direction. (An inverse fit runs its forward model's states on the target, so
    the warm-up targets set the states it starts the scored samples from.)"""
    x = signal()
    y = gpi_plant(x)
    spoiled = y.clone()
    spoiled[:, :100] += 0.7 + torch.linspace(0, 2, 100, dtype=F64)
    outputs = [fitted(spec, x, t, warmup=100)(x)[0].detach() for t in (y, spoiled)]
    torch.testing.assert_close(outputs[0], outputs[1], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("spec", [*DIRECT, {"fit": "pi_nonneg", "direction": "inverse"}],
                         ids=lambda s: s["fit"] + s.get("direction", ""))
def test_family_fits_leave_the_samples_outside_the_mask_out(spec):
    """A cross-validation fold's block and a shorter row's padding (False in the mask): the
    states run through them, their targets change nothing in the fit, and without the mask
    the same spoiled targets would. (An inverse fit runs its forward model on the target:
    the block's targets set its states after the block, but are never fitted, so a block
    at a row's end changes nothing either.)"""
    x = signal(rows=2)
    y = gpi_plant(x)
    mask = torch.ones_like(x, dtype=torch.bool)
    if spec.get("direction") == "inverse":
        x, y = pi_plant(x), x  # the input a PI model of the target: its inverse fits
        mask[:, 450:] = False
    else:
        mask[0, 250:350] = False
        mask[1, 500:] = False
    bad = torch.where(mask, y, y + 0.7 + torch.linspace(0, 2, x.shape[1], dtype=F64))
    clean = fitted(spec, x, y, warmup=50, mask=mask)(x)[0].detach()
    other = fitted(spec, x, bad, warmup=50, mask=mask)(x)[0].detach()
    torch.testing.assert_close(other, clean, rtol=1e-9, atol=1e-9)
    try:
        moved = fitted(spec, x, bad, warmup=50)(x)[0].detach()
    except FitError:  # the spoiled targets leave no fit better than a line: moved too
        return
    assert float((moved - clean).abs().max()) > 1e-3


@pytest.mark.parametrize("rmse, starts", [(0.5, 1), (0.5004, 1), (0.6, 3)])
def test_gpi_is_not_started_again_when_it_ended_on_the_line(monkeypatch, rmse, starts):
    """A gpi fit no better than a straight line is started again from the next ridges' PI
    fits (a poor local optimum), unless it ended on the line itself (within ON_THE_LINE)."""
    from torchhys.identification import errors as fit_checks
    from torchhys.identification import generalized_pi

    calls = []

    def no_better(model, x, t, scored, name, *args, **kwargs):  # noqa: ANN001
        calls.append(name)
        raise fit_checks.NoBetterThanLine(f"{name}: no better", rmse, 0.5)

    monkeypatch.setattr(generalized_pi, "_checked", no_better)
    _, fit = generalized_pi._gpi({"fit": "gpi", "epochs": 20})
    t = torch.arange(400, dtype=torch.float64)
    x = torch.sin(0.05 * t).reshape(1, -1)
    y = torch.tanh(2 * x) + 0.1 * torch.sin(0.3 * t)
    with pytest.raises(fit_checks.FitError) as err:
        fit(x, y, 0, None)
    assert len(calls) == starts
    assert ("no other start tried" in str(err.value)) == (starts == 1)
