"""Fitting: full-batch training of inverse-hysteresis networks and sequence models (Adam,
then L-BFGS), and the
least-squares identification of Prandtl-Ishlinskii models (a causal inverse model of a
hysteretic plant, or a feature for the network)."""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchhys._checks import (
    as_batched_sequence,
    check_bool,
    check_int,
    check_nonnegative,
    check_positive,
    check_same_shape,
    check_warmup,
    check_widths,
    fitted_samples,
)
from torchhys.functional.backlash import backlash
from torchhys.identification._nnls import (
    check_validation,
    fit_segments,
    moments,
    nnls_gram,
    select_on_holdout,
)
from torchhys.networks import InverseHysteresisNet
from torchhys.operator import HysteresisOperator, check_operator
from torchhys.operators.prandtl_ishlinskii import PrandtlIshlinskii
from torchhys.protocols import SequenceModel

__all__ = [
    "FitResult", "LINEAR_FLOOR", "fit_full_batch", "fit_prandtl_ishlinskii", "play_width_grid",
    "select_pi_ridge",
]


class FitResult(NamedTuple):
    """Outcome of :func:`fit_full_batch`."""

    mse: float
    """Final training MSE (physical units)."""
    epochs: int
    """Optimizer iterations: Adam steps plus L-BFGS iterations."""
    seconds: float
    """Wall-clock training time."""


def fit_full_batch(
    model: InverseHysteresisNet | HysteresisOperator | SequenceModel, x: Tensor, y: Tensor, *,
    adam_epochs: int = 2000, lbfgs_epochs: int = 500, lr: float = 1e-2, tolerance: float = 0.0,
    warmup: int = 0, penalty: Callable[[], Tensor] | None = None, mask: Tensor | None = None,
) -> FitResult:
    """Fit ``model`` to (x, y) with full-batch Adam then L-BFGS (strong Wolfe line search).

    A network's normalization is fitted first. When its elementary operators have no
    trainable parameters their outputs are computed once and only the network is trained.
    ``y`` is passed as ``target`` (used only by per-segment, non-causal EIHOs). An operator
    with one output (e.g. :class:`~torchhys.operators.generalized_pi.GeneralizedPrandtlIshlinskii`)
    is fitted as a model of ``y`` itself: the loss is ``mean((op(x) - y)^2)``, computed through
    ``op.mse_closure(x, y, samples)`` (:meth:`torchhys.HysteresisOperator.mse_closure`: a
    faster closure of the loss on this fixed input where the operator has one, e.g.
    :meth:`~torchhys.GeneralizedPrandtlIshlinskii.mse_closure`). A
    :class:`~torchhys.protocols.SequenceModel` (a :class:`~torchhys.compose.Composed`: a
    user's module through :func:`~torchhys.compose.compose`) records its ranges on (x, y)
    first (``record_ranges``, over ``mask``), then its output ``model(x)`` is fitted to
    ``y``, end to end.

    Args:
        model: the network, a causal operator with ``n_outputs == 1``, or a sequence model.
        x: input, (time,) or (batch, time).
        y: target, same shape.
        adam_epochs: Adam steps.
        lbfgs_epochs: L-BFGS iterations, run as whole ``LBFGS.step`` calls of 20, so
            rounded up to a multiple of 20; fewer when L-BFGS converges or the MSE falls
            below ``tolerance``.
        lr: Adam learning rate.
        tolerance: stop L-BFGS once the MSE is below this value.
        warmup: samples at the start of each row left out of the loss (they still run the
            states), ``0 <= warmup < time``.
        penalty: a term added to the loss (a 0-dim tensor of the model's parameters), or
            None. :class:`FitResult` reports the mean squared error without it.
        mask: the samples in the loss (and in a network's normalization), bool, the shape
            of ``y`` (False: left out, the states still run through them); None: every
            sample (after ``warmup`` in both cases).

    Returns:
        :class:`FitResult`.

    Raises:
        TypeError, ValueError: a model that is none of these, an operator with several
            outputs or one that needs the target, a sequence model whose output is not of
            y's shape; a warmup out of range, a bad mask.
    """
    start = time.perf_counter()
    check_int(adam_epochs, "adam_epochs", minimum=0)
    check_int(lbfgs_epochs, "lbfgs_epochs", minimum=0)
    check_warmup(warmup, x.shape[-1])
    if mask is not None:
        rows = x.shape[0] if x.dim() == 2 else 1
        mask = fitted_samples(mask, (rows, x.shape[-1]), warmup).to(x.device)
    if isinstance(model, InverseHysteresisNet):
        loss_fn = _network_loss(model, x, y, warmup, mask)
    elif isinstance(model, SequenceModel) and not isinstance(model, HysteresisOperator):
        loss_fn = _sequence_loss(model, x, y, warmup, mask)
    elif not isinstance(model, HysteresisOperator):
        raise TypeError(f"model must be an InverseHysteresisNet, a torchhys.HysteresisOperator "
                        f"or a torchhys.protocols.SequenceModel (a user's module through "
                        f"torchhys.compose.compose), got {type(model).__name__}")
    else:
        loss_fn = _operator_loss(model, x, y, warmup, mask)
    objective = loss_fn if penalty is None else (lambda: loss_fn() + penalty())
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise ValueError(f"model {type(model).__name__} has no trainable parameters")
    adam = torch.optim.Adam(params, lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(adam, max(adam_epochs, 1))
    for _ in range(adam_epochs):
        adam.zero_grad()
        loss = objective()
        loss.backward()
        adam.step()
        sched.step()
    lbfgs = torch.optim.LBFGS(
        params, lr=1.0, max_iter=20, history_size=50, line_search_fn="strong_wolfe",
        tolerance_grad=1e-12, tolerance_change=1e-15,
    )

    def closure() -> Tensor:
        lbfgs.zero_grad()
        loss = objective()
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


def _mse(error: Tensor, warmup: int, mask: Tensor | None) -> Tensor:
    """Mean square of ``error`` (rows, time) over the samples from ``warmup`` on, or over
    those of ``mask`` (already combined with ``warmup``)."""
    return torch.mean(error[:, warmup:] ** 2) if mask is None else torch.mean(error[mask] ** 2)


def _network_loss(model: InverseHysteresisNet, x: Tensor, y: Tensor, warmup: int,
                  mask: Tensor | None) -> Callable[[], Tensor]:
    model.fit_normalization(x, y, mask=mask)
    trainable_ops = any(p.requires_grad for p in model.operators.parameters())
    yb = y.reshape(-1, y.shape[-1])
    if not trainable_ops:
        with torch.no_grad():
            feats, _ = model.features(x, target=y)
        return lambda: _mse(model.head(feats).reshape(yb.shape) - yb, warmup, mask)
    return lambda: _mse(model(x.reshape(yb.shape), target=yb)[0] - yb, warmup, mask)


def _sequence_loss(model: SequenceModel, x: Tensor, y: Tensor, warmup: int,
                   mask: Tensor | None) -> Callable[[], Tensor]:
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, xb, "y", "x")
    model.record_ranges(xb, yb, mask=mask)
    with torch.no_grad():
        out = model(xb)
    if not isinstance(out, Tensor) or out.shape != yb.shape:
        got = tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__
        raise ValueError(f"model {type(model).__name__} must map x (batch, time) to y (batch, "
                         f"time): its output for x {tuple(xb.shape)} is {got}")
    return lambda: _mse(model(xb) - yb, warmup, mask)


def _operator_loss(op: object, x: Tensor, y: Tensor, warmup: int,
                   mask: Tensor | None) -> Callable[[], Tensor]:
    op = check_operator(op, "model")
    if op.n_outputs != 1 or not op.causal:
        raise ValueError(f"model must be an InverseHysteresisNet or a causal operator with one "
                         f"output, got {type(op).__name__} with n_outputs={op.n_outputs}, "
                         f"causal={op.causal}")
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, xb, "y", "x")
    # a faster closure where the operator has one (the class's method: a submodule that
    # happens to be called `mse_closure` does not shadow it)
    samples = fitted_samples(mask, (xb.shape[0], xb.shape[1]), warmup).to(xb.device)
    return type(op).mse_closure(op, xb, yb, samples)


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
    power = check_positive(power, "power")
    span = (ub.max() - ub.min()).detach()
    if float(span) == 0.0:
        raise ValueError("u is constant: its span gives no scale for the widths")
    k = torch.arange(1, n + 1, dtype=ub.dtype, device=ub.device)
    return span * (k / n) ** power


def fit_prandtl_ishlinskii(
    u: Tensor, y: Tensor, widths: Tensor, *, ridge: float = 0.0, learnable: bool = False,
    warmup: int = 0, nonnegative: bool = False, mask: Tensor | None = None,
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

    ``nonnegative=True`` constrains the play weights to ``w_i >= 0`` and the linear weight to
    ``w0 >= LINEAR_FLOOR * max(g, 0)``, ``g = cov(u, y) / var(u)`` the least-squares static
    gain over the fitted samples (``LINEAR_FLOOR = 1e-3``). Every branch of the model then
    rises with slope ``>= w0 > 0``: it is monotone and has an exact inverse
    (:meth:`~torchhys.PrandtlIshlinskii.inverse`), which an unconstrained fit need not have.
    (With ``g <= 0`` the floor is 0 and the model may not be invertible.) It is solved by
    the Lawson-Hanson method on the normal equations of the ridge-augmented design
    ``[A / sqrt(n); sqrt(ridge) [0 I]]`` (float64), with ``w0 - floor`` as the variable.

    Args:
        u: model input, (time,) or (batch, time) (rows are independent records).
        y: target, same shape.
        widths: full dead-band widths d_i >= 0, shape (N,).
        ridge: Tikhonov weight: minimizes ``mean(residual^2) + ridge * |w|^2`` (w without
            ``w0``), >= 0; choose it with :func:`select_pi_ridge`.
        learnable: return a model with trainable widths and weights.
        warmup: leading samples of each row left out of the least-squares fit,
            ``0 <= warmup < time``.
        nonnegative: constrain the weights as above (a monotone, invertible model).
        mask: the samples to fit, bool, the shape of ``u`` (False: left out of the fit, the
            plays still run through them, e.g. a held-out block or a shorter row's
            padding); None: every sample (after ``warmup`` in both cases).

    Returns:
        :class:`~torchhys.PrandtlIshlinskii` in the dtype of ``u`` (detached parameters;
        with ``nonnegative=True`` a ``nonnegative`` model, which refuses negative weights
        from a state dict).

    Raises:
        TypeError, ValueError: bad or mismatched ``u``, ``y``, ``widths``, ``ridge``,
            ``warmup``.

    References:
        K. Kuhnen, "Modeling, identification and compensation of complex hysteretic
        nonlinearities: a modified Prandtl-Ishlinskii approach", European Journal of
        Control 9(4), 2003; C. L. Lawson and R. J. Hanson, Solving Least Squares Problems,
        1995, Ch. 23.
    """
    ub, yb = _check_pi_data(u, y, widths, warmup)
    ridge = check_nonnegative(ridge, "ridge")
    check_bool(nonnegative, "nonnegative")
    (A, target), = _pi_segments(ub, yb, widths, [fitted_samples(mask, ub.shape, warmup)])
    if nonnegative:
        m = moments(A, target)
        floor = _linear_floor(A[:, 0], target)
        w = _pi_solve(m.gram / m.count, m.moment / m.count, ridge, True, floor)
    else:
        w = _pi_lstsq(A, target, ridge)
    _warn_below_line(A, target, w)
    model = PrandtlIshlinskii(
        widths.detach().to(ub.dtype), w[1:].to(ub.dtype), linear_weight=float(w[0]),
        learnable=learnable, nonnegative=nonnegative,
    )
    return model.to(ub.device)


def _warn_below_line(A: Tensor, target: Tensor, w: Tensor) -> None:
    """Warn (one line) when the PI fit ``A w`` is no better than a straight line with an
    intercept on the fitted samples: a PI model has no intercept, so data far from zero
    (a response of -123 to -74 um) cannot be fitted without centring."""
    A64, t64 = A.double(), target.double()
    rmse = float((A64 @ w.double().reshape(-1, 1) - t64.reshape(-1, 1)).square().mean().sqrt())
    design = torch.stack([A64[:, 0], torch.ones_like(A64[:, 0])], 1)
    line = float((design @ torch.linalg.lstsq(design, t64.reshape(-1, 1)).solution
                  - t64.reshape(-1, 1)).square().mean().sqrt())
    exact = rmse <= 1e-9 * max(float(t64.abs().max()), 1e-300)  # a fit to rounding
    if not (rmse < line or exact):
        warnings.warn(f"fit_prandtl_ishlinskii: the fitted model (RMSE {rmse:.4g}) is no "
                      f"better than a straight line with an intercept (RMSE {line:.4g}) on the "
                      "fitted samples: a PI model has no intercept; centre u and y (subtract "
                      "their means), or use torchhys.Compensator.fit, which adds one",
                      UserWarning, stacklevel=3)


def select_pi_ridge(
    u: Tensor, y: Tensor, widths: Tensor, ridges: Sequence[float], *,
    nonnegative: bool = False, validation: float = 0.25, warmup: int = 0,
    mask: Tensor | None = None,
) -> tuple[float, dict[float, float]]:
    """Choose the ``ridge`` of :func:`fit_prandtl_ishlinskii` on a time-ordered hold-out.

    Each candidate is fitted on the first ``1 - validation`` of every row (after
    ``warmup``) and scored by the RMS error on the rest; the play states run through the
    whole sequence. The same scoring as :func:`torchhys.select_penalty` (Preisach), from the
    normal equations of the two parts. The held-out samples never enter a fit (nor the
    ``nonnegative`` floor of the linear weight).

    Args:
        u, y, widths, warmup, nonnegative, mask: as in :func:`fit_prandtl_ishlinskii`.
        ridges: candidate ridge weights (each >= 0), at least one.
        validation: share of the samples of each row held out at its end, in (0, 1) (with
            a ``mask``: of its masked samples).

    Returns:
        The ridge with the least hold-out RMS error (the first on ties), and the RMS error
        of each. Refit on all samples with ``fit_prandtl_ishlinskii(..., ridge=best)``.

    Raises:
        TypeError, ValueError: bad arguments, or no training sample before the split.
    """
    ub, yb = _check_pi_data(u, y, widths, warmup)
    segments = fit_segments(ub.shape, warmup, mask, check_validation(validation))
    (A, t), (Av, tv) = _pi_segments(ub, yb, widths, segments)
    nonnegative = check_bool(nonnegative, "nonnegative")
    floor = _linear_floor(A[:, 0], t) if nonnegative else 0.0

    def solve(G: Tensor, h: Tensor, ridge: float) -> Tensor:
        return _pi_solve(G, h, ridge, nonnegative, floor)

    return select_on_holdout(moments(A, t), moments(Av, tv), ridges, solve, name="ridges")


LINEAR_FLOOR = 1e-3
"""Least linear weight of a ``nonnegative`` PI fit, as a share of the static gain."""


def _check_pi_data(u: Tensor, y: Tensor, widths: Tensor, warmup: int) -> tuple[Tensor, Tensor]:
    ub, _ = as_batched_sequence(u, "u")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, ub, "y", "u")
    check_widths(widths, "widths")
    check_warmup(warmup, ub.shape[1])
    return ub, yb


def _pi_segments(u: Tensor, y: Tensor, widths: Tensor,
                 segments: list[Tensor]) -> list[tuple[Tensor, Tensor]]:
    """Design ``[u, plays]`` (rows, N + 1) and target (rows,), float64 on the CPU, of the
    samples of each segment (a (batch, time) bool mask; the plays run from 0)."""
    with torch.no_grad():
        u64, y64 = u.detach().double().cpu(), y.detach().double().cpu()
        plays = backlash(u64, widths.detach().double().cpu())
        design = torch.cat([u64.unsqueeze(-1), plays], dim=-1)
        return [(design[m], y64[m]) for m in segments]


def _pi_lstsq(A: Tensor, target: Tensor, ridge: float) -> Tensor:
    """Unconstrained ridge least squares on the augmented design (rank-revealing gelsd)."""
    n, m = A.shape
    t = target[:, None]
    if ridge > 0:
        penalty = torch.eye(m, dtype=torch.float64)[1:] * math.sqrt(ridge)
        A = torch.cat([A / math.sqrt(n), penalty])
        t = torch.cat([t / math.sqrt(n), t.new_zeros(m - 1, 1)])
    return torch.linalg.lstsq(A, t, driver="gelsd").solution[:, 0]


def _linear_floor(u: Tensor, y: Tensor) -> float:
    """``LINEAR_FLOOR * max(cov(u, y) / var(u), 0)`` over the fitted samples u, y (rows,)."""
    du, dy = u - u.mean(), y - y.mean()
    var = float(du @ du)
    return LINEAR_FLOOR * max(float(du @ dy) / var, 0.0) if var > 0 else 0.0


def _pi_solve(G: Tensor, h: Tensor, ridge: float, nonnegative: bool, floor: float) -> Tensor:
    """Weights ``[w0, w_1..w_N]`` from the per-sample normal equations plus the ridge."""
    P = G + ridge * torch.diag(torch.cat([G.new_zeros(1), G.new_ones(G.shape[0] - 1)]))
    if not nonnegative:
        return torch.linalg.lstsq(P, h[:, None], driver="gelsd").solution[:, 0]
    w = nnls_gram(P, h - floor * G[:, 0], torch.zeros(h.shape, dtype=torch.bool))
    w[0] += floor
    return w
