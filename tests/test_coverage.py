"""What a training record cannot show: the branches between reversals
(``torchhys.functional.reversal_ranges``) and the warning of ``torchhys fit``'s model
selection on records of one loop amplitude or less than one closed loop
(``torchhys.selection.coverage.coverage_warning``)."""

from __future__ import annotations

import math
import warnings
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
import torch
from _training_helpers import DROP, LINE, cli, small_config

from torchhys.functional import reversal_ranges
from torchhys.selection.coverage import WHAT_TO_RECORD, coverage_warning

F64 = torch.float64


def zigzag(points: list[float], n: int = 10) -> torch.Tensor:
    """Straight segments of ``n`` samples between successive ``points``."""
    parts = [np.linspace(a, b, n, endpoint=False) for a, b in pairwise(points)]
    return torch.tensor(np.concatenate(parts + [[points[-1]]]), dtype=F64)


def loop_reference(x: np.ndarray) -> tuple[list[int], list[float]]:
    """Turning points of a noise-free piecewise-monotone sequence by a plain loop: where
    the sign of the step changes; the branches between them."""
    steps = np.sign(np.diff(x))
    turns = [t for t in range(1, len(x) - 1) if steps[t - 1] != 0 and steps[t] == -steps[t - 1]]
    return turns, [abs(x[b] - x[a]) for a, b in pairwise(turns)]


def test_reversal_ranges_against_a_plain_loop() -> None:
    x = zigzag([0.0, 1.0, -1.0, 0.5, -0.5, 2.0, 0.2])
    turns, ranges = loop_reference(x.numpy())
    assert turns == [10, 20, 30, 40, 50]
    b = reversal_ranges(x)
    assert b.start.tolist() == turns[:-1]
    assert b.end.tolist() == turns[1:]
    torch.testing.assert_close(b.range, torch.tensor(ranges, dtype=F64))
    torch.testing.assert_close(b.range, torch.tensor([2.0, 1.5, 1.0, 2.5], dtype=F64))


def test_reversal_ranges_threshold_ignores_small_swings() -> None:
    # a swing back of 0.1 inside the rise from -1 to 1
    x = zigzag([1.0, -1.0, 0.0, -0.1, 1.0, -1.0, 1.0])
    assert reversal_ranges(x).range.tolist() == pytest.approx([1.0, 0.1, 1.1, 2.0])
    b = reversal_ranges(x, threshold=0.2)
    assert b.range.tolist() == pytest.approx([2.0, 2.0])
    assert b.start.tolist() == [10, 40] and b.end.tolist() == [40, 50]
    assert reversal_ranges(torch.ones(5, dtype=F64)).range.numel() == 0


def test_reversal_ranges_errors() -> None:
    with pytest.raises(ValueError, match=r"x must be a sequence of shape \(time,\)"):
        reversal_ranges(torch.zeros(2, 10))
    with pytest.raises(ValueError, match="x"):
        reversal_ranges(torch.tensor([0.0, math.nan, 1.0]))


def sine(amplitudes: list[float], per: int = 40, noise: float = 0.0) -> torch.Tensor:
    """Whole periods of a sine, one period per amplitude."""
    t = torch.arange(per, dtype=F64) * 2 * math.pi / per
    x = torch.cat([a * torch.sin(t) for a in amplitudes])
    return x + noise * torch.randn(x.shape, dtype=F64, generator=torch.Generator().manual_seed(0))


def scored_after(x: torch.Tensor, warmup: int) -> torch.Tensor:
    mask = torch.zeros_like(x, dtype=torch.bool)
    mask[..., warmup:] = True
    return mask


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_one_amplitude(noise: float) -> None:
    x = sine([1.0, 1.0, 1.0], noise=noise)[None]
    message = coverage_warning(x, scored_after(x, 80), source="loop.csv")
    assert message is not None
    assert "loops of one amplitude" in message and "loop.csv" in message
    assert "What to record for a fit" in message


@pytest.mark.parametrize("rows", [
    [[0.4, 0.4, 0.4], [1.0, 1.0, 1.0]],  # two recordings, one amplitude each
    [[1.0, 0.8, 0.6, 0.4, 0.2, 0.2]],  # a decaying sine
    [[1.0, 0.5, 1.0, 0.5, 1.0, 0.5]],  # a minor loop after each major one
])
def test_several_amplitudes(rows: list[list[float]]) -> None:
    x = torch.stack([sine(r) for r in rows])
    assert coverage_warning(x, scored_after(x, 20)) is None


@pytest.mark.parametrize("scored", [slice(45, 60), slice(45, 75)])
def test_less_than_one_closed_loop(scored: slice) -> None:
    """Part of one stroke, or a stroke and part of the next (the warm-up holds whole
    loops, the scored samples do not)."""
    x = sine([1.0, 1.0, 1.0])[None]
    mask = torch.zeros_like(x, dtype=torch.bool)
    mask[0, scored] = True
    message = coverage_warning(x, mask, source="short.csv")
    assert message is not None and "less than one closed loop" in message
    mask[0, scored.start:scored.start + 40] = True  # one whole period: a closed loop
    assert "one amplitude" in coverage_warning(x, mask)


@pytest.mark.parametrize("points", [
    [-1.0, 1.0, -1.0, 1.0, -1.0],  # two whole loops, every sample scored
    [0.0, 1.0, -1.0, 1.0, -1.0, 0.0],  # a sine's two periods from 0
])
def test_one_amplitude_scored_from_the_first_sample(points: list[float]) -> None:
    """Without a warm-up the first reversal ends no complete branch; the loops still close."""
    x = zigzag(points)[None]
    message = coverage_warning(x, torch.ones_like(x, dtype=torch.bool))
    assert message is not None and "loops of one amplitude" in message
    one_period = sine([1.0])[None]  # a whole period scored from its start: a closed loop
    assert "less than one closed loop" not in (
        coverage_warning(one_period, torch.ones_like(one_period, dtype=torch.bool)) or "")


def test_a_recording_at_rest_does_not_close_the_loop() -> None:
    """A row whose scored part is at rest travels nothing: with part of a stroke in the
    other row, the training part still holds less than one closed loop."""
    stroke = torch.linspace(-1.0, 1.0, 120, dtype=F64)
    x = torch.stack([stroke, torch.zeros_like(stroke)])
    message = coverage_warning(x, scored_after(x, 20))
    assert message is not None and "less than one closed loop" in message


def test_coverage_warning_errors_constant_input_and_empty_mask() -> None:
    x = sine([1.0, 0.5])[None]
    with pytest.raises(ValueError, match=r"x and mask must have the same shape"):
        coverage_warning(x, torch.ones(1, 10, dtype=torch.bool))
    assert coverage_warning(x, torch.zeros_like(x, dtype=torch.bool)) is None
    flat = torch.ones(2, 50, dtype=F64)
    assert coverage_warning(flat, scored_after(flat, 5)) is None  # the fits say why
    assert coverage_warning(x.float(), scored_after(x, 5).float()) is None  # 0/1 mask


SELECT = {"select": [{"operator": None}, {"operator": [{"fit": "pi_nonneg", "n_widths": 4}]}],
          "select_cv": 2}


@pytest.mark.parametrize("select", [True, False])
@pytest.mark.parametrize(("amplitudes", "warns"), [([1.0] * 6, True),
                                                   ([1.0, 0.4] * 3, False)])
def test_fit_warns_on_one_amplitude(monkeypatch, tmp_path: Path, amplitudes: list[float],
                                    warns: bool, select: bool) -> None:
    """Once, with model selection (before the candidates train) or without (before the
    fit)."""
    u = sine(amplitudes).numpy()
    y = u + 0.2 * np.tanh(np.gradient(u) * 10)  # a lagging, loop-shaped response
    data = tmp_path / "loops.csv"
    np.savetxt(data, np.c_[u, y], delimiter=",", header="u,y", comments="")
    model = {**LINE, **SELECT} if select else {**LINE,
                                                "operator": [{"fit": "pi_ls", "n_widths": 4}]}
    cfg = small_config(tmp_path, "fit.yaml",
                       trainer={"max_epochs": 2, "check_val_every_n_epoch": DROP}, model=model,
                       data={"simulation": DROP, "t_end": DROP, "path": data,
                             "input_column": "u", "target_column": "y",
                             "split": [0.8, 0.0, 0.2], "warmup": 40})
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path}")
    mine = [str(w.message) for w in record if WHAT_TO_RECORD in str(w.message)]
    assert len(mine) == (1 if warns else 0), mine
    if warns:
        prefix = "model.select" if select else "fit"
        assert mine[0].startswith(f"{prefix}: every branch of the training part of")
        assert "loops of one amplitude" in mine[0]
