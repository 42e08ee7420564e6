"""Identification of the drift operator by non-negative least squares: :func:`fit_drift`, and
the ``drift`` family of the configs.

``{"fit": "drift", "scales": [0.5, 1, 2, 4, 8, 16, 32]}``: :func:`torchhys.fit_drift`, a
monotone, decelerating drift of the target with the input's accumulated variation
(saturation scales in spans of the scored training input), weights of one sign; beside a
hysteresis model in one candidate (``[{fit: stop_pi}, {fit: drift}]``, one affine
readout of both) it shifts the loop as the device is used (the ratcheting of a
shape-memory alloy). It is fitted beside a free slope in the input (not part of the
drift), so that a loop's rise and fall with the input is not taken for a drift.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_bool,
    check_positive,
    check_warmup,
    fitted_samples,
)
from torchhys.functional.drift import (
    accumulated_variation,
    check_scales,
    drift_features,
)
from torchhys.identification._family_spec import Fitter, _keys
from torchhys.identification._nnls import nnls_gram
from torchhys.identification.errors import _samples, _standardized
from torchhys.operators.drift import Drift
from torchhys.registry import register_family

__all__ = ["fit_drift"]


def fit_drift(x: Tensor, y: Tensor, scales: Tensor | Sequence[float], *,
              warmup: int = 0, linear: bool = True, mask: Tensor | None = None) -> Drift:
    """Identify a :class:`Drift` (fresh start of every row) by least squares with weights of
    one sign, the offset free:

        min  mean_t (y[t] - offset - b x[t] - s sum_k w_k g_k[t])**2   subject to w >= 0,

    ``g_k = 1 - exp(-v / c_k)``, for s = +1 and s = -1; the better fit is kept (+1 on ties).
    The returned drift's floor (``min_variation``) is the least variation of the fitted
    samples: on a record whose fitted samples start late (after a held-out block) it is held
    there rather than extrapolated backwards.
    With ``linear`` the slope b is free and not part of the returned drift: the drift of a
    target that also follows the input (a loop beside it), which a drift alone would confuse
    with the input's own rise and fall; without it b = 0. Solved in float64 from the normal
    equations (Lawson-Hanson).

    Args:
        x, y: input and target, (time,) or (batch, time) (rows are independent records).
        scales: saturation scales c_k > 0, (K,).
        warmup: samples at the start of each row left out of the fit (their variation still
            counts).
        linear: fit a free slope in x beside the drift (left out of the returned model).
        mask: the samples to fit, bool, the shape of ``x`` (False: left out of the fit,
            their variation still counts, e.g. a held-out block or a shorter row's padding);
            None: every sample (after ``warmup`` in both cases).

    Returns:
        The fitted drift, in x's dtype.

    Raises:
        ValueError: NaN/inf, shapes differ, bad scales, warmup >= time, a bad mask.
    """
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    if xb.shape != yb.shape:
        raise ValueError(f"x and y must have the same shape, got {tuple(x.shape)} and "
                         f"{tuple(y.shape)}")
    check_warmup(warmup, xb.shape[1])
    check_bool(linear, "linear")
    c = torch.as_tensor(scales, dtype=torch.float64)
    check_scales(c)
    fitted = fitted_samples(mask, tuple(xb.shape), warmup).to(xb.device)
    v, _ = accumulated_variation(xb)
    g = drift_features(v[fitted], c)  # (n, K)
    floor = float(v[fitted].min())
    t = yb[fitted].to(torch.float64)
    xs = xb[fitted].unsqueeze(1).to(torch.float64)
    # the offset at column K (free), then the slope (free)
    A = torch.cat([g, torch.ones_like(t)[:, None]] + ([xs - xs.mean()] if linear else []), 1)
    n, K = t.numel(), c.numel()
    G, h0 = A.T @ A / n, A.T @ t / n
    free = torch.arange(A.shape[1]) >= K
    best: tuple[float, float, Tensor] | None = None
    for sign in (1.0, -1.0):
        theta = nnls_gram(G, sign * h0, free)
        theta[:K] = theta[:K].clamp_min(0.0)
        sse = float(((A @ theta - sign * t) ** 2).sum())
        if best is None or sse < best[0]:
            best = (sse, sign, theta)
    _, sign, theta = best
    offset = float(theta[K]) - (float(theta[K + 1] * xs.mean()) if linear else 0.0)
    return Drift(c.to(xb.dtype), sign * theta[:K].to(xb.dtype), offset=sign * offset,
                 min_variation=floor)


DRIFT_SCALES = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
"""Saturation scales of the ``drift`` family, in spans of the scored training input (a full
cycle over the span adds two spans to the accumulated variation)."""


def _drift(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"scales"})
    scales = spec.get("scales", DRIFT_SCALES)
    if (isinstance(scales, (str, bytes)) or not hasattr(scales, "__len__")
            or len(scales) == 0):
        raise ValueError(f"fit 'drift': scales must be a non-empty list of positive "
                         f"numbers (spans of the training input), got {scales!r}")
    mult = [check_positive(c, "fit 'drift': scales[]") for c in scales]

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        scored, _ = _samples(x, warmup, mask)
        _, t = _standardized(x, y, scored)
        span = float(x[scored].max() - x[scored].min())
        return fit_drift(x, t, [span * c for c in mult], mask=scored)

    return Drift(torch.ones(len(mult))).requires_grad_(False), fit


register_family("drift", _drift)
