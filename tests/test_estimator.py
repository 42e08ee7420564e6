"""torchhys.Compensator: a compensator fitted from arrays in one call, against the selection
it runs (torchhys.selection.select on the same record), its own exports and the command
line's choice on the measured config."""

from __future__ import annotations

import csv
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import torchhys
from torchhys.selection import select

ROOT = Path(__file__).resolve().parents[1]
CONFIG = {  # a small config: the line and two PI families, blocked CV on 3 blocks
    "seed_everything": 0,
    "trainer": {"max_epochs": 5},
    "data": {"warmup": 20},
    "model": {"operator": None, "hidden": 1, "activation": "identity", "optimizer": "lbfgs",
              "select": [{"operator": None},
                         {"operator": [{"fit": "pi_nonneg", "n_widths": 8, "power": 2.0,
                                        "direction": "inverse"}]},
                         {"operator": [{"fit": "stop_pi", "n_widths": 10, "power": 2.0,
                                        "segments": 3}]}],
              "select_cv": 3, "select_rule": "min"},
}


def plant_record(n: int = 1200, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(response, command) of a backlash-like plant: the response lags the command."""
    t = np.arange(n) / 50.0
    rng = np.random.default_rng(seed)
    u = 3.0 * np.sin(0.7 * t) * (1.0 - 0.8 * t / t[-1]) + 0.5 * np.sin(2.3 * t)
    y = np.empty(n)
    state = 0.0
    for i, v in enumerate(u):  # a play of half-width 0.4, then a gain
        state = min(max(state, v - 0.4), v + 0.4)
        y[i] = 1.5 * state
    return y + 0.001 * rng.standard_normal(n), u


def test_fit_runs_the_configs_selection_on_the_arrays() -> None:
    y, u = plant_record()
    seen = []
    comp = torchhys.Compensator.fit(y, u, config=CONFIG,
                                    progress=lambda done, total, s: seen.append((done, total)))
    model = CONFIG["model"]
    ref = select(model["select"], torch.tensor(y)[None], torch.tensor(u)[None],
                 base={k: model[k] for k in ("operator", "hidden", "activation", "optimizer")},
                 warmup=20, cv=3, rule="min", seed=0, epochs=5)
    assert comp.selection.chosen.index == ref.chosen.index != 0  # a hysteresis model
    for a, b in zip(comp.selection.scores, ref.scores, strict=True):
        assert a.val_mse == b.val_mse or (math.isnan(a.val_mse) and math.isnan(b.val_mse))
    assert seen == [(1, 3), (2, 3), (3, 3)]
    got = comp.predict(y)
    want, _ = ref.model(torch.tensor(y)[None])
    assert got.shape == y.shape
    np.testing.assert_allclose(got, want[0].detach().numpy(), rtol=0, atol=1e-12)
    # numpy and torch inputs, a list of recordings: the same commands
    np.testing.assert_array_equal(comp.predict(torch.tensor(y)), got)


def test_score_reports_rmse_range_and_the_baselines() -> None:
    y, u = plant_record()
    comp = torchhys.Compensator.fit(y[:900], u[:900], config=CONFIG)
    s = comp.score(y[900:], u[900:])
    pred = comp.predict(y[900:])
    rmse = float(np.sqrt(np.mean((pred - u[900:]) ** 2)))
    assert s["rmse"] == pytest.approx(rmse, rel=1e-12)
    assert s["max_error"] == pytest.approx(float(np.abs(pred - u[900:]).max()), rel=1e-12)
    assert s["rmse_pct_of_range"] == pytest.approx(100 * rmse / np.ptp(u[900:]), rel=1e-12)
    line = np.polyfit(y[20:900], u[20:900], 1)  # the line on the scored training samples
    line_rmse = float(np.sqrt(np.mean((np.polyval(line, y[900:]) - u[900:]) ** 2)))
    assert s["line_rmse"] == pytest.approx(line_rmse, rel=1e-6)
    assert s["ratio_to_baseline"] < 1.0  # the plant's backlash: the model earns its place


def test_recordings_label_the_rows() -> None:
    y, u = plant_record(1000)
    labels = np.repeat([0, 1], 500)
    comp = torchhys.Compensator.fit(y, u, config=CONFIG, recordings=labels)
    assert comp._x.shape == (2, 500)
    rows = torchhys.Compensator.fit([y[:500], y[500:]], [u[:500], u[500:]], config=CONFIG)
    assert [s.val_mse for s in comp.selection.scores] == \
        [s.val_mse for s in rows.selection.scores]


def test_export_c_and_torchscript_run_the_fitted_model(tmp_path: Path) -> None:
    from torchhys.deploy.export import load_torchscript

    y, u = plant_record()
    comp = torchhys.Compensator.fit(y, u, config=CONFIG)
    comp.export("torchscript", tmp_path / "c.pt")
    h, c = comp.export("c", tmp_path)
    assert h.exists() and c.exists()
    module = load_torchscript(tmp_path / "c.pt")
    assert float(module.high) == pytest.approx(u.max())  # saturated to the training range
    x = torch.tensor(y[:300])
    streamed = np.array([float(module.step(x[i:i + 1])[0]) for i in range(300)])
    np.testing.assert_allclose(streamed, comp.predict(y[:300]), rtol=0, atol=1e-9)


def test_plot_writes_a_figure(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    y, u = plant_record(600)
    comp = torchhys.Compensator.fit(y, u, config=CONFIG)
    fig = comp.plot(path=tmp_path / "loop.png")
    assert (tmp_path / "loop.png").stat().st_size > 1000 and len(fig.axes) == 2


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"response": "abc"}, "response must be an array of numbers"),
    ({"command": np.zeros(5)}, "response and command must have the same shape"),
    ({"response": np.zeros((2, 2, 2))}, "response must be (time,) or (rows, time)"),
    ({"config": "no_such_config"}, "no shipped config of that name"),
    ({"config": 3}, "config must be a shipped config's name"),
    ({"recordings": np.zeros(3)}, "recordings must label each sample"),
])
def test_bad_input_names_the_argument(kwargs: dict, message: str) -> None:
    y, u = plant_record(200)
    args = {"response": y, "command": u, "config": CONFIG, **kwargs}
    with pytest.raises((ValueError, TypeError)) as err:
        torchhys.Compensator.fit(args.pop("response"), args.pop("command"), **args)
    assert message in str(err.value) and "\n" not in str(err.value)


@pytest.mark.slow
def test_the_measured_config_chooses_as_the_command_line(tmp_path: Path,
                                                        monkeypatch: pytest.MonkeyPatch,
                                                        capsys) -> None:
    """``Compensator.fit(config="measured")`` on the training split of the example file
    scores every candidate as ``torchhys fit --config configs/measured.yaml`` does."""
    pytest.importorskip("lightning")
    sys.path.insert(0, str(Path(__file__).parent))
    from _training_helpers import cli

    monkeypatch.chdir(ROOT)
    cli(monkeypatch, "fit", "--config", "configs/measured.yaml",
        f"--trainer.default_root_dir={tmp_path}", "--trainer.enable_progress_bar=false",
        "--model.select_jobs=1")
    capsys.readouterr()
    with open(next(tmp_path.glob("**/selection.csv"))) as fh:
        table = list(csv.DictReader(fh))
    with open(ROOT / "examples/data/bouc_wen.csv") as fh:
        rows = list(csv.DictReader(line for line in fh if not line.startswith("#")))
    y = np.array([float(r["response"]) for r in rows])
    u = np.array([float(r["command"]) for r in rows])
    n = round(0.7 * len(y))  # the config's training split
    comp = torchhys.Compensator.fit(y[:n], u[:n], config="measured")
    got = [s.val_mse for s in comp.selection.scores]
    want = [float(r["val_mse"]) for r in table]
    np.testing.assert_allclose(got, want, rtol=1e-6, equal_nan=True)
