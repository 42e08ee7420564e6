"""What every model family's fit checks (the families of
:mod:`torchhys.identification.specs`): its scored and known samples, the standardized target,
its RMS error, and that it beats a straight line on its training samples (else
:class:`FitError`, which model selection scores as failed)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchhys._checks import fitted_samples

__all__ = ["ON_THE_LINE", "FitError", "NoBetterThanLine"]


class FitError(ValueError):
    """A model family that cannot be fitted to these data (model selection skips it)."""


class NoBetterThanLine(FitError):
    """A fit no better than a straight line on its training samples (standardized RMS
    errors ``rmse`` and ``line``)."""

    def __init__(self, message: str, rmse: float, line: float) -> None:
        super().__init__(message)
        self.rmse, self.line = rmse, line

    @property
    def on_the_line(self) -> bool:
        """Whether the fit ended on the line itself (RMS error within
        :data:`ON_THE_LINE` of it, relative): its nonlinear part found nothing to fit."""
        return self.rmse <= self.line * (1.0 + ON_THE_LINE)


ON_THE_LINE = 1e-3
"""How close to the straight line's RMS error (relative) a failed fit ends "on the line"
(:attr:`NoBetterThanLine.on_the_line`): a ``gpi`` fit that does is not started again from
the next ridge's PI fit."""


def _samples(x: Tensor, warmup: int, mask: Tensor | None) -> tuple[Tensor, Tensor]:
    """The scored samples (in ``mask``, after the warm-up) and the known ones (in ``mask``,
    the warm-up's too), (rows, time) bool each; ``mask`` None: every sample."""
    known = fitted_samples(mask, (x.shape[0], x.shape[1]), 0).to(x.device)
    scored = known.clone()
    scored[:, :warmup] = False
    if not bool(scored.any()):
        raise FitError(f"no scored training sample (warmup {warmup}, {int(known.sum())} "
                       "samples in the mask)")
    return scored, known


def _standardized(x: Tensor, y: Tensor, scored: Tensor) -> tuple[float, Tensor]:
    """The input's scale (std of the scored samples) and the standardized target."""
    xs, ys = x[scored], y[scored]
    sx, sy = float(xs.std()), float(ys.std())
    if not (sx > 0 and sy > 0):
        raise FitError("the input and the target must vary over the scored training samples")
    return sx, (y - ys.mean()) / sy


def _rmse(model: nn.Module, x: Tensor, t: Tensor, scored: Tensor, mean: float = 0.0,
          std: float = 1.0) -> float:
    """RMSE of ``(model(x) - mean) / std`` against t on the scored samples."""
    with torch.no_grad():
        return float(((model(x)[0] - mean) / std - t)[scored].square().mean().sqrt())


def _checked(model: nn.Module, x: Tensor, t: Tensor, scored: Tensor, name: str,
             mean: float = 0.0, std: float = 1.0, rmse: float | None = None) -> nn.Module:
    """``model`` if it fits the standardized target t on the scored training samples better
    than a straight line in x does, else :class:`FitError` (a diverged or degenerate fit;
    an exact inverse of a poor forward fit can blow up). A model of the physical target
    gives the target's ``mean`` and ``std``: its output is standardized as t was. ``rmse``:
    the model's :func:`_rmse` when the caller has it already (not computed again)."""
    if rmse is None:
        rmse = _rmse(model, x, t, scored, mean, std)
    xs, ts = x[scored], t[scored]
    design = torch.stack([xs, torch.ones_like(xs)], 1)
    line = float((design @ torch.linalg.lstsq(design, ts[:, None]).solution - ts[:, None])
                 .square().mean().sqrt())
    if not rmse < line:
        raise NoBetterThanLine(f"{name}: the fitted model is no better than a straight line on "
                               f"the training samples (standardized RMSE {rmse:.3g}, line "
                               f"{line:.3g})", rmse, line)
    return model
