"""The command line with operating conditions: ``data.condition_columns``, the choice by
leaving one condition out (``configs/conditions.yaml``), ``test`` beside a polynomial of
the input and the condition, ``predict`` writing the condition, ``export`` to C whose step
takes the condition (compiled and run against the network), and one-line errors for bad
condition columns."""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

import torchhys
from torchhys.checkpoints import read_checkpoint
from torchhys.cli.export import build_net
from torchhys.cli.export import main as export_main
from torchhys.cli.main import main
from torchhys.deploy.streaming import StreamingCompensator

sys.path.insert(0, str(Path(__file__).parent))
from _export_helpers import CC, NO_CC, run_driver  # noqa: E402
from test_conditions_export import DRIVER  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
VOLTS = (0.0, 1.0, 2.0, 3.0, 4.0)


def _write_log(path: Path, *, constant: bool = False, bad: str | None = None) -> Path:
    """Two recordings per condition (even: train, odd: test): plays whose widths and gain
    grow with the condition, driven by sines whose amplitude swells and fades."""
    t = torch.linspace(0, 16, 400, dtype=torch.float64)
    r = torch.linspace(0.0, 0.4, 5, dtype=torch.float64)
    rows = []
    for k in range(2 * len(VOLTS)):
        v = 2.0 if constant else VOLTS[k // 2]
        x = torch.sin(t * (1 + 0.15 * k)) * (0.65 + 0.35 * torch.cos(0.7 * t))
        y = torchhys.Backlash(r * (1 + 0.3 * v))(x[None])[0][0].sum(-1) * (1 + 0.5 * v)
        rows += [[k, v, float(a), float(b)] for a, b in zip(x, y, strict=True)]
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["recording", "voltage_V", "response", "command"])
        for i, row in enumerate(rows):
            w.writerow([row[0], bad if bad is not None and i == 50 else row[1], *row[2:]])
    return path


def _config(tmp: Path, log: Path, **data: object) -> Path:
    cfg = yaml.safe_load((ROOT / "configs" / "conditions.yaml").read_text())
    cfg["trainer"]["default_root_dir"] = str(tmp / "runs")
    cfg["trainer"]["enable_progress_bar"] = False
    cfg["data"].update({"path": str(log), "input_column": "response",
                        "target_column": "command", "train_recordings": [0, 2, 4, 6, 8],
                        "test_recordings": [1, 3, 5, 7, 9], "warmup": 10})
    del cfg["data"]["time_column"]
    cfg["data"].update(data)
    out = tmp / "conditions.yaml"
    out.write_text(yaml.safe_dump(cfg))
    return out


@pytest.fixture(scope="module")
def fitted(tmp_path_factory) -> tuple[Path, Path, Path]:
    tmp = tmp_path_factory.mktemp("conditions_cli")
    config = _config(tmp, _write_log(tmp / "log.csv"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(sys, "argv", ["torchhys"])
        main(["fit", "--config", str(config)])
    return tmp, config, tmp / "runs" / "logs" / "version_0" / "checkpoints" / "last.ckpt"


def test_fit_leaves_one_condition_out_and_chooses_a_conditioned_model(fitted) -> None:
    tmp, _, ckpt = fitted
    table = list(csv.DictReader((tmp / "runs" / "logs" / "version_0" /
                                 "selection.csv").open()))
    chosen = [r for r in table if r["selected"] == "1"]
    assert len(chosen) == 1 and "condition_degree" in chosen[0]["config"]
    assert all(r["fold_5"] for r in table if r["val_mse"] != "nan")  # five conditions
    plain = [float(r["val_mse"]) for r in table if "condition_degree" not in r["config"]]
    assert float(chosen[0]["val_mse"]) < 0.2 * min(plain)
    hp = read_checkpoint(ckpt)["hyper_parameters"]
    assert hp["n_conditions"] == 1 and hp["condition_degree"] is not None


def test_test_compares_with_a_polynomial_of_the_input_and_the_condition(fitted, capsys) -> None:
    tmp, config, ckpt = fitted
    main(["test", "--config", str(config), "--ckpt_path", str(ckpt)])
    out = capsys.readouterr().out
    values = {ln.split()[0]: float(ln.split()[1]) for ln in out.splitlines()
              if ln.strip().startswith("test_")}
    assert values["test_ratio"] < 0.5
    # the polynomial sees the condition: far better than the line, which does not
    assert values["test_poly_mse"] < 0.8 * values["test_line_mse"]


def test_predict_writes_the_condition(fitted) -> None:
    tmp, config, ckpt = fitted
    main(["predict", "--config", str(config), "--ckpt_path", str(ckpt)])
    rows = list(csv.DictReader((tmp / "runs" / "predictions.csv").open()))
    assert "voltage_V" in rows[0]
    assert sorted({float(r["voltage_V"]) for r in rows}) == list(VOLTS)


@pytest.mark.skipif(CC is None, reason=NO_CC)
def test_export_writes_a_c_step_that_takes_the_condition(fitted) -> None:
    tmp, _, ckpt = fitted
    out = tmp / "c"
    out.mkdir()
    assert export_main(["--ckpt", str(ckpt), "--format", "c", "--out", str(out),
                        "--direction", "none"]) == 0
    header = (out / "torchhys_comp.h").read_text()
    assert "#define torchhys_comp_N_CONDITIONS 1" in header
    net = build_net(read_checkpoint(ckpt))
    t = torch.linspace(0, 10, 300, dtype=torch.float64)
    x, c = torch.sin(t) * 0.8, 1.5 + torch.sin(0.3 * t)  # a condition that moves
    got = run_driver(out, DRIVER, out / "torchhys_comp.c", zip(x, c, strict=True))[1:301]
    comp = StreamingCompensator(net, direction="none")
    want = torch.stack([comp.step(x[k:k + 1], c[k].view(1, 1)) for k in range(300)])[:, 0]
    np.testing.assert_allclose([float(v) for v in got], want.detach().numpy(), rtol=0,
                               atol=1e-9)


def _error(capsys, config: Path) -> str:
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--config", str(config)])
    assert exc.value.code == 2
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert lines[-1].startswith("torchhys fit: error: ") and "Traceback" not in lines[-1]
    return lines[-1]


def test_a_missing_condition_column_is_one_line(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    config = _config(tmp_path, _write_log(tmp_path / "log.csv"), condition_columns=["volts"])
    line = _error(capsys, config)
    assert "'volts'" in line and "condition_columns[0]" in line


def test_a_constant_condition_is_one_line(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    config = _config(tmp_path, _write_log(tmp_path / "log.csv", constant=True))
    line = _error(capsys, config)
    assert "'voltage_V'" in line and "constant over the training split" in line


@pytest.mark.parametrize("bad", ["high", "nan"])
def test_a_non_numeric_or_nan_condition_is_one_line(tmp_path, capsys, monkeypatch,
                                                     bad: str) -> None:
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    config = _config(tmp_path, _write_log(tmp_path / "log.csv", bad=bad))
    line = _error(capsys, config)
    assert "voltage_V" in line and "line 52" in line


def test_condition_columns_that_are_no_list_or_repeat_a_column(tmp_path, capsys,
                                                               monkeypatch) -> None:
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    log = _write_log(tmp_path / "log.csv")
    line = _error(capsys, _config(tmp_path, log, condition_columns=["voltage_V", "response"]))
    assert "condition_columns" in line and "'response'" in line


def test_lightning_runs_of_the_candidates_leave_one_condition_out(tmp_path, capsys,
                                                                  monkeypatch) -> None:
    """A trainer section select cannot honour (gradient clipping) trains each candidate by
    Lightning on the folds of torchhys.training.folds.ConditionFold."""
    from torchhys.data.files import read_recordings
    from torchhys.training import HysteresisDataModule
    from torchhys.training.folds import ConditionFold

    monkeypatch.setattr(sys, "argv", ["torchhys"])
    log = _write_log(tmp_path / "log.csv")
    config = _config(tmp_path, log)
    cfg = yaml.safe_load(config.read_text())
    cfg["trainer"]["gradient_clip_val"] = 1.0
    cfg["model"]["optimizer_kwargs"] = {}
    cfg["model"]["select"] = [
        {"operator": None, "hidden": 3, "activation": "tanh", "optimizer": "adam", "lr": 0.01},
        {"operator": None, "hidden": 3, "activation": "tanh", "optimizer": "adam", "lr": 0.01,
         "condition_degree": 1}]
    config.write_text(yaml.safe_dump(cfg))
    main(["fit", "--config", str(config)])
    err = capsys.readouterr().err
    assert "trained through Lightning: trainer.gradient_clip_val" in err
    table = list(csv.DictReader((tmp_path / "runs" / "logs" / "version_0" /
                                 "selection.csv").open()))
    assert all(r["fold_5"] and r["val_mse"] != "nan" for r in table)
    # the folds: each condition's training recordings held out together, with conditions
    data = HysteresisDataModule(**{k: v for k, v in cfg["data"].items()})
    fold = ConditionFold(data, 2)
    assert fold.k == 5 and len(fold._val) == 5 and len(fold._train) == 5
    assert set(fold._val[4].unique().tolist()) == {VOLTS[2]}
    assert VOLTS[2] not in set(fold._train[4].unique().tolist())
    assert fold.train_conditions().shape[:-1] == fold.train_tensors()[0].shape
    assert len(read_recordings(log, input_column="response", target_column="command",
                               run_column="recording")) == 10
