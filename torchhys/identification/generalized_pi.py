"""Identification of the generalized Prandtl-Ishlinskii model: :func:`fit_generalized_pi`
(a least-squares PI start, then full-batch training of the output function)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from torchhys._checks import (
    as_batched_sequence,
    check_int,
    check_penalty,
    check_same_shape,
    fitted_samples,
)
from torchhys.identification.fitting import fit_full_batch, fit_prandtl_ishlinskii
from torchhys.operators.backlash import _inverse_softplus
from torchhys.operators.generalized_pi import GeneralizedPrandtlIshlinskii

__all__ = ["fit_generalized_pi"]


def fit_generalized_pi(
    x: Tensor, y: Tensor, widths: Tensor, *, units: int = 6, ridge: float = 0.0,
    adam_epochs: int = 0, lbfgs_epochs: int = 1000, lr: float = 1e-2, warmup: int = 0,
    anchor: float = 1e-6, mask: Tensor | None = None,
) -> GeneralizedPrandtlIshlinskii:
    """Fit a :class:`GeneralizedPrandtlIshlinskii` model ``y ~ g(p[x])``.

    Initialisation: ``p`` from the non-negative PI fit
    (``fit_prandtl_ishlinskii(x, y, widths, ridge=ridge, nonnegative=True)``), its play
    weights raised to at least 1% of the largest (so that none starts dead); ``g`` with
    ``units`` tanh units centered on quantiles of that fit's output, slopes ``2 / spacing``
    and weights ``0.1 spacing`` (spacing: the output's span / units), gain 1, offset 0. Then
    full-batch training of every parameter but the widths and ``w0`` on the mean squared error plus
    ``anchor * (|log a - log a_init|^2 + |log s - log s_init|^2)``
    (:func:`~torchhys.identification.fitting.fit_full_batch`: Adam, then L-BFGS). The fit sees y
    divided by its standard deviation over the scored samples (then ``a``, ``c_k`` and the offset
    are scaled back), so that the fit, its tolerances and the anchor mean the same in any units of
    y.

    Why ``w0`` is held and the logarithms anchored: the model is unchanged when ``p`` is
    scaled by k and ``g``'s input by 1 / k (``w, w0, b`` times k, ``a, s`` over k), and
    nearly unchanged when a unit's slope shrinks while its weight grows (it becomes a
    linear term) or when the gain vanishes and the units carry ``g``. Left free, the fit
    drifts along these directions until parameters underflow (a gain or slope of 0: no
    inverse) or the loss turns NaN; holding ``w0`` removes the first, and the anchor (small
    next to the error of a fit) stops the others.

    Args:
        x: input, (time,) or (batch, time); y: output, same shape.
        widths: full dead-band widths, (N,).
        units: tanh units of g, >= 0.
        ridge: ridge weight of the initial PI fit (e.g. from
            :func:`~torchhys.identification.fitting.select_pi_ridge`).
        adam_epochs, lbfgs_epochs, lr: as in
        :func:`~torchhys.identification.fitting.fit_full_batch`.
        warmup: samples at the start of each row left out of the initial fit, the centers of
            g and the loss (they still run the plays), to forget the zero initial state.
        anchor: weight of the penalty on the log-gain and log-slopes moving from their
            initial values (y in units of its standard deviation), >= 0 (0: none).
        mask: the scored samples, bool, the shape of ``x`` (False: left out of the initial
            fit, the centers, the scale of y and the loss, as the warm-up; the plays still run
            through them, e.g. a held-out block or a shorter row's padding); None: every
            sample (after ``warmup`` in both cases).

    Returns:
        The model, in x's dtype.

    Raises:
        TypeError, ValueError: bad input (see
        :func:`~torchhys.identification.fitting.fit_prandtl_ishlinskii`),
            y constant over the scored samples, or y that does not increase with x (the
            initial fit has no positive linear weight).
    """
    check_int(units, "units", minimum=0)
    anchor = check_penalty(anchor, "anchor")
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, xb, "y", "x")
    pi = fit_prandtl_ishlinskii(xb, yb, widths, ridge=ridge, nonnegative=True, warmup=warmup,
                                mask=mask)
    scored = fitted_samples(mask, tuple(xb.shape), warmup).to(xb.device)
    sy = float(yb[scored].std())
    if not sy > 0:
        raise ValueError("y must vary over the scored samples (after warmup)")
    w0 = float(pi.linear_weight) / sy
    if not w0 > 0:
        raise ValueError("y does not increase with x (the least-squares static gain is not "
                         "positive): a generalized PI model of increasing loops does not fit")
    with torch.no_grad():
        v = pi(xb)[0][scored] / sy
        q = (torch.arange(units, dtype=v.dtype, device=v.device) + 0.5) / max(units, 1)
        centers = torch.quantile(v, q) if units else v.new_zeros(0)
        spacing = float((v.max() - v.min()).clamp_min(1e-12)) / max(units, 1)
        weights = pi.weights.clamp_min(0.01 * float(pi.weights.max())) / sy
    model = GeneralizedPrandtlIshlinskii(
        pi.get_widths(), weights, linear_weight=w0, centers=centers,
        slopes=torch.full_like(centers, 2.0 / spacing),
        unit_weights=torch.full_like(centers, 0.1 * spacing),
    ).to(xb.device)
    log_gain, log_slopes = model.log_gain.detach().clone(), model.log_slopes.detach().clone()

    def drift() -> Tensor:
        return anchor * ((model.log_gain - log_gain).square()
                         + (model.log_slopes - log_slopes).square().sum())

    model.log_linear_weight.requires_grad_(False)
    try:
        fit_full_batch(model, xb, yb / sy, adam_epochs=adam_epochs, lbfgs_epochs=lbfgs_epochs,
                       lr=lr, warmup=warmup, penalty=drift if anchor > 0 else None,
                       mask=mask)
    finally:
        model.log_linear_weight.requires_grad_(True)
    with torch.no_grad():  # g's output back to the units of y
        model.log_gain.add_(math.log(sy))
        model.raw_unit_weights.copy_(_inverse_softplus(F.softplus(model.raw_unit_weights) * sy))
        model.offset.mul_(sy)
    return model
