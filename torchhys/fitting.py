"""Full-batch training of inverse-hysteresis networks (Adam, then L-BFGS)."""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import torch
from torch import Tensor

from torchhys.networks import InverseHysteresisNet

__all__ = ["FitResult", "fit_full_batch"]


class FitResult(NamedTuple):
    """Outcome of :func:`fit_full_batch`."""

    mse: float
    """Final training MSE (physical units)."""
    epochs: int
    """Optimizer iterations: Adam steps plus L-BFGS iterations."""
    seconds: float
    """Wall-clock training time."""


def fit_full_batch(
    model: InverseHysteresisNet, x: Tensor, y: Tensor, *, adam_epochs: int = 2000,
    lbfgs_epochs: int = 500, lr: float = 1e-2, tolerance: float = 0.0,
) -> FitResult:
    """Fit ``model`` to (x, y) with full-batch Adam then L-BFGS (strong Wolfe line search).

    Normalization is fitted first. When the elementary operators have no trainable
    parameters their outputs are computed once and only the network is trained. ``y`` is
    passed as ``target`` (used only by per-segment, non-causal EIHOs).

    Args:
        model: the network.
        x: input, (time,) or (batch, time).
        y: target, same shape.
        adam_epochs: Adam steps.
        lbfgs_epochs: L-BFGS iterations.
        lr: Adam learning rate.
        tolerance: stop L-BFGS once the MSE is below this value.

    Returns:
        :class:`FitResult`.
    """
    start = time.perf_counter()
    model.fit_normalization(x, y)
    trainable_ops = any(p.requires_grad for p in model.operators.parameters())
    yb = y.reshape(-1, y.shape[-1])
    if not trainable_ops:
        with torch.no_grad():
            feats, _ = model.features(x, target=y)

        def loss_fn() -> Tensor:
            return torch.mean((model.head(feats) - yb) ** 2)
    else:

        def loss_fn() -> Tensor:
            return torch.mean((model(x.reshape(yb.shape), target=yb)[0] - yb) ** 2)

    params = [p for p in model.parameters() if p.requires_grad]
    adam = torch.optim.Adam(params, lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(adam, max(adam_epochs, 1))
    for _ in range(adam_epochs):
        adam.zero_grad()
        loss = loss_fn()
        loss.backward()
        adam.step()
        sched.step()
    lbfgs = torch.optim.LBFGS(
        params, lr=1.0, max_iter=20, history_size=50, line_search_fn="strong_wolfe",
        tolerance_grad=1e-12, tolerance_change=1e-15,
    )

    def closure() -> Tensor:
        lbfgs.zero_grad()
        loss = loss_fn()
        loss.backward()
        return loss

    done = 0
    while done < lbfgs_epochs:
        lbfgs.step(closure)
        n_iter = lbfgs.state[lbfgs._params[0]].get("n_iter", 0)
        if n_iter <= done:
            break
        done = n_iter
        with torch.no_grad():
            if float(loss_fn()) < tolerance:
                break
    with torch.no_grad():
        mse = float(loss_fn())
    if not math.isfinite(mse):
        raise FloatingPointError(f"training diverged: final MSE {mse}")
    return FitResult(mse, adam_epochs + done, time.perf_counter() - start)
