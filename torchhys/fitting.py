"""Fitting: full-batch training of inverse-hysteresis networks (Adam, then L-BFGS), and the
least-squares identification of Prandtl-Ishlinskii models (a causal inverse model of a
hysteretic plant, or a feature for the network)."""

from __future__ import annotations

import math
import time
from typing import NamedTuple

import torch
from torch import Tensor

from torchhys._checks import as_batched_sequence, check_int, check_same_shape, check_widths
from torchhys.functional.backlash import backlash
from torchhys.networks import InverseHysteresisNet
from torchhys.prandtl_ishlinskii import PrandtlIshlinskii

__all__ = ["FitResult", "fit_full_batch", "fit_prandtl_ishlinskii", "play_width_grid"]


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
        n_iter = lbfgs.state[params[0]].get("n_iter", 0)
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


def play_width_grid(u: Tensor, n: int = 30, *, power: float = 3.0) -> Tensor:
    """Dead-band widths ``span(u) (k / n)^power``, ``k = 1..n``, for a model of input ``u``.

    The inverse of a Prandtl-Ishlinskii plant is a Prandtl-Ishlinskii model of the plant's
    output whose loading curve bends most right after a reversal (its thresholds
    ``r'_j = sum_{i<=j} w_i (r_j - r_i)`` grow quadratically for evenly spaced plant widths,
    and a plant without a linear term makes the inverse jump at every reversal). A grid
    dense at small widths (``power=3``) covers both: its smallest width (``span / n^3``)
    acts as a direction-of-motion feature, its largest is the span of ``u``.

    Args:
        u: the model's input, (time,) or (batch, time) (only its range is used).
        n: number of widths, >= 1.
        power: grid exponent, > 0 (1: evenly spaced).

    Returns:
        Full widths, shape (n,), increasing, dtype of ``u``.

    Raises:
        TypeError, ValueError: bad ``u``, ``n`` or ``power``; a constant ``u``.
    """
    ub, _ = as_batched_sequence(u, "u")
    check_int(n, "n", minimum=1)
    if not (isinstance(power, (int, float)) and math.isfinite(power) and power > 0):
        raise ValueError(f"power must be a positive number, got {power!r}")
    span = (ub.max() - ub.min()).detach()
    if float(span) == 0.0:
        raise ValueError("u is constant: its span gives no scale for the widths")
    k = torch.arange(1, n + 1, dtype=ub.dtype, device=ub.device)
    return span * (k / n) ** power


def fit_prandtl_ishlinskii(
    u: Tensor, y: Tensor, widths: Tensor, *, ridge: float = 0.0, learnable: bool = False,
    warmup: int = 0,
) -> PrandtlIshlinskii:
    """Least-squares Prandtl-Ishlinskii model ``y ~ w0 u + sum_i w_i play_{d_i}[u]``.

    With the widths fixed the output is linear in the weights, so they solve a linear
    least-squares problem (the classical identification of a PI model). Fitted from the
    plant's output ``u = h`` to its input ``y = x`` it is a causal inverse model of the
    plant: the exact inverse of an invertible PI plant when ``widths`` holds its inverse
    thresholds (:func:`~torchhys.functional.prandtl_ishlinskii_inverse_parameters`), and a
    strong one from a dense :func:`play_width_grid` otherwise. Use it as a compensator, or as
    an operator of :class:`~torchhys.InverseHysteresisNet` (the network then models the
    residual). Play states start at zero at the first sample, as in the returned model;
    ``warmup`` leaves the first samples out of the fit only (the states still run through
    them), e.g. while the states forget their zero start.

    Args:
        u: model input, (time,) or (batch, time) (rows are independent records).
        y: target, same shape.
        widths: full dead-band widths d_i >= 0, shape (N,).
        ridge: Tikhonov weight: minimizes ``mean(residual^2) + ridge * |w|^2`` (w without
            ``w0``), >= 0.
        learnable: return a model with trainable widths and weights.
        warmup: leading samples of each row left out of the least-squares fit,
            ``0 <= warmup < time``.

    Returns:
        :class:`~torchhys.PrandtlIshlinskii` in the dtype of ``u`` (detached parameters).

    Raises:
        TypeError, ValueError: bad or mismatched ``u``, ``y``, ``widths``, ``ridge``,
            ``warmup``.

    References:
        K. Kuhnen, "Modeling, identification and compensation of complex hysteretic
        nonlinearities: a modified Prandtl-Ishlinskii approach", European Journal of
        Control 9(4), 2003.
    """
    ub, _ = as_batched_sequence(u, "u")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, ub, "y", "u")
    check_widths(widths, "widths")
    if not (isinstance(ridge, (int, float)) and math.isfinite(ridge) and ridge >= 0):
        raise ValueError(f"ridge must be a finite number >= 0, got {ridge!r}")
    check_int(warmup, "warmup", minimum=0)
    if warmup >= ub.shape[1]:
        raise ValueError(
            f"warmup must leave samples to fit: warmup={warmup} of {ub.shape[1]} samples"
        )
    with torch.no_grad():
        ub64, yb64 = ub.detach().double().cpu(), yb.detach().double().cpu()
        plays = backlash(ub64, widths.detach().double().cpu())  # run through the warm-up
        design = torch.cat([ub64.unsqueeze(-1), plays], dim=-1)[:, warmup:]
        design = design.reshape(-1, widths.shape[0] + 1)
        n = design.shape[0]
        target = yb64[:, warmup:].reshape(-1, 1)
        if ridge > 0:
            penalty = torch.eye(widths.shape[0] + 1, dtype=torch.float64)[1:] * math.sqrt(ridge)
            design = torch.cat([design / math.sqrt(n), penalty])
            target = torch.cat([target / math.sqrt(n), target.new_zeros(widths.shape[0], 1)])
        w = torch.linalg.lstsq(design, target, driver="gelsd").solution[:, 0]  # rank-revealing
    model = PrandtlIshlinskii(
        widths.detach().to(ub.dtype), w[1:].to(ub.dtype), linear_weight=float(w[0]),
        learnable=learnable,
    )
    return model.to(ub.device)
