"""HysteresisDataModule with several recordings: run column, lists of files, splits by
recording, fresh states per recording, ``repeat``, padding outside the loss, errors."""

from __future__ import annotations

import csv
import math
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from _training_helpers import DROP, small_config, trainer

from torchhys.cli.main import main
from torchhys.data.files import read_recordings
from torchhys.data.tables import DataFileError
from torchhys.training import HysteresisDataModule, InverseHysteresisModule

torch.set_num_threads(1)
# training_step called directly, outside a Trainer, logs nothing
pytestmark = pytest.mark.filterwarnings("ignore:You are trying to `self.log\\(\\)`")

FERRITE = Path(__file__).resolve().parents[1] / "examples/data/mnzn_ferrite_bh_loops.csv"
LENGTHS = {10: 40, 11: 30, 12: 50, 13: 24}
"""Synthetic recordings: run id -> samples (different lengths)."""
OPERATORS = ["eiho", {"fit": "plays", "widths": [0.2, 0.6]}]
"""Operators with a state (turning points, play outputs) and no data-dependent fit."""


def run_rows(rid: int, n: int) -> list[list]:
    """Rows ``run, time, command, response`` of one recording: time restarts at 0, a
    decaying oscillation of its own amplitude (turning points that differ per run)."""
    t = np.arange(n) * 0.01
    u = (1.0 + 0.2 * (rid % 7)) * np.exp(-t) * np.sin(9.0 * t + 0.5 * rid)
    return [[rid, f"{a:.2f}", f"{b:.6f}", f"{0.8 * b + 0.1 * math.tanh(b):.6f}"]
            for a, b in zip(t, u, strict=True)]


def write_runs(path: Path, lengths: dict[int, int],
               header: str = "run,time,command,response") -> Path:
    rows = [r for rid, n in lengths.items() for r in run_rows(rid, n)]
    path.write_text("\n".join([header] + [",".join(str(v) for v in r) for r in rows]) + "\n")
    return path


def data(path: Path | list, **kwargs) -> HysteresisDataModule:
    opts = dict(run_column="run", time_column="time", min_samples=8)
    opts.update(kwargs)
    dm = HysteresisDataModule(path=path if isinstance(path, list) else str(path), **opts)
    dm.setup()
    return dm


def ids(dm: HysteresisDataModule, stage: str) -> list:
    return [dm.recordings[w.index].id for w in dm.windows[stage]]


def alone(module: InverseHysteresisModule, dm: HysteresisDataModule, rid: int) -> torch.Tensor:
    """The model's output on one recording, run by itself from a fresh state, (time,)."""
    (rec,) = [r for r in dm.recordings if r.id == rid]
    with torch.no_grad():
        return module(torch.from_numpy(rec.x).unsqueeze(0), target=torch.from_numpy(
            rec.y).unsqueeze(0))[0]


def model(dm: HysteresisDataModule, **kwargs) -> InverseHysteresisModule:
    torch.manual_seed(0)
    opts = dict(operator=OPERATORS, hidden=6, optimizer="adam")
    opts.update(kwargs)
    module = InverseHysteresisModule(**opts).double()
    x, y = dm.train_tensors()
    module.fit_normalization(x, y, warmup=dm.train_warmup)
    return module


# --- which recordings go where -------------------------------------------------------------
def test_run_column_splits_a_file_into_recordings(tmp_path: Path) -> None:
    dm = data(write_runs(tmp_path / "runs.csv", LENGTHS), split_by="recording")
    assert [r.id for r in dm.recordings] == list(LENGTHS)
    assert [len(r.x) for r in dm.recordings] == list(LENGTHS.values())
    assert all(r.t[0] == 0.0 for r in dm.recordings)  # time restarts per recording
    for stage in ("train", "val", "test"):  # split="paper": all of them everywhere
        assert ids(dm, stage) == list(LENGTHS)


@pytest.mark.parametrize(
    "kwargs, expected",
    [(dict(split=[0.5, 0.25, 0.25]), ([10, 11], [12], [13])),
     (dict(split=[0.5, 0.25, 0.0]), ([10, 11], [12], [])),
     (dict(train_recordings=[13, 10], test_recordings=[11]), ([13, 10], [13, 10], [11])),
     (dict(train_recordings=[13, 10], val_recordings=[], test_recordings=[11, 12]),
      ([13, 10], [], [11, 12])),
     (dict(test_recordings=[11, 13]), ([10, 12], [10, 12], [11, 13])),
     (dict(split=[0.5, 0.25, 0.25], test_recordings=["11"]), ([10, 12], [13], [11])),
     (dict(split=[0.75, 0.25, 0.0], val_recordings=[10]), ([11, 12, 13], [10], []))],
)
def test_split_by_recording(tmp_path: Path, kwargs: dict, expected: tuple) -> None:
    dm = data(write_runs(tmp_path / "runs.csv", LENGTHS), split_by="recording", **kwargs)
    assert (ids(dm, "train"), ids(dm, "val"), ids(dm, "test")) == expected
    for stage, want in zip(("train", "val", "test"), expected, strict=True):
        batches = dm.batches(stage)
        assert len(batches) == (1 if want else 0)  # one full batch, or no loader
        if want:
            x, y, warmup, mask = batches[0]
            longest = max(LENGTHS[i] for i in want)
            assert x.shape == y.shape == mask.shape == (len(want), longest)
            assert mask.sum(1).tolist() == [LENGTHS[i] for i in want]
            assert warmup.tolist() == [0] * len(want)
    if expected[1]:
        assert len(dm.val_dataloader()) == 1
    else:
        assert dm.val_dataloader() == []


def test_list_of_files_are_recordings_by_index(tmp_path: Path) -> None:
    a = write_runs(tmp_path / "a.csv", {0: 40})
    b = write_runs(tmp_path / "b.csv", {0: 30})
    c = write_runs(tmp_path / "c.csv", {0: 20})
    dm = data([str(a), str(b), str(c)], run_column=None, split_by="recording",
              train_recordings=[2, 0], test_recordings=[1])
    assert [r.id for r in dm.recordings] == [0, 1, 2]
    assert ids(dm, "train") == [2, 0] and ids(dm, "test") == [1]
    torch.testing.assert_close(dm.x, torch.cat([torch.from_numpy(r.x) for r in dm.recordings]))


def test_list_of_files_with_a_run_column(tmp_path: Path) -> None:
    a = write_runs(tmp_path / "a.csv", {10: 40, 11: 30})
    b = write_runs(tmp_path / "b.csv", {12: 50, 13: 24})
    dm = data([str(a), str(b)], split_by="recording", split=[0.5, 0.0, 0.5])
    assert ids(dm, "train") == [10, 11] and ids(dm, "val") == [] and ids(dm, "test") == [12, 13]
    assert dm.recordings[2].label == f"{b}: recording 12"


def test_time_split_cuts_each_recording(tmp_path: Path) -> None:
    dm = data(write_runs(tmp_path / "runs.csv", {10: 40, 11: 80}), split=[0.5, 0.25, 0.25],
              warmup=3)
    assert [tuple(w) for w in dm.windows["train"]] == [(0, 0, 20), (1, 0, 40)]
    assert [tuple(w) for w in dm.windows["val"]] == [(0, 20, 30), (1, 40, 60)]
    x, y, warmup, mask = dm.batches("val")[0]
    assert x.shape == (2, 60) and warmup.tolist() == [20, 40]  # the preceding rows warm up
    assert mask.sum(1).tolist() == [10, 20]
    assert torch.equal(x[0, :30], torch.from_numpy(dm.recordings[0].x[:30]))
    xt, yt = dm.train_tensors()  # different lengths: one row each, the shorter padded
    assert xt.shape == (2, 40) and dm.train_warmup == 3
    assert dm.train_mask.sum(1).tolist() == [20, 40]
    assert torch.equal(xt[0, 20:], xt[0, 19].expand(20))  # padded with its last sample
    assert dm.bounds == {}  # only for a single recording


# --- fresh state per recording, repeat, padding -------------------------------------------
def test_each_recording_starts_from_a_fresh_state(tmp_path: Path) -> None:
    dm = data(write_runs(tmp_path / "runs.csv", LENGTHS), split_by="recording")
    module = model(dm)
    x, y, _, mask = dm.batches("train")[0]
    with torch.no_grad():
        batch = module(x, target=y)
    for row, rec in enumerate(dm.recordings):
        n = len(rec.x)
        torch.testing.assert_close(batch[row, :n], alone(module, dm, rec.id), rtol=0,
                                   atol=1e-12)
        assert not mask[row, n:].any()
    # the test can tell: after another recording the states differ
    x01 = torch.from_numpy(np.concatenate([dm.recordings[0].x, dm.recordings[1].x]))
    with torch.no_grad():
        carried = module(x01.unsqueeze(0))[0, len(dm.recordings[0].x):]
    assert (carried - batch[1, :30]).abs().max() > 1e-3


@pytest.mark.parametrize("warmup, first", [(0, 80), (5, 80), (85, 85)])
def test_repeat_scores_only_the_last_period(tmp_path: Path, warmup: int, first: int) -> None:
    dm = data(write_runs(tmp_path / "runs.csv", {10: 40, 11: 30}), split_by="recording",
              repeat=3, warmup=warmup)
    x, y, first_t, mask = dm.batches("train")[0]
    rec = torch.from_numpy(dm.recordings[0].x)
    assert x.shape == (2, 120) and torch.equal(x[0], rec.repeat(3))
    assert torch.equal(y[1, :90], torch.from_numpy(dm.recordings[1].y).repeat(3))
    assert first_t.tolist() == [first, max(warmup, 60)]
    assert mask[0].nonzero().flatten().tolist() == list(range(first, 120))
    assert mask[1].nonzero().flatten().tolist() == list(range(max(warmup, 60), 90))
    module = model(dm)
    with torch.no_grad():
        pred = module(x, target=y)
    expected = torch.cat([pred[0, first:] - y[0, first:],
                          pred[1, max(warmup, 60):90] - y[1, max(warmup, 60):90]])
    loss = module.training_step(dm.batches("train")[0], 0)
    torch.testing.assert_close(loss, expected.pow(2).mean(), rtol=1e-12, atol=0)


def test_equal_lengths_fit_on_the_last_period(tmp_path: Path) -> None:
    dm = data(write_runs(tmp_path / "runs.csv", {10: 40, 11: 40}), split_by="recording",
              repeat=2)
    x, y = dm.train_tensors()
    assert x.shape == (2, 80) and dm.train_warmup == 40


def test_padding_never_enters_the_loss_or_the_metrics(tmp_path: Path) -> None:
    dm = data(write_runs(tmp_path / "runs.csv", LENGTHS), split_by="recording", warmup=4)
    module = model(dm)
    errors = []
    for rec in dm.recordings:
        pred = alone(module, dm, rec.id)
        errors.append(pred[4:] - torch.from_numpy(rec.y)[4:])
    by_hand = torch.cat(errors).pow(2).mean()  # every real scored sample counts once
    batch = dm.batches("train")[0]
    torch.testing.assert_close(module.training_step(batch, 0), by_hand, rtol=1e-12, atol=0)
    x, y, warmup, mask = batch
    real = torch.arange(x.shape[1]) < torch.tensor(list(LENGTHS.values())).unsqueeze(1)
    wild = (x.where(real, 1e6), y.where(real, -1e6), warmup, mask)
    torch.testing.assert_close(module.training_step(wild, 0), by_hand, rtol=1e-12, atol=0)
    result = trainer().test(module, dm, verbose=False)
    assert result[0]["test_mse"] == pytest.approx(float(by_hand), rel=1e-6)


@pytest.mark.parametrize("optimizer", ["cg", "lbfgs"])
def test_closure_optimizers_see_all_recordings_in_one_batch(tmp_path: Path,
                                                             optimizer: str) -> None:
    dm = data(write_runs(tmp_path / "runs.csv", LENGTHS), split_by="recording",
              train_recordings=[10, 11, 12])
    module = InverseHysteresisModule(operator=OPERATORS, hidden=6, optimizer=optimizer,
                                     optimizer_kwargs={"max_iter": 3} if optimizer == "lbfgs"
                                     else None)
    seen = []
    step = module.training_step

    def recording(batch, batch_idx):  # noqa: ANN001, ANN202
        seen.append(tuple(batch[0].shape))
        return step(batch, batch_idx)

    module.training_step = recording
    trainer(max_epochs=2).fit(module, dm)
    assert seen == [(3, 50), (3, 50)]  # one step per epoch, all training recordings


# --- the command line on the ferrite loops ------------------------------------------------
FERRITE_CONFIG = {
    "trainer": {"check_val_every_n_epoch": DROP},
    "model": {"operator": [{"fit": "pi_ls", "n_widths": 10, "power": 2.0}],
              "operator_kwargs": DROP},
    "data": {"simulation": DROP, "t_end": DROP, "split": DROP, "input_column": "B_T",
             "target_column": "H_Apm", "run_column": "loop"}}
"""The sections of :func:`small_config`: the PI operator and 8 sigmoids on the ferrite loops
(the files given by --data.path)."""


def test_cli_fits_and_tests_the_ferrite_loops_by_recording(monkeypatch, tmp_path: Path) -> None:
    # two files (loops 0-1 and 2-3) given as a list; the run column names the loops
    with FERRITE.open() as fh:
        lines = [ln for ln in fh if not ln.startswith("#")]
    parts = [tmp_path / "loops01.csv", tmp_path / "loops23.csv"]
    for part, loops in zip(parts, ("01", "23"), strict=True):
        part.write_text(lines[0] + "".join(ln for ln in lines[1:] if ln[0] in loops))
    cfg = small_config(tmp_path, "ferrite.yaml", **FERRITE_CONFIG)
    root = tmp_path / "run"
    args = ["--config", str(cfg), f"--data.path=[{parts[0]}, {parts[1]}]",
            "--data.split_by", "recording", "--data.train_recordings=[0, 3]",
            "--data.val_recordings=[]", "--data.test_recordings=[1, 2]", "--data.repeat", "3",
            f"--trainer.default_root_dir={root}"]
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    main(["fit", *args])
    ckpt = root / "logs/version_0/checkpoints/last.ckpt"
    main(["test", *args, f"--ckpt_path={ckpt}"])
    with (root / "logs/version_0/metrics.csv").open() as fh:
        fit_rows = list(csv.DictReader(fh))
    assert len([r for r in fit_rows if r.get("train_loss")]) == 3
    with (root / "logs/version_1/metrics.csv").open() as fh:
        (row,) = [r for r in csv.DictReader(fh) if r.get("test_mse")]
    assert math.isfinite(float(row["test_mse"]))
    hparams = torch.load(ckpt, weights_only=False)["datamodule_hyper_parameters"]
    assert hparams["path"] == [str(p) for p in parts] and hparams["repeat"] == 3


# --- errors -------------------------------------------------------------------------------
def test_missing_run_column_names_file_and_argument(tmp_path: Path) -> None:
    path = write_runs(tmp_path / "runs.csv", LENGTHS)
    where = re.escape(str(path))
    with pytest.raises(DataFileError, match=rf"{where}: column 'loop' \(run_column\) not found"):
        data(path, run_column="loop")


def test_recording_shorter_than_its_warmup(tmp_path: Path) -> None:
    path = write_runs(tmp_path / "runs.csv", LENGTHS)
    where = re.escape(str(path))
    with pytest.raises(DataFileError,
                       match=rf"{where}: recording 13 holds 24 samples, not more than warmup=25"):
        data(path, split_by="recording", warmup=25)
    with pytest.raises(DataFileError, match=r"recording 13 holds 24 samples \(repeat=2: 48\)"):
        data(path, split_by="recording", warmup=48, repeat=2)


@pytest.mark.parametrize(
    "kwargs, match",
    [(dict(split=[0.5, 0.25, 0.25]), r"split=\[0.5, 0.25, 0.25\] gives the test split none"),
     (dict(train_recordings=[]), "the train split holds no recording"),
     (dict(train_recordings=[10], test_recordings=[11], split=[0.5, 0.25, 0.25]),
      "gives the val split none of the 0 recordings left by the listed stages"),
     (dict(test_recordings=[10, 12]), r"test_recordings: unknown recording 12; the "
      r"recordings of .*runs\.csv are \[10, 11\]"),
     (dict(train_recordings=[10, 10]), "train_recordings: recording 10 is listed twice"),
     (dict(train_recordings=[10, 11], test_recordings=[11], split=[0.5, 0.0, 0.5]),
      r"recording\(s\) \[11\] are listed in train_recordings and in test_recordings"),
     (dict(train_recordings=[10], val_recordings=[10], split=[0.5, 0.0, 0.5]),
      r"\[10\] are listed in train_recordings and in val_recordings")],
)
def test_split_errors(tmp_path: Path, kwargs: dict, match: str) -> None:
    path = write_runs(tmp_path / "runs.csv", {10: 40, 11: 30})
    with pytest.raises(ValueError, match=match):
        data(path, split_by="recording", **kwargs)


@pytest.mark.parametrize("repeat", [0, -1, 1.5, True])
def test_repeat_must_be_a_positive_int(repeat) -> None:
    with pytest.raises(ValueError, match=rf"repeat must be an int >= 1, got {repeat!r}"):
        HysteresisDataModule(repeat=repeat)


def test_mixed_columns_across_files(tmp_path: Path) -> None:
    a = write_runs(tmp_path / "a.csv", {10: 40})
    b = write_runs(tmp_path / "b.csv", {11: 40}, header="loop,time,command,response")
    with pytest.raises(DataFileError, match=rf"{re.escape(str(b))}: columns \['loop', .*\] "
                       rf"differ from the columns \['run', .*\] of {re.escape(str(a))}; every "
                       "file in path"):
        data([str(a), str(b)])


def test_recording_ids_unique_across_files(tmp_path: Path) -> None:
    a = write_runs(tmp_path / "a.csv", {10: 40, 11: 30})
    b = write_runs(tmp_path / "b.csv", {11: 40})
    where = rf"{re.escape(str(b))}: recording 11 .* is also in {re.escape(str(a))}"
    with pytest.raises(DataFileError, match=where):
        data([str(a), str(b)])


def test_recording_rows_must_be_contiguous(tmp_path: Path) -> None:
    path = tmp_path / "runs.csv"
    rows = run_rows(10, 20) + run_rows(11, 20) + run_rows(10, 20)
    path.write_text("run,time,command,response\n"
                    + "".join(",".join(str(v) for v in r) + "\n" for r in rows))
    with pytest.raises(DataFileError, match=r"column 'run' \(run_column\), row 40 \(line 42\): "
                       "recording 10 starts again"):
        read_recordings(path, input_column="response", target_column="command",
                        run_column="run")


def test_time_restarting_needs_the_run_column(tmp_path: Path) -> None:
    path = write_runs(tmp_path / "runs.csv", {10: 40, 11: 30})
    with pytest.raises(DataFileError, match=r"column 'time' \(time_column\), row 40"):
        data(path, run_column=None)


@pytest.mark.parametrize(
    "kwargs, match",
    [(dict(split_by="run"), "split_by must be one of"),
     (dict(train_recordings=[0]), "train_recordings need split_by='recording'"),
     (dict(run_column="loop"), "run_column='loop' needs recorded data"),
     (dict(path=[]), "path must be a file or a non-empty list of files"),
     (dict(path=["a.csv", "./a.csv"]), "path lists the file './a.csv' twice"),
     (dict(min_samples=0), "min_samples must be an int >= 1, got 0"),
     (dict(min_samples="16"), "min_samples must be an int >= 1, got '16'")],
)
def test_bad_options(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        HysteresisDataModule(**kwargs)


def test_tensors_needs_a_single_sequence(tmp_path: Path) -> None:
    dm = data(write_runs(tmp_path / "runs.csv", LENGTHS), split_by="recording")
    with pytest.raises(ValueError, match=r"tensors\('train'\) needs a stage of one sequence"):
        dm.tensors("train")


def test_paper_split_may_evaluate_on_training_recordings(tmp_path: Path) -> None:
    path = write_runs(tmp_path / "runs.csv", {10: 40, 11: 30})
    dm = data(path, split_by="recording", split="paper", train_recordings=[10, 11],
              test_recordings=[11])
    assert dm is not None


def test_a_file_read_again_is_parsed_once_until_it_changes(tmp_path: Path,
                                                           monkeypatch) -> None:
    """Model selection builds a datamodule per candidate and fold: the file is parsed once,
    every caller gets its own arrays, and a file written again is read again."""
    import os

    from torchhys.data import files

    path = tmp_path / "log.csv"
    path.write_text("u,y\n" + "".join(f"{i},{2 * i}\n" for i in range(10)))
    parsed = []
    real = files._read
    monkeypatch.setattr(files, "_read", lambda *a: parsed.append(1) or real(*a))
    first = read_recordings(path, input_column="u", target_column="y")
    first[0].x[0] = 99.0  # a caller's copy: the next read does not see it
    second = read_recordings(path, input_column="u", target_column="y")
    assert len(parsed) == 1 and second[0].x[0] == 0.0
    assert read_recordings(path, input_column="y", target_column="u")[0].x[1] == 2.0
    path.write_text("u,y\n" + "".join(f"{i},{3 * i}\n" for i in range(10)))
    os.utime(path, ns=(1, 1))  # a new modification time even on a coarse clock
    assert read_recordings(path, input_column="u", target_column="y")[0].y[1] == 3.0
    assert len(parsed) == 3
