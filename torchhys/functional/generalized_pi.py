"""The memoryless output function of the generalized Prandtl-Ishlinskii model and its inverse.

``g(v) = a v + sum_k c_k tanh(s_k (v - b_k)) + offset`` with ``a > 0``, ``c_k >= 0``,
``s_k > 0`` is strictly increasing (:func:`monotone_output`, its slope
:func:`monotone_slope`); :func:`monotone_inverse` solves ``g(v) = y`` by bisection on a
bracket, then Newton steps. Pure tensor functions, scriptable.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchhys.functional._compile import call_function, signature_once

__all__ = ["BISECTIONS", "NEWTON", "monotone_inverse", "monotone_mse", "monotone_output",
           "monotone_slope"]


def monotone_output(v: Tensor, gain: Tensor, unit_weights: Tensor, centers: Tensor,
                    slopes: Tensor, offset: Tensor) -> Tensor:
    """``g(v) = gain v + sum_k c_k tanh(s_k (v - b_k)) + offset``: v (...) -> (...).

    ``gain``, ``offset``: 0-dim; ``unit_weights`` (c), ``centers`` (b), ``slopes`` (s):
    (K,), K >= 0. Strictly increasing when ``gain > 0``, ``c >= 0``, ``s > 0``. With
    ``c = 0`` (or K = 0), ``gain = 1``, ``offset = 0`` it returns v exactly. Scriptable: the
    sequence path and the step call it.
    """
    units = torch.tanh(slopes * (v.unsqueeze(-1) - centers))
    return gain * v + (units * unit_weights).sum(-1) + offset


BISECTIONS = 20
"""Halvings of the bracket of ``g^-1`` (its width shrinks by 2^-20), before the Newton
steps."""


NEWTON = 2
"""Newton steps from the bisection's midpoint, each kept inside the final bracket
(quadratic convergence: from 2^-20 of the bracket to float64's resolution), before the last
one that carries the gradient."""


def monotone_slope(v: Tensor, gain: Tensor, unit_weights: Tensor, centers: Tensor,
                   slopes: Tensor) -> Tensor:
    """``g'(v)`` of :func:`monotone_output`'s ``g``: v (...) -> (...). Scriptable."""
    tanh = torch.tanh(slopes * (v.unsqueeze(-1) - centers))
    return gain + (unit_weights * slopes * (1.0 - tanh * tanh)).sum(-1)


def monotone_inverse(y: Tensor, gain: Tensor, unit_weights: Tensor, centers: Tensor,
                     slopes: Tensor, offset: Tensor, lower: Tensor, upper: Tensor,
                     bisections: int = BISECTIONS, newton: int = NEWTON) -> Tensor:
    """``v`` in ``[lower, upper]`` with ``g(v) = y`` for the increasing ``g`` of
    :func:`monotone_output` (the bound where there is none): y (...) -> (...). Scriptable.

    Bisection on ``[(y - offset - C) / gain, (y - offset + C) / gain]`` (``C`` the sum of
    ``unit_weights``) cut to ``[lower, upper]`` (0-dim, may be infinite), then ``newton``
    Newton steps kept inside the final bracket, all detached, then two more Newton steps on
    the graph (the gradient with respect to y and the parameters is the implicit-function
    one, and so is its derivative: ``gradgradcheck`` passes), clamped to the bounds.
    """
    if unit_weights.numel() == 0:  # g is affine: its inverse in closed form
        return torch.minimum(torch.maximum((y - offset) / gain, lower), upper)
    spread = unit_weights.sum()
    base = (y - offset).detach()
    lo = torch.maximum((base - spread.detach()) / gain.detach(), lower)
    hi = torch.minimum((base + spread.detach()) / gain.detach(), upper)
    hi = torch.maximum(lo, hi)
    target = y.detach()
    a, c, b, s, off = (gain.detach(), unit_weights.detach(), centers.detach(), slopes.detach(),
                       offset.detach())
    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        below = monotone_output(mid, a, c, b, s, off) < target
        lo = torch.where(below, mid, lo)
        hi = torch.where(below, hi, mid)
    v = 0.5 * (lo + hi)
    for _ in range(newton):
        step = (monotone_output(v, a, c, b, s, off) - target) / monotone_slope(v, a, c, b, s)
        v = torch.minimum(torch.maximum(v - step, lo), hi)
    # two Newton steps on the graph: the first gives the implicit-function gradient, the
    # second its derivative too (the second derivative of a single step from a detached
    # point misses g''s curvature)
    for _ in range(2):
        residual = monotone_output(v, gain, unit_weights, centers, slopes, offset) - y
        v = v - residual / monotone_slope(v, gain, unit_weights, centers, slopes)
    return torch.minimum(torch.maximum(v, lower), upper)


def _mse_terms(design: Tensor, y: Tensor, w: Tensor, gain: Tensor, unit_weights: Tensor,
               centers: Tensor, slopes: Tensor, offset: Tensor
               ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """v = design @ w, z = s (v - b), tanh(z) and the residuals of :func:`monotone_mse`."""
    v = design @ w
    z = slopes * (v.unsqueeze(-1) - centers)
    units = torch.tanh(z)
    return v, z, units, gain * v + units @ unit_weights + offset - y


@signature_once
class _MonotoneMSE(torch.autograd.Function):
    """:func:`monotone_mse` with its gradient written out: one ``tanh`` pass forward, the
    rest matrix-vector products (autograd's graph of the same expression takes about twice
    the time on long records).

    Returns the loss and, not differentiable, the terms of :func:`_mse_terms` (which the
    backward reads). Works with ``torch.func`` (``generate_vmap_rule``). Differentiable
    twice: when a graph of the gradient is asked for, the backward recomputes the terms from
    the inputs, so that the gradient's own derivative is exact (it would miss the terms'
    dependence on the parameters if it read the saved ones)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(design: Tensor, y: Tensor, w: Tensor, gain: Tensor,  # type: ignore[override]
                unit_weights: Tensor, centers: Tensor, slopes: Tensor,
                offset: Tensor) -> tuple[Tensor, ...]:
        terms = _mse_terms(design, y, w, gain, unit_weights, centers, slopes, offset)
        return (terms[3].square().mean(), *terms)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:  # type: ignore[override]  # noqa: ANN001
        ctx.mark_non_differentiable(*output[1:])
        ctx.save_for_backward(*inputs, *output[1:])

    @staticmethod
    def backward(ctx, grad: Tensor, *_: Tensor  # type: ignore[override]
                 ) -> tuple[Tensor | None, ...]:
        design, y, w, gain, c, b, s, offset, v, z, units, r = ctx.saved_tensors
        if torch.is_grad_enabled():  # a graph of the gradient: the terms with theirs
            v, z, units, r = _mse_terms(design, y, w, gain, c, b, s, offset)
        g = r * (2.0 * grad / r.numel())  # d loss / d output, per sample
        sech2 = 1.0 - units.square()  # d tanh(z) / dz
        gs = g @ sech2  # (K,)
        dv = g * (gain + sech2 @ (c * s))  # d loss / d v, per sample
        return (None, None, design.T @ dv, g @ v, g @ units, -gs * c * s,
                c * (g @ (sech2 * z)) / s, g.sum())


def monotone_mse(design: Tensor, y: Tensor, w: Tensor, gain: Tensor, unit_weights: Tensor,
                 centers: Tensor, slopes: Tensor, offset: Tensor) -> Tensor:
    """``mean((g(design @ w) - y)^2)`` (:func:`monotone_output` for g), 0-dim, with an
    analytic gradient in ``w`` and g's parameters (none in ``design`` and ``y``),
    differentiable again, ``torch.func`` transforms included.

    Args:
        design: (M, P); y: (M,); w: (P,); gain, offset: 0-dim; unit_weights, centers,
            slopes: (K,). One dtype.
    """
    return call_function(_MonotoneMSE, design, y, w, gain, unit_weights, centers, slopes,
                         offset)[0]
