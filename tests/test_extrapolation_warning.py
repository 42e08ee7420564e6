"""``torchhys test`` and ``torchhys predict`` warn once with the share of inputs outside the
training input range; an exported compensator clamps them (tests/test_streaming_direction.py).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from _training_helpers import DROP, LINE, cli, small_config

CONFIG = {"trainer": {"max_epochs": 2}, "model": {**LINE, "lr": 1.0},
          "data": {"simulation": DROP, "t_end": DROP, "input_column": "response",
                   "target_column": "command"}}
"""The sections of :func:`small_config`: the straight line, on a file given by --data.path."""


def record(path: Path, late_gain: float) -> tuple[np.ndarray, float, float]:
    """A CSV of 500 rows whose last 40 % (validation and test) are ``late_gain`` times
    larger than the training part; the inputs and the training range."""
    t = np.linspace(0, 20 * np.pi, 500)
    gain = np.where(np.arange(500) < 300, 1.0, late_gain)
    x = gain * np.sin(t)
    y = x + 0.2 * np.cos(t)
    np.savetxt(path, np.column_stack([x, y]), delimiter=",", header="response,command",
               comments="")
    return x, float(x[:300].min()), float(x[:300].max())


def run(monkeypatch, tmp_path: Path, late_gain: float) -> tuple[list[str], np.ndarray, float,
                                                                float]:
    data = tmp_path / "log.csv"
    x, lo, hi = record(data, late_gain)
    cfg = small_config(tmp_path, "c.yaml", **CONFIG)
    root = tmp_path / "run"
    common = ["--config", str(cfg), f"--data.path={data}", f"--trainer.default_root_dir={root}"]
    cli(monkeypatch, "fit", *common)
    ckpt = str(root / "logs/version_0/checkpoints/last.ckpt")
    messages = []
    for sub in ("test", "predict"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cli(monkeypatch, sub, *common, f"--ckpt_path={ckpt}")
        messages += [str(w.message) for w in caught if "outside the training input" in
                     str(w.message)]
    return messages, x, lo, hi


def test_test_and_predict_warn_once_with_the_share_outside(monkeypatch, tmp_path) -> None:
    messages, x, lo, hi = run(monkeypatch, tmp_path, 3.0)
    assert len(messages) == 2, messages
    test_part = x[400:]  # the test split (the last 20 %)
    outside = int(((test_part < lo) | (test_part > hi)).sum())
    assert messages[0].startswith(f"test: {outside} of {test_part.size} input samples")
    assert f"[{lo:.6g}, {hi:.6g}]" in messages[0]
    # predict scores the whole record: its share is that of all 500 samples
    outside = int(((x < lo) | (x > hi)).sum())
    assert messages[1].startswith(f"predict: {outside} of {x.size} input samples")


def test_no_warning_inside_the_range(monkeypatch, tmp_path) -> None:
    messages, *_ = run(monkeypatch, tmp_path, 0.5)
    assert messages == []
