"""The model beside the memoryless baselines on a split, and its picture.

:func:`compare_baselines` fits a straight line and a polynomial of the input (with operating
conditions, of the input and the conditions) on the training part and scores them and the
model on the samples of another split; :func:`draw_report` draws the loop, the tracking
beside the baselines and the error over time into a PNG. Two callbacks use them:
:class:`~torchhys.training.callbacks.BaselineComparison` after ``test``
(``test_report.png``) and :class:`FitReport` after ``fit`` (``fit_report.png``, on the
validation split).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.utilities import rank_zero_warn

from torchhys._checks import check_int
from torchhys.training.baselines import (
    MAX_DEGREE,
    fit_condition_polynomial,
    fit_polynomial,
    max_degree,
)

__all__ = ["Comparison", "FitReport", "compare_baselines", "draw_report", "scored_samples"]

Scored = tuple[torch.Tensor, torch.Tensor, torch.Tensor, "torch.Tensor | None"]
"""A batch's scored samples: input, target, prediction (each flat) and conditions or None."""


@dataclass
class Comparison:
    """The model and the baselines on the scored samples of a split.

    ``results`` (keys prefixed by the split's name, ``test_`` or ``val_``): ``mse``,
    ``line_mse``, ``poly_mse``, ``poly_degree``, ``ratio`` (the model's RMSE over the better
    baseline's; 1 when both are 0), ``rmse``, ``max_error``, ``rmse_pct`` (the RMSE in % of
    the targets' range). The tensors are the scored samples, flat, in the batches' order.
    """

    results: dict[str, float]
    input: torch.Tensor
    target: torch.Tensor
    prediction: torch.Tensor
    line: torch.Tensor
    poly: torch.Tensor


def compare_baselines(train: Sequence[Any], scored: Sequence[Scored], split: str,
                      max_degree_: int = MAX_DEGREE) -> Comparison | None:
    """The baselines fitted on the rows of the ``train`` batches (``(x, y, warmup, mask[,
    conditions])``), scored with the model on ``scored``; None (with a warning where the
    reason is the data) when there is nothing to compare."""
    if not scored or not train:
        return None
    x, y, mask = _rows(train)
    top = min(max_degree_, max_degree(mask))
    if top < 1:
        rank_zero_warn("baselines: the training split has too few scored samples to fit "
                       "a straight line before its hold-out; no comparison")
        return None
    line = fit_polynomial(x, y, mask, degrees=(1,))
    tx, ty, pred = (torch.cat(v) for v in list(zip(*scored, strict=True))[:3])
    conds = [t[3] for t in scored]
    if all(c is not None for c in conds) and len(train[0]) == 5:
        cx = _condition_rows(train, x.shape[-1])
        poly = fit_condition_polynomial(x, cx, y, mask, degrees=range(1, min(5, top) + 1))
        poly_out = poly(tx, torch.cat(conds))  # type: ignore[arg-type]
    else:
        poly = fit_polynomial(x, y, mask, degrees=range(1, top + 1))
        poly_out = poly(tx)

    def mse(p: torch.Tensor) -> float:
        return float((p - ty).square().mean())

    model, line_out = mse(pred), line(tx)
    line_mse, poly_mse = mse(line_out), mse(poly_out)
    best = min(line_mse, poly_mse)
    ratio = math.sqrt(model / best) if best > 0 else (1.0 if model == 0 else math.inf)
    span = float(ty.max() - ty.min()) if ty.numel() else 0.0
    results = {"mse": model, "line_mse": line_mse, "poly_mse": poly_mse,
               "poly_degree": float(poly.degree), "ratio": ratio, "rmse": math.sqrt(model),
               "max_error": float((pred - ty).abs().max()),
               "rmse_pct": 100.0 * math.sqrt(model) / span if span > 0 else math.nan}
    return Comparison({f"{split}_{k}": v for k, v in results.items()}, tx, ty, pred,
                      line_out, poly_out)


def draw_report(path: str | Path, comparison: Comparison, split: str) -> Path | None:
    """Draw ``comparison`` (:func:`compare_baselines` of the split named ``split``) into
    the PNG ``path``: the loop of target and prediction against the input, the tracking
    beside the baselines, the error over the samples. None without matplotlib."""
    try:
        import matplotlib
    except ImportError:  # the train extra holds it; a bare environment draws nothing
        return None
    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    r = {k.removeprefix(f"{split}_"): v for k, v in comparison.results.items()}
    name = {"val": "validation"}.get(split, split)
    x, y, pred, line, poly = (v.numpy() for v in (comparison.input, comparison.target,
                                                  comparison.prediction, comparison.line,
                                                  comparison.poly))
    fig, (a, b, c) = plt.subplots(1, 3, figsize=(15, 4))
    a.plot(x, y, color="0.6", lw=1, label="target")
    a.plot(x, pred, color="C0", lw=1, label="model")
    a.set(xlabel="input", ylabel="target", title=f"the loop ({name} samples)")
    a.legend()
    b.plot(y, color="0.6", lw=1, label="target")
    b.plot(pred, color="C0", lw=1, label=f"model (RMSE {r['rmse']:.3g})")
    b.plot(line, color="C1", lw=0.8, ls="--", label="straight line")
    b.plot(poly, color="C2", lw=0.8, ls=":", label=f"polynomial (degree {int(r['poly_degree'])})")
    b.set(xlabel=f"{name} sample", ylabel="target",
          title=f"tracking and the baselines (ratio {r['ratio']:.3g})")
    b.legend(fontsize=8)
    c.plot(pred - y, lw=0.8)
    c.set(xlabel=f"{name} sample", ylabel="model - target",
          title=f"error (max {r['max_error']:.3g}, RMSE {r['rmse_pct']:.3g} % of range)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


class FitReport(L.Callback):
    """After ``fit``: the fitted model on the validation split beside the baselines fitted on
    the training split (:func:`compare_baselines`), drawn into ``fit_report.png`` in the
    run's log folder (:func:`draw_report`), its path printed (rank 0, a trainer with a
    logger, a datamodule serving ``batches("train")`` and ``batches("val")``; needs
    matplotlib). :attr:`results` keeps the comparison's numbers (``val_rmse``, ...).

    Args:
        max_degree: the highest polynomial degree tried (>= 1).
        enabled: draw the report (``--fit_report.enabled false``: not).
    """

    def __init__(self, max_degree: int = MAX_DEGREE, enabled: bool = True) -> None:
        self.max_degree = check_int(max_degree, "max_degree", minimum=1)
        self.enabled = bool(enabled)
        self.report_path: Path | None = None
        self.results: dict[str, float] = {}

    def on_fit_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        dm = getattr(trainer, "datamodule", None)
        if (not self.enabled or not trainer.loggers or dm is None or not hasattr(dm, "batches")
                or not hasattr(pl_module, "scored_outputs")):
            return
        folder = Path(trainer.log_dir)  # a broadcast: every rank asks, or rank 0 waits forever
        if trainer.global_rank != 0:
            return
        val = dm.batches("val")
        if not val:
            return
        was_training = pl_module.training
        pl_module.eval()
        try:
            scored = [scored_samples(pl_module.scored_outputs(_to(b, pl_module.device), "val"))
                      for b in val]
        finally:
            pl_module.train(was_training)
        comparison = compare_baselines(dm.batches("train"), scored, "val", self.max_degree)
        if comparison is None:
            return
        self.results = comparison.results
        self.report_path = draw_report(folder / "fit_report.png", comparison, "val")
        if self.report_path is not None:
            print(f"torchhys fit: the fitted loop, the validation tracking and error in "
                  f"{self.report_path}", flush=True)


def _to(batch: Sequence[Any], device: torch.device) -> tuple[Any, ...]:
    return tuple(b.to(device) if isinstance(b, torch.Tensor) else b for b in batch)


def scored_samples(out: Mapping[str, torch.Tensor]) -> Scored:
    """A batch's scored samples as :func:`compare_baselines` takes them, from what
    ``InverseHysteresisModule.scored_outputs`` (and ``test_step``) returns: input, target and
    prediction flat, conditions or None, on the CPU in float64."""
    def cpu(t: torch.Tensor) -> torch.Tensor:
        return t.detach().to("cpu", torch.float64)

    c = out.get("conditions")
    return (cpu(out["input"]).reshape(-1), cpu(out["target"]).reshape(-1),
            cpu(out["prediction"]).reshape(-1), None if c is None else cpu(c))


def _condition_rows(batches: Sequence[Any], T: int) -> torch.Tensor:
    """The conditions (rows, T, n) of every batch's rows as :func:`_rows` pads them."""
    def pad(c: torch.Tensor) -> torch.Tensor:
        c = c.detach().to("cpu", torch.float64)
        return torch.cat([c, c[:, -1:].expand(-1, T - c.shape[1], -1)], 1)

    return torch.cat([pad(b[4]) for b in batches])


def _rows(batches: Sequence[Any]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The rows of every ``(x, y, warmup, mask[, conditions])`` batch as one ``(x, y,
    mask)``, each row padded at its end to the longest (padding not scored)."""
    T = max(int(b[0].shape[-1]) for b in batches)

    def pad(t: torch.Tensor, value: float | bool) -> torch.Tensor:
        t = t.detach().to("cpu").reshape(-1, t.shape[-1])
        return torch.nn.functional.pad(t, (0, T - t.shape[-1]), value=value)

    x = torch.cat([pad(b[0].double(), 0.0) for b in batches])
    y = torch.cat([pad(b[1].double(), 0.0) for b in batches])
    mask = torch.cat([pad(b[3].bool(), False) for b in batches])
    return x, y, mask
