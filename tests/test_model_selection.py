"""``torchhys fit`` with ``model.select``: the choice, its table, the fitted checkpoint, the
test split left alone, blocked cross-validation, errors."""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import re
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from _training_helpers import DROP, LINE, cli, small_config, trainer

from torchhys.cli.export import main as export_main
from torchhys.cli.selection import check_candidates, model_arguments
from torchhys.deploy.export import load_torchscript
from torchhys.selection import CandidateScore, best, standard_error
from torchhys.selection.folds import block_split
from torchhys.selection.progress import brief
from torchhys.training import HysteresisDataModule, InverseHysteresisModule
from torchhys.training.folds import BlockFold, RecordingFold

ROOT = Path(__file__).resolve().parents[1]

# The paper's plant (a Prandtl-Ishlinskii model of plays) over two slow periods, 503
# samples: the least-squares PI operator makes a far better inverse than a plain network
# (a static map) or a few plays, after 20 CG epochs.
DATA = {"dt": 0.05, "t_end": 25.2, "split": [0.5, 0.25, 0.25]}
PI = [{"fit": "pi_ls", "n_widths": 8}]
CANDIDATES = [{"operator": None}, {"operator": PI}, {"operator": [{"fit": "plays", "n": 4}]}]
SELECT = {"trainer": {"max_epochs": 20},
          "model": {"operator": None, "operator_kwargs": DROP, "hidden": 4,
                    "select": CANDIDATES},
          "data": DATA}
"""The sections of :func:`small_config`: a plain network of 4 sigmoids, the PI operator
and 4 plays as candidates (CG)."""


def config(tmp_path: Path, **changes: dict) -> Path:
    """SELECT with ``changes`` applied to each of its sections key by key."""
    sections = {k: {**v, **changes.pop(k, {})} for k, v in SELECT.items()}
    assert not changes, changes
    return small_config(tmp_path, "select.yaml", **sections)


def candidates(i: int, candidate: dict) -> list[dict]:
    """CANDIDATES with candidate ``i`` replaced by ``candidate``."""
    return [candidate if j == i else c for j, c in enumerate(CANDIDATES)]


def table(root: Path) -> list[dict]:
    with (root / "logs/version_0/selection.csv").open() as fh:
        return list(csv.DictReader(fh))


@pytest.fixture
def stages(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Every stage whose batches a HysteresisDataModule hands out."""
    requested: list[str] = []
    batches = HysteresisDataModule.batches

    def record(self: HysteresisDataModule, stage: str) -> list:
        requested.append(stage)
        return batches(self, stage)

    monkeypatch.setattr(HysteresisDataModule, "batches", record)
    return requested


def validation_mse(ckpt: Path, **data) -> float:
    module = InverseHysteresisModule.load_from_checkpoint(ckpt)
    (res,) = trainer(limit_val_batches=None).validate(
        module, HysteresisDataModule(**data), verbose=False)
    return res["val_mse"]


def test_fit_selects_the_best_candidate_and_fits_it(monkeypatch, capsys, tmp_path,
                                                    stages) -> None:
    root = tmp_path / "run"
    cfg = config(tmp_path)
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={root}")
    rows = table(root)
    assert [int(r["candidate"]) for r in rows] == [0, 1, 2]
    assert [json.loads(r["config"]) for r in rows] == [
        {"operator": None}, {"operator": PI}, {"operator": [{"fit": "plays", "n": 4}]}]
    mse = [float(r["val_mse"]) for r in rows]
    assert mse[1] < 0.2 * min(mse[0], mse[2])  # clearly better
    assert [r["selected"] for r in rows] == ["0", "1", "0"]
    out = capsys.readouterr().out
    assert f'selected candidate 1: {{"operator": {json.dumps(PI)}}} (val_mse {mse[1]:.6g})' in out

    # the test split was never handed out, and no test metric was logged
    assert "test" not in stages and {"train", "val"} <= set(stages)
    for log in root.rglob("metrics.csv"):
        assert "test_mse" not in log.read_text()
    assert len(list((root / "logs/version_0/selection").rglob("metrics.csv"))) == 3

    # the chosen configuration is the one fitted and saved, from the same seed
    ckpt = root / "logs/version_0/checkpoints/last.ckpt"
    saved = torch.load(ckpt, weights_only=True)
    assert saved["hyper_parameters"]["operator"] == PI
    assert "select" not in saved["hyper_parameters"]
    assert "net.operators.0.weights" in saved["state_dict"]
    saved_cfg = yaml.safe_load((root / "logs/version_0/config.yaml").read_text())
    assert saved_cfg["model"]["operator"] == PI and "select" not in saved_cfg["model"]
    assert validation_mse(ckpt, **DATA) == pytest.approx(mse[1], rel=1e-6)

    # held-out data scored afterwards: test (the config's select is ignored: the
    # checkpoint gives the model), export
    cli(monkeypatch, "test", "--config", str(cfg), f"--trainer.default_root_dir={root}",
        f"--ckpt_path={ckpt}")
    assert "test" in stages
    out_file = tmp_path / "comp.pt"
    assert export_main(["--ckpt", str(ckpt), "--format", "torchscript", "--out",
                        str(out_file), "--limits", "-100", "100"]) == 0
    x = torch.linspace(-3.0, 3.0, 40, dtype=torch.float64)
    assert load_torchscript(out_file)(x).isfinite().all()


def test_select_on_the_command_line(monkeypatch, tmp_path) -> None:
    root = tmp_path / "run"
    cfg = config(tmp_path, model={"select": DROP})
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={root}",
        "--model.select", json.dumps([{"hidden": 2}, {"operator": PI, "hidden": 2}]))
    rows = table(root)
    assert [json.loads(r["config"]) for r in rows] == [{"hidden": 2},
                                                      {"operator": PI, "hidden": 2}]
    assert [r["selected"] for r in rows] == ["0", "1"]
    hp = torch.load(root / "logs/version_0/checkpoints/last.ckpt",
                    weights_only=True)["hyper_parameters"]
    assert hp["operator"] == PI and hp["hidden"] == 2 and hp["optimizer"] == "cg"
    # resuming fits the checkpoint's model: no second selection
    before = (root / "logs/version_0/selection.csv").stat().st_mtime_ns
    with pytest.warns(UserWarning, match="resumes the checkpoint's model: model.select is"):
        cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={root}",
            "--trainer.max_epochs=21", "--model.select", json.dumps([{"hidden": 3}]),
            f"--ckpt_path={root / 'logs/version_0/checkpoints/last.ckpt'}")
    assert (root / "logs/version_0/selection.csv").stat().st_mtime_ns == before
    assert torch.load(root / "logs/version_1/checkpoints/last.ckpt",
                      weights_only=True)["hyper_parameters"]["hidden"] == 2


def test_candidate_runs_print_one_line_each(monkeypatch, capsys, tmp_path) -> None:
    """The candidates' runs are quiet: no progress bar, model summary or device and seed
    messages per run (6 runs here), one progress line per candidate instead; the final fit
    keeps the config's bar and summary (--verbose: its device and seed lines too)."""
    monkeypatch.setenv("TORCHHYS_VERBOSE", "1")
    cfg = config(tmp_path, trainer={"enable_progress_bar": DROP, "enable_model_summary": DROP},
                 data={"split": [0.6, 0.0, 0.4]}, model={"select_cv": 2})
    records: list[str] = []
    handler = logging.Handler(logging.INFO)
    handler.emit = lambda record: records.append(record.getMessage())  # type: ignore[method-assign]
    loggers = [logging.getLogger(n) for n in ("lightning.pytorch", "lightning.fabric")]
    for log in loggers:
        log.addHandler(handler)
    try:
        cli(monkeypatch, "fit", "--config", str(cfg),
            f"--trainer.default_root_dir={tmp_path / 'run'}")
    finally:
        for log in loggers:
            log.removeHandler(handler)
    out, err = capsys.readouterr()
    # before each candidate: what runs and the time left (estimated once a training ran)
    starts = [line for line in out.splitlines() if " starts, " in line]
    assert [line.split(",")[0] for line in starts] == [
        "candidate 0 (1 of 3) starts", "candidate 1 (2 of 3) starts",
        "candidate 2 (3 of 3) starts"]
    assert "2 trainings, time left: estimated after the first training" in starts[0]
    assert all(re.search(r"2 trainings, about \d+ s left: ", line) for line in starts[1:])
    lines = [line for line in out.splitlines() if line.startswith("candidate ")
             and " starts, " not in line]
    assert [line.split(":")[0] for line in lines] == [
        "candidate 0 (1 of 3)", "candidate 1 (2 of 3)", "candidate 2 (3 of 3)"]
    rows = table(tmp_path / "run")
    for line, row in zip(lines, rows, strict=True):
        assert f"val_mse {float(row['val_mse']):.6g}, 2 folds, " in line
        assert line.endswith(": " + brief(json.loads(row["config"])))
    assert sum("GPU available" in r for r in records) == 1  # the final fit's
    assert sum("Trainable params" in r for r in records + [out]) == 1
    assert sum(r.startswith("Seed set to") for r in records) <= 2  # the CLI's, the final fit's
    assert err.count("Sanity Checking") <= 2  # the final fit's bar only
    # the levels are restored: a later trainer reports as usual
    assert all(log.level == logging.INFO for log in loggers[:1])


def test_blocked_cross_validation_inside_the_training_part(monkeypatch, tmp_path,
                                                           stages) -> None:
    """``select_cv: 3`` on a record without a validation split: each candidate is trained
    three times, the table holds each fold and the MSE over all held-out samples."""
    root = tmp_path / "run"
    cfg = config(tmp_path, data={"split": [0.6, 0.0, 0.4]}, model={"select_cv": 3})
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={root}")
    rows = table(root)
    assert [r["selected"] for r in rows] == ["0", "1", "0"]
    dm = HysteresisDataModule(**{**DATA, "split": [0.6, 0.0, 0.4]})
    counts = [BlockFold(dm, 3, j).n_val for j in range(3)]
    for r in rows:
        folds = [float(r[f"fold_{j}"]) for j in (1, 2, 3)]
        pooled = sum(f * n for f, n in zip(folds, counts, strict=True)) / sum(counts)
        assert float(r["val_mse"]) == pytest.approx(pooled, rel=1e-12)
    assert len(list((root / "logs/version_0/selection").rglob("metrics.csv"))) == 9
    assert "test" not in stages


@pytest.mark.parametrize("warmup", [0, 7])
def test_block_folds_partition_the_scored_samples(warmup: int) -> None:
    dm = HysteresisDataModule(t_end=6.3, split=[0.8, 0.2, 0.0], warmup=warmup)
    x, y, first, mask = dm.batches("train")[0]
    held = []
    for j in range(4):
        fold = BlockFold(dm, 4, j)
        (tx, ty, tw, tmask), = list(fold.train_dataloader())
        (vx, _, _, vmask), = list(fold.val_dataloader())
        assert torch.equal(tx, x) and torch.equal(vx, x) and torch.equal(tw, first)
        assert not (tmask & vmask).any() and torch.equal(tmask | vmask, mask)
        idx = vmask[0].nonzero().flatten()
        assert torch.equal(idx, torch.arange(int(idx[0]), int(idx[-1]) + 1))  # contiguous
        assert fold.n_val == idx.numel()
        # the fits run the whole rows (the states through the block) but use neither the
        # held-out targets nor anything after the training part
        fx, fy = fold.train_tensors()
        assert torch.equal(fx, x) and torch.equal(fy, y) and fold.train_warmup == warmup
        keep = torch.ones_like(mask)
        keep[0, idx] = False
        assert torch.equal(fold.train_mask, keep)
        held.append(vmask)
    assert torch.equal(torch.stack(held).sum(0), mask.long())
    with pytest.raises(ValueError, match=r"holds \d+ scored samples, at least 600"):
        BlockFold(dm, 300, 0)


def test_block_folds_of_several_recordings() -> None:
    """The ferrite loops, one row each: every row loses its own block."""
    dm = HysteresisDataModule(path=str(ROOT / "examples/data/mnzn_ferrite_bh_loops.csv"),
                              input_column="B_T", target_column="H_Apm", run_column="loop",
                              split_by="recording")
    _, _, _, mask = dm.batches("train")[0]
    fold = BlockFold(dm, 3, 2)
    (_, _, _, vmask), = list(fold.val_dataloader())
    assert mask.shape[0] == 4 and (vmask.sum(1) == 43).all()
    assert fold.train_tensors()[0].shape == (4, 129)
    assert torch.equal(fold.train_mask, mask & ~vmask)


def test_block_split_on_tensors() -> None:
    """The cut on plain tensors: a mask of any dtype, a gap inside a block left out of the
    validation samples, rows of other lengths (padding unscored), bad shapes named."""
    mask = torch.ones(2, 12, dtype=torch.uint8)
    mask[:, :2] = 0  # warm-up
    mask[1, 10:] = 0  # a shorter second row
    mask[0, 5] = 0  # a gap
    held = block_split(mask, 3, 1)
    assert held.dtype == torch.bool
    # row 0 scores 2-4, 6-11 (9 samples): blocks 2-4 | 6-8 | 9-11; row 1 scores 2-9
    assert held[0].nonzero().flatten().tolist() == [6, 7, 8]
    assert held[1].nonzero().flatten().tolist() == [5, 6, 7]
    held = block_split(mask, 3, 0)
    assert held[0].nonzero().flatten().tolist() == [2, 3, 4]  # the gap at 5 is not held
    with pytest.raises(ValueError, match=r"mask must have shape \(rows, time\)"):
        block_split(mask[0], 3, 0)
    with pytest.raises(ValueError, match=r"fold must be in \[0, 3\)"):
        block_split(mask, 3, 3)
    with pytest.raises(ValueError, match=r"row 0 of the data holds 9 scored samples, at "
                                         r"least 10"):
        block_split(mask, 5, 0)


FERRITE = {"path": str(ROOT / "examples/data/mnzn_ferrite_bh_loops.csv"), "input_column": "B_T",
           "target_column": "H_Apm", "run_column": "loop", "split_by": "recording"}


@pytest.mark.parametrize("repeat", [1, 2])
def test_recording_folds_hold_each_recording_out_whole(repeat: int) -> None:
    """Leave one recording out: fold j validates on training row j (its own scored
    samples, as the datamodule scores it) and trains and fits on the other rows only."""
    dm = HysteresisDataModule(**FERRITE, train_recordings=[0, 1, 3], val_recordings=[],
                              test_recordings=[2], repeat=repeat)
    x, y, first, mask = dm.batches("train")[0]
    assert x.shape[0] == 3
    held = []
    for j in range(3):
        fold = RecordingFold(dm, j)
        keep = [r for r in range(3) if r != j]
        (tx, ty, tw, tmask), = list(fold.train_dataloader())
        (vx, vy, vw, vmask), = list(fold.val_dataloader())
        assert fold.k == 3 and fold.n_val == int(mask[j].sum())
        assert torch.equal(vx[0], x[j]) and torch.equal(vy[0], y[j]) and torch.equal(vmask[0],
                                                                                    mask[j])
        assert torch.equal(tx, x[keep]) and torch.equal(ty, y[keep]) and torch.equal(tw,
                                                                                   first[keep])
        assert torch.equal(tmask, mask[keep])
        # the fits see the other recordings only: (2, time), the loops have equal lengths
        fx, fy = fold.train_tensors()
        assert torch.equal(fx, x[keep]) and torch.equal(fy, y[keep]) and fold.train_mask is None
        assert fold.train_warmup == int(first[0]) == (repeat - 1) * 129
        held.append(vmask[0])
    assert torch.equal(torch.stack(held), mask)


def test_recording_folds_of_recordings_of_different_lengths(tmp_path: Path) -> None:
    """Recordings of different lengths: the fits see the other recordings, one row each
    from its own initial state, up to its last sample (the padding outside the mask)."""
    path = tmp_path / "runs.csv"
    t = np.arange(300) * 0.05
    rows = [(r, np.sin(k), np.sin(k) ** 3) for r, n in ((0, 100), (1, 160), (2, 120))
            for k in t[:n]]
    np.savetxt(path, rows, delimiter=",", header="run,u,y", comments="")
    dm = HysteresisDataModule(path=str(path), input_column="u", target_column="y",
                              time_column=None, run_column="run", split_by="recording",
                              train_recordings=[0, 1, 2], val_recordings=[],
                              test_recordings=[], warmup=10)
    fold = RecordingFold(dm, 0)
    fx, fy = fold.train_tensors()
    assert fx.shape == (2, 160) and fold.train_warmup == 10
    assert torch.allclose(fy[0], torch.sin(torch.tensor(t[:160])) ** 3)
    assert torch.allclose(fy[1, :120], torch.sin(torch.tensor(t[:120])) ** 3)
    expect = torch.ones(2, 160, dtype=torch.bool)
    expect[1, 120:] = False  # the shorter recording's padding
    assert torch.equal(fold.train_mask, expect)
    assert fold.n_val == 100 - 10


def test_leave_one_recording_out_of_one_recording(monkeypatch, tmp_path) -> None:
    cfg = config(tmp_path, model={"select_cv": "recording"})
    with pytest.raises(ValueError, match=r"select_cv='recording' holds each training recording "
                                         r"out once, but the training split of paper holds 1"):
        cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path}")
    assert not list(tmp_path.rglob("metrics.csv")) and not list(tmp_path.rglob("selection.csv"))


def test_recording_folds_need_two_training_recordings() -> None:
    dm = HysteresisDataModule(**FERRITE, train_recordings=[3], val_recordings=[],
                              test_recordings=[0])
    with pytest.raises(ValueError, match=r"select_cv='recording' .* holds 1: give several"):
        RecordingFold(dm, 0)
    dm = HysteresisDataModule(**FERRITE, train_recordings=[0, 3], val_recordings=[],
                              test_recordings=[1])
    with pytest.raises(ValueError, match=r"fold must be in \[0, 2\), got 2"):
        RecordingFold(dm, 2)


def test_leave_one_recording_out_on_the_command_line(monkeypatch, capsys, tmp_path,
                                                     stages) -> None:
    """``select_cv: recording``: each candidate trained once per training recording, the
    table holds each fold and the MSE pooled over all held-out samples, which is that of an
    independent least-squares line (numpy) for the straight-line candidate."""
    root = tmp_path / "run"
    cfg = small_config(
        tmp_path, "loo.yaml", trainer=SELECT["trainer"],
        model={**SELECT["model"], "hidden": 1, "activation": "identity", "optimizer": "lbfgs",
               "optimizer_kwargs": {"max_iter": 50, "tolerance_grad": 1.0e-12,
                                    "tolerance_change": 1.0e-15},
               "select": CANDIDATES[:2], "select_cv": "recording"},
        data={"simulation": DROP, "t_end": DROP, "split": DROP, **FERRITE,
              "time_column": None, "train_recordings": [0, 1, 3], "val_recordings": [],
              "test_recordings": [2], "repeat": 2, "warmup": 0})
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={root}")
    assert "leave-one-recording-out cross-validation" in capsys.readouterr().out
    rows = table(root)
    assert len(rows) == 2 and all(r["fold_3"] != "" for r in rows) and "fold_4" not in rows[0]
    dm = HysteresisDataModule(**FERRITE, train_recordings=[0, 1, 3], val_recordings=[],
                              test_recordings=[2], repeat=2)
    x, y, _, mask = (v.numpy() for v in dm.batches("train")[0])
    folds, counts = [], []
    for j in range(3):
        keep = [r for r in range(3) if r != j]
        k, c = np.polyfit(x[keep][mask[keep]], y[keep][mask[keep]], 1)
        folds.append(np.mean((k * x[j][mask[j]] + c - y[j][mask[j]]) ** 2))
        counts.append(mask[j].sum())
    line = rows[0]
    assert [float(line[f"fold_{j + 1}"]) for j in range(3)] == pytest.approx(folds, rel=1e-6)
    assert float(line["val_mse"]) == pytest.approx(np.dot(folds, counts) / sum(counts),
                                                   rel=1e-6)
    assert len(list((root / "logs/version_0/selection").rglob("metrics.csv"))) == 6
    assert "test" not in stages


# --- errors ---------------------------------------------------------------------------
@pytest.mark.parametrize(("change", "error", "match"), [
    ({"model": {"select": []}},
     ValueError, r"model.select is empty"),
    ({"model": {"select": candidates(0, {"hiden": 3})}},
     ValueError, r"model.select\[0\]: 'hiden' is not a model argument; valid: \['operator', "
                 r"'hidden'"),
    ({"model": {"select": candidates(0, {"hidden": "many"})}},
     ValueError, r"model.select\[0\] .*model.hidden"),
    ({"data": {"split": [0.8, 0.0, 0.2]}},
     ValueError, r"validation split is empty \(data: paper\): .*model.select_cv"),
    ({"data": {"split": "paper"}},
     ValueError, r"validation split is the training data \(split='paper'\)"),
    ({"model": {"select": candidates(2, {"operator": [{"name": "playz", "n": 4}]})}},
     ValueError, r"model.select\[2\] .*operator\[0\]: no operator is registered as 'playz'"),
    ({"model": {"select": candidates(2, {"operator": [{"fit": "playz", "n": 4}]})}},
     ValueError, r"model.select\[2\] .*operator\[0\]: no model family is called 'playz'"),
    ({"model": {"select": candidates(2, {"operator": [{"fit": "plays", "m": 4}]})}},
     ValueError, r"model.select\[2\] .*fit 'plays': unknown option\(s\) \['m'\]"),
    ({"model": {"select_cv": 1}},
     ValueError, r"model.select_cv must be an int >= 2, got 1"),

    ({"model": {"select": DROP, "select_cv": 3}},
     ValueError, r"model.select_cv=3 needs model.select"),
])
def test_errors(monkeypatch, tmp_path, stages, change, error, match) -> None:
    cfg = config(tmp_path, **change)
    with pytest.raises(error, match=match):
        cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path}")
    assert "train" not in stages  # raised before any training
    assert not list(tmp_path.rglob("selection.csv"))


def test_check_candidates() -> None:
    valid = model_arguments(InverseHysteresisModule)
    assert "net" not in valid and {"operator", "hidden", "optimizer_kwargs"} <= set(valid)
    assert check_candidates([{}, {"hidden": 2}], valid) == [{}, {"hidden": 2}]
    with pytest.raises(TypeError, match=r"model.select\[1\] must be a dict"):
        check_candidates([{}, 3], valid)
    with pytest.raises(TypeError, match="model.select must be a list"):
        check_candidates({"hidden": 2}, valid)
    with pytest.raises(ValueError, match=r"'a', 'b' are not model arguments"):
        check_candidates([{"b": 1, "a": 2}], valid)


def test_example_config_runs(monkeypatch, capsys, tmp_path) -> None:
    monkeypatch.chdir(ROOT)  # the config names the example file relative to the repository
    root = tmp_path / "example"
    cli(monkeypatch, "fit", "--config", "configs/select_example.yaml",
        f"--trainer.default_root_dir={root}", "--trainer.max_epochs=2",
        "--trainer.enable_progress_bar=false")
    rows = table(root)
    assert len(rows) == 3 and all(math.isfinite(float(r["val_mse"])) for r in rows)
    assert "selected candidate" in capsys.readouterr().out
    assert (root / "logs/version_0/checkpoints/last.ckpt").is_file()


def test_standard_error_is_batch_means() -> None:
    """Against a numpy batch-means reference; correlated errors get a larger standard error
    than independent ones of the same spread."""
    g = np.random.default_rng(0)
    e = g.exponential(size=50)
    k = 7  # floor(sqrt(50))
    means = np.array([b.mean() for b in np.array_split(e, k)])
    expected = means.std(ddof=1) / np.sqrt(k)
    assert standard_error(torch.from_numpy(e)) == pytest.approx(expected, rel=1e-12)
    assert math.isnan(standard_error(torch.ones(3)))
    independent = torch.from_numpy(g.permutation(np.repeat(e[:10], 5)))
    correlated = torch.from_numpy(np.repeat(e[:10], 5))  # runs of equal errors
    assert standard_error(correlated) > 1.5 * standard_error(independent)


def _score(i: int, mse: float, se: float) -> CandidateScore:
    return CandidateScore(i, {"i": i}, mse, val_se=se)


def test_one_standard_error_rule_keeps_the_baseline_unless_beaten_clearly() -> None:
    close = [_score(0, 1.0, 0.1), _score(1, 0.95, 0.1), _score(2, 0.92, 0.1)]
    assert best(close, "min").index == 2
    assert best(close, "1se").index == 0  # 1.0 <= 0.92 + 0.1
    clear = [_score(0, 1.0, 0.1), _score(1, 0.5, 0.1), _score(2, 0.3, 0.1)]
    assert best(clear, "1se").index == 2  # the lowest, not the first within its bound
    skipped = [_score(0, math.nan, math.nan), _score(1, 0.5, 0.1), _score(2, 0.55, 0.1)]
    assert best(skipped, "1se").index == 1
    with pytest.raises(ValueError, match="model.select_rule must be one of"):
        best(close, "2se")


def test_select_rule_on_the_command_line(monkeypatch, capsys, tmp_path) -> None:
    cfg = config(tmp_path)
    root = tmp_path / "run"
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={root}",
        "--model.select_rule=1se")
    rows = table(root)
    assert all(float(r["val_se"]) > 0 for r in rows)
    mse = [float(r["val_mse"]) for r in rows]
    se = [float(r["val_se"]) for r in rows]
    lowest = min(range(3), key=mse.__getitem__)
    expected = 0 if mse[0] <= mse[lowest] + se[lowest] else lowest
    assert [int(r["selected"]) for r in rows] == [int(i == expected) for i in range(3)]
    assert "one-standard-error rule" in capsys.readouterr().out
    bad = config(tmp_path, model={"select": DROP, "select_rule": "1se"})
    with pytest.raises(ValueError, match=r"model.select_rule='1se' needs model.select"):
        cli(monkeypatch, "fit", "--config", str(bad), f"--trainer.default_root_dir={tmp_path}")


@pytest.mark.parametrize("fold", [0, 2])
def test_a_block_folds_fits_ignore_its_held_out_targets(tmp_path: Path, fold: int) -> None:
    """Through the datamodule and the module's set-up: a fold of blocked cross-validation
    fits the family operators and the normalization on the whole training rows, so targets
    spoiled inside its held-out block change none of them, while the block's inputs still
    run the states (spoiling the inputs there does change the fit)."""
    rows = list(csv.DictReader((ROOT / "examples/data/bouc_wen.csv").open()))[:600]
    kw = {"input_column": "response", "target_column": "command", "time_column": "time",
          "split": [0.8, 0.2, 0.0], "warmup": 50}

    def fitted(table: list[dict]) -> tuple[dict, torch.Tensor]:
        path = tmp_path / f"rec{len(list(tmp_path.iterdir()))}.csv"
        with path.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(table[0]))
            writer.writeheader()
            writer.writerows(table)
        block = BlockFold(HysteresisDataModule(path=str(path), **kw), 4, fold)
        torch.manual_seed(0)
        module = InverseHysteresisModule(
            operator=[{"fit": "stop_pi", "n_widths": 8}, {"fit": "drift"}], hidden=1,
            activation="identity")
        x, y = block.train_tensors()
        module.fit_normalization(x, y, warmup=block.train_warmup, mask=block.train_mask)
        (_, _, _, vmask), = list(block.val_dataloader())
        return {k: v.clone() for k, v in module.net.state_dict().items()}, vmask[0]

    clean, held = fitted(rows)
    assert 0 < int(held.sum()) < len(rows)
    inside = [i < held.numel() and bool(held[i]) for i in range(len(rows))]
    spoiled = [dict(r, command=str(float(r["command"]) + 5.0)) if inside[i] else r
               for i, r in enumerate(rows)]
    other, _ = fitted(spoiled)
    for key, value in clean.items():
        assert torch.equal(other[key], value), key
    moved = [dict(r, response=str(-float(r["response"]))) if inside[i] else r
             for i, r in enumerate(rows)]
    states, _ = fitted(moved)
    assert any(not torch.equal(states[k], v) for k, v in clean.items())


def test_a_diverged_training_scores_nan_with_its_reason() -> None:
    """A Lightning run whose training diverged (validation logs a NaN MSE) scores NaN with
    its reason in the loop the library's selection scores by (score_folds), its later folds
    not run."""
    from torchhys.selection.run import score_folds
    from torchhys.training import selection

    class Trainer:  # a run whose training diverged: validation logs a NaN MSE
        def fit(self, module, datamodule) -> None:  # noqa: ANN001
            pass

        def validate(self, module, datamodule, verbose) -> list[dict]:  # noqa: ANN001
            return [{"val_mse": math.nan}]

    mse, errors = selection._train_and_validate(None, None, Trainer())
    assert math.isnan(mse) and errors.numel() == 0
    with pytest.warns(RuntimeWarning, match="candidate 3: validation MSE nan: the training "
                                            "diverged"):
        score = score_folds(3, {}, 1, lambda j: (mse, errors, 5), None)
    assert math.isnan(score.val_mse) and score.folds == ()
    assert score.error == "validation MSE nan: the training diverged"
    runs = []
    with pytest.warns(RuntimeWarning, match="candidate 3, fold 2 of 3: validation MSE nan"):
        score = score_folds(3, {}, 3, lambda j: runs.append(j) or (
            (0.5, torch.ones(4, dtype=torch.float64), 4) if j == 0 else (mse, errors, 4)), 3)
    assert runs == [0, 1] and math.isnan(score.val_mse)
    assert score.folds[0] == 0.5 and all(math.isnan(f) for f in score.folds[1:])
    assert score.error == ("fold 2 of 3: validation MSE nan: the training diverged (folds 3-3 "
                           "not run)")


def test_quiet_prints_no_progress(monkeypatch, capsys, tmp_path) -> None:
    cfg = config(tmp_path)
    monkeypatch.delenv("TORCHHYS_QUIET", raising=False)
    cli(monkeypatch, "fit", "--quiet", "--config", str(cfg),
        f"--trainer.default_root_dir={tmp_path / 'run'}")
    assert "TORCHHYS_QUIET" not in os.environ  # restored when the command returns
    out, err = capsys.readouterr()
    assert not [line for line in out.splitlines() if line.startswith("candidate ")]
    assert "torch threads" not in err
    assert "selected candidate" in out  # the result is still printed


# --- a hold-out of solved candidates ------------------------------------------------------
SOLVED = {"trainer": {"max_epochs": 3},
          "model": {**LINE, "init": "default", "select_cv": DROP,
                    "select": [{"operator": None},
                               {"operator": [{"fit": "stop_pi", "n_widths": 8, "power": 2.0,
                                              "segments": 2}]}]},
          "data": {"simulation": "paper", "t_end": 6.3, "split": [0.6, 0.2, 0.2],
                   "warmup": 10}}
"""A hold-out (``select_cv`` left out) of two candidates whose affine readouts are solved:
the line and a stop-type PI model."""


def test_a_holdout_of_solved_candidates_is_the_least_squares_reference(monkeypatch,
                                                                       tmp_path) -> None:
    """``select_cv: null`` with affine readouts goes through :func:`torchhys.selection.select`
    (no Lightning run per candidate) on the datamodule's own split: the line's val_mse is
    numpy's least-squares line on the training samples ``[warmup, round(0.6 n))``, scored on
    ``[round(0.6 n), round(0.8 n))``; and the final fit saves the chosen readout as the
    least-squares solution on the training split (not trained again: the normal equations
    hold to rounding)."""
    import torchhys.training.selection as lightning_selection
    from torchhys.data.simulations import simulate

    def refused(*args, **kwargs):
        raise AssertionError("a Lightning run per candidate")

    monkeypatch.setattr(lightning_selection, "run_selection", refused)
    root = tmp_path / "run"
    cfg = small_config(tmp_path, "solved.yaml", **SOLVED)
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={root}")
    rows = table(root)
    _, x, y = simulate("paper", dt=0.01, t_end=6.3)
    xn, yn, n = x.numpy(), y.numpy(), x.numel()
    a, b = round(0.6 * n), round(0.8 * n)
    design = np.stack([xn[10:a], np.ones(a - 10)], 1)
    c = np.linalg.lstsq(design, yn[10:a], rcond=None)[0]
    errors = (c[0] * xn[a:b] + c[1] - yn[a:b]) ** 2
    assert float(rows[0]["val_mse"]) == pytest.approx(errors.mean(), rel=1e-10)
    assert float(rows[0]["val_se"]) == pytest.approx(
        standard_error(torch.from_numpy(errors)), rel=1e-10)
    assert all(not r["error"] for r in rows) and "fold_1" not in rows[0]
    logs = sorted((root / "logs/version_0/selection").rglob("metrics.csv"))
    assert [p.relative_to(root / "logs/version_0/selection").parts[0] for p in logs] == [
        "candidate_0", "candidate_1"]

    chosen = int(next(r["candidate"] for r in rows if r["selected"] == "1"))
    module = InverseHysteresisModule.load_from_checkpoint(
        root / "logs/version_0/checkpoints/last.ckpt", weights_only=True)
    assert module.hparams["operator"] == SOLVED["model"]["select"][chosen]["operator"]
    net = module.net.double()
    with torch.no_grad():
        z = ((net.features(x[None, :a])[0] - net.in_mean) / net.in_std)[0, 10:].numpy()
        got = net(x[None, :a])[0][0, 10:].numpy()
    design = np.concatenate([z, np.ones((z.shape[0], 1))], 1)
    t = ((y[10:a] - net.out_mean) / net.out_std).numpy()
    want = (design @ np.linalg.lstsq(design, t, rcond=None)[0]) * float(net.out_std) + float(
        net.out_mean)
    assert np.abs(got - want).max() < 1e-12 * np.abs(want).max()


# --- trained candidates -------------------------------------------------------------------
TRAINED = {"trainer": {"max_epochs": 6},
           "model": {"operator": None, "operator_kwargs": DROP, "hidden": 4,
                     "activation": "tanh", "init": "default", "optimizer": "adam",
                     "lr": 0.02, "optimizer_kwargs": DROP, "select_cv": DROP,
                     "select": [{}, {"operator": [{"fit": "plays", "n": 3}]}]},
           "data": {"simulation": "paper", "t_end": 6.3, "split": [0.6, 0.2, 0.2],
                    "warmup": 10}}
"""A hold-out of two candidates of 4 tanh units trained by Adam: no readout solved."""


def _lightning_holdout_errors(model: dict, data: dict, epochs: int) -> torch.Tensor:
    """A candidate trained by hand as a Lightning run of it trains (seeded, one full batch
    an epoch, float64), and its squared errors on the validation split in float64."""
    from lightning.pytorch import seed_everything

    seed_everything(0, verbose=False)
    module = InverseHysteresisModule(**model)
    dm = HysteresisDataModule(**data)
    trainer(max_epochs=epochs).fit(module, datamodule=dm)
    x, y, _, mask = dm.batches("val")[0]
    with torch.no_grad():
        return (module(x.double()) - y.double()).square()[mask]


def test_trained_candidates_go_through_select_as_their_lightning_runs(monkeypatch,
                                                                      tmp_path) -> None:
    """Where the trainer section asks only for steps on the CPU, trained candidates are
    scored by :func:`torchhys.selection.select` (no Lightning run per candidate), and each
    scores what a Lightning run of it gives from the same seed (float64 errors, to
    rounding)."""
    import torchhys.training.selection as lightning_selection

    def refused(*args, **kwargs):
        raise AssertionError("a Lightning run per candidate")

    monkeypatch.setattr(lightning_selection, "run_selection", refused)
    root = tmp_path / "run"
    cli(monkeypatch, "fit", "--config", str(small_config(tmp_path, "t.yaml", **TRAINED)),
        f"--trainer.default_root_dir={root}")
    rows = table(root)
    base = {k: v for k, v in TRAINED["model"].items()
            if v is not DROP and not k.startswith("select")}
    for row, overrides in zip(rows, TRAINED["model"]["select"], strict=True):
        errors = _lightning_holdout_errors({**base, **overrides}, TRAINED["data"], 6)
        assert float(row["val_mse"]) == pytest.approx(float(errors.mean()), rel=1e-12)
        assert float(row["val_se"]) == pytest.approx(standard_error(errors), rel=1e-12)


@pytest.mark.parametrize(("option", "value", "cv", "precision"), [
    ("gradient_clip_val", 1.0, None, "32-true"), ("max_steps", 3, 2, "64-true")])
def test_a_trainer_option_select_cannot_honour_keeps_the_lightning_runs(
        monkeypatch, tmp_path, option, value, cv, precision) -> None:
    """A trainer option that changes a candidate's training and that select does not do
    (clipping, accumulation, a step limit...) trains the candidates by Lightning, as
    before (scored by the library's loop: folds pooled by their held-out samples; a
    float32 hold-out scored in the module's dtype); trainer_reason names it."""
    import torchhys.training.selection as lightning_selection
    from torchhys.cli.selection import trainer_reason

    calls = []
    run = lightning_selection.run_selection
    monkeypatch.setattr(lightning_selection, "run_selection",
                        lambda *a, **k: calls.append(1) or run(*a, **k))
    sections = {**TRAINED, "trainer": {**TRAINED["trainer"], option: value,
                                       "precision": precision},
                "model": {**TRAINED["model"], "select_cv": cv if cv else DROP}}
    cli(monkeypatch, "fit", "--config", str(small_config(tmp_path, "t.yaml", **sections)),
        f"--trainer.default_root_dir={tmp_path / 'run'}")
    rows = table(tmp_path / "run")
    assert calls == [1] and len(rows) == 2
    if cv:
        dm = HysteresisDataModule(**TRAINED["data"])
        counts = [BlockFold(dm, cv, j).n_val for j in range(cv)]
        for r in rows:
            folds = [float(r[f"fold_{j + 1}"]) for j in range(cv)]
            pooled = sum(f * n for f, n in zip(folds, counts, strict=True)) / sum(counts)
            assert float(r["val_mse"]) == pytest.approx(pooled, rel=1e-12)
    trainer_section = {"accelerator": "cpu", "devices": 1, "precision": "64-true",
                       "max_epochs": 3, option: value}
    assert trainer_reason(trainer_section).startswith(f"trainer.{option}={value!r}")


def test_trainer_reason_names_what_select_does_not_do() -> None:
    from torchhys.cli.selection import trainer_reason

    cpu = {"accelerator": "cpu", "devices": 1, "precision": "64-true", "max_epochs": 3,
           "max_time": "00:00:01:00", "enable_progress_bar": False, "logger": False,
           "check_val_every_n_epoch": 7, "plugins": [
               {"class_path": "torchhys.training.checkpoint_io.AtomicCheckpointIO"}]}
    assert trainer_reason(cpu) is None
    assert "precision='bf16-mixed'" in trainer_reason({**cpu, "precision": "bf16-mixed"})
    assert "accelerator='gpu'" in trainer_reason({**cpu, "accelerator": "gpu"})
    assert "devices=2" in trainer_reason({**cpu, "devices": 2})
    assert "callbacks" in trainer_reason({**cpu, "callbacks": [{"class_path": "x"}]})
    assert "max_epochs=0" in trainer_reason({**cpu, "max_epochs": 0})
    assert "max_time=3" in trainer_reason({**cpu, "max_time": 3})
    assert trainer_reason({**cpu, "accumulate_grad_batches": 2}).startswith(
        "trainer.accumulate_grad_batches=2")


@pytest.mark.parametrize("max_epochs", [None, -1, 0, 3])
def test_the_command_and_a_lightning_run_solve_the_same_readouts(max_epochs) -> None:
    """``torchhys fit`` (its check of the trainer section) and the Lightning path
    (``solvable``, on the Trainer) solve a readout for the same ``max_epochs``: every value
    but 0 (None: Lightning's 1000 epochs, -1: unlimited) steps it, and the least-squares
    solution is what it converges to."""
    from torchhys.selection.candidates import steps_readout
    from torchhys.training.readout import solvable

    module = InverseHysteresisModule(operator=None, hidden=1, activation="identity",
                                     optimizer="lbfgs")
    fold = BlockFold(HysteresisDataModule(**DATA), 2, 0)
    run = trainer(max_epochs=max_epochs, max_time="00:00:00:05" if max_epochs == -1 else None)
    assert steps_readout(max_epochs) is solvable(module, fold, run) is (max_epochs != 0)
    assert not steps_readout(3, 0) and not solvable(module, fold, trainer(limit_train_batches=0))


def test_brief_names_a_candidate_in_a_few_words() -> None:
    assert brief({"operator": None}) == "straight line"
    assert brief({"operator": [{"fit": "stop_pi", "n_widths": 40, "power": 2.0,
                                "segments": 4}, {"fit": "preisach", "n": 40,
                                                 "direction": "inverse"}]}) == \
        "stop_pi 40/4 + preisach 40 inverse"
    assert brief({"operator": [{"fit": "gpi", "n_widths": 10, "units": 4, "epochs": 200,
                                "direction": "inverse"}]}) == "gpi 10/4 inverse epochs=200"
    assert brief({"operator": "eiho", "hidden": 16, "lr": 0.1, "activation": "tanh"}) == \
        "eiho, hidden=16, lr=0.1, ..."
    assert brief({}) == "the base model"


def test_the_time_left_is_smoothed_over_the_candidates(monkeypatch, capsys) -> None:
    """Candidates of 1 s and 9 s in turn: the estimate blends the mean-based one with the
    last estimate less the time since (half each)."""
    import torchhys.selection.progress as progress

    clock = [0.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: clock[0])
    p = progress.SelectionProgress([{}] * 5, None)
    p.starts(0, None)
    clock[0] = 1.0
    p.starts(1, None)  # one training of 1 s done: 4 left at 1 s
    assert p.eta == (4.0, 1.0)
    clock[0] = 10.0
    p.starts(2, None)  # mean 5 s, 3 left: 15; the last less 9 s: 0 -> 7.5
    assert p.eta == (7.5, 10.0)
    clock[0] = 11.0
    p.starts(3, None)  # mean 11/3, 2 left: 7.33; the last less 1 s: 6.5
    assert p.eta[0] == pytest.approx(0.5 * (22.0 / 3.0 + 6.5))
    assert "about 7 s left: the base model" in capsys.readouterr().out
