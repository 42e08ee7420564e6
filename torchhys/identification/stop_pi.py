"""Identification of the stop-type Prandtl-Ishlinskii model by (non-negative) least squares:
:func:`fit_stop_pi` and its ridge chosen on a hold-out, :func:`select_stop_pi_ridge`, and the
``stop_pi`` family of the configs.

``{"fit": "stop_pi", "n_widths": 20, "power": 2.0, "segments": 4, "ridge": "auto",
"nonnegative": True}``: :func:`torchhys.fit_stop_pi`, stop operators with thresholds on
:func:`~torchhys.identification.fitting.play_width_grid` of the input (up to its span: the
largest make the memoryless part), each through a piecewise-linear characteristic of
``segments`` equal segments (non-negative slopes: a friction element with a nonlinear spring,
whose loops run clockwise); both signs of the target fitted, the better kept.

Its search (:data:`torchhys.registry.SEARCHES`, the real-data benchmark's rows):
:func:`search_stop_pi`, over the settings of :func:`stop_pi_settings`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_bool,
    check_int,
    check_penalty,
    check_positive,
    check_real,
    check_same_shape,
    check_warmup,
    fitted_samples,
)
from torchhys.functional.backlash import backlash
from torchhys.functional.stop_pi import (
    check_thresholds,
    stop_segments,
)
from torchhys.identification._family_spec import (
    PENALTIES,
    VALIDATION,
    Fitter,
    _check_columns,
    _holdout,
    _keys,
    _penalty,
    holdout_share,
)
from torchhys.identification._nnls import (
    Moments,
    check_validation,
    fit_segments,
    moments_rmse,
    nnls_gram,
    select_on_holdout,
)
from torchhys.identification.errors import _checked, _samples, _standardized
from torchhys.identification.fitting import play_width_grid
from torchhys.operators.stop_pi import StopPrandtlIshlinskii
from torchhys.registry import Searched, register_family

__all__ = ["StopSetting", "fit_stop_pi", "fit_stop_pi_signs", "fit_stop_setting",
           "search_stop_pi", "select_stop_pi_ridge", "stop_pi_settings"]


# --- identification -----------------------------------------------------------------------
def _check_data(x: Tensor, y: Tensor, thresholds: Tensor, segments: int,
                warmup: int) -> tuple[Tensor, Tensor, int]:
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, xb, "y", "x")
    segments = check_int(segments, "segments", minimum=1)
    check_thresholds(thresholds)
    check_warmup(warmup, xb.shape[1])
    return xb, yb, segments


def _center(xb: Tensor, fitted: Tensor, center: float | None) -> float:
    """The midpoint of the range of the fitted input (the samples of the (rows, time) bool
    mask ``fitted``), or the given center."""
    if center is not None:
        return check_real(center, "center")
    xs = xb[fitted.to(xb.device)]
    return 0.5 * (float(xs.min()) + float(xs.max()))


def _min_linear_weight(value: float | None) -> float | None:
    """None, or a finite number >= 0 as a float; ``ValueError`` naming the argument."""
    if value is None:
        return None
    return check_penalty(value, "min_linear_weight")


_CHUNK = 8192


def _moments(xb: Tensor, yb: Tensor, thresholds: Tensor, segments: int, center: float,
             samples: list[Tensor]) -> list[tuple[Moments, Tensor]]:
    """The normal equations of the design ``[1, u, segment features]`` (2 + N K columns) for
    the samples of each segment (a (rows, time) bool mask), float64, accumulated in chunks;
    with each, which columns vary over those samples ((2 + N K,) bool; the first two always
    True)."""
    r = thresholds.detach().double().cpu()
    m = 2 + r.numel() * segments
    out = []
    with torch.no_grad():
        u = xb.detach().double().cpu() - center
        t = yb.detach().double().cpu()
        s = u.unsqueeze(-1) - backlash(u, 2.0 * r)  # (B, T, N)
        for seg in samples:
            G, h = torch.zeros(m, m, dtype=torch.float64), torch.zeros(m, dtype=torch.float64)
            yy, count = torch.zeros((), dtype=torch.float64), 0
            lo = torch.full((m,), math.inf, dtype=torch.float64)
            hi = torch.full((m,), -math.inf, dtype=torch.float64)
            for row in range(u.shape[0]):
                for i in seg[row].nonzero().flatten().split(_CHUNK):
                    A = torch.cat([torch.ones(i.numel(), 1, dtype=torch.float64), u[row, i, None],
                                   stop_segments(s[row, i], r, segments).flatten(1)], 1)
                    G += A.T @ A
                    h += A.T @ t[row, i]
                    yy += t[row, i] @ t[row, i]
                    count += i.numel()
                    lo = torch.minimum(lo, A.amin(0))
                    hi = torch.maximum(hi, A.amax(0))
            varying = hi > lo
            varying[:2] = True
            out.append((Moments(G, h, yy, count), varying))
    return out


def _solve(G: Tensor, h: Tensor, ridge: float, nonnegative: bool, varying: Tensor,
           min_linear_weight: float | None = None) -> Tensor:
    """``[offset, w0, W.flatten()]`` from the per-sample normal equations plus ``ridge`` on W,
    with ``w0 >= min_linear_weight`` when it is given.

    A segment the fitted samples never enter (``varying`` False: its feature is constant, a
    knot beyond the input's range) has no data for its slope: its weight is 0 and it is left
    out of the solve, which removes its exact collinearity with the offset. The bound on w0:
    with non-negative slopes, a non-negativity constraint on ``w0 - min_linear_weight`` (the
    target less ``min_linear_weight * u``); with free slopes, the unbounded solution if its
    w0 meets the bound, else the best one with w0 at the bound (one bound on one variable of
    a convex problem: the optimum is on it).
    """
    pen = torch.ones_like(h)
    pen[:2] = 0.0
    P = G + ridge * torch.diag(pen)
    theta = torch.zeros_like(h)
    m = min_linear_weight
    if not nonnegative:
        theta[varying] = _lstsq(P[varying][:, varying], h[varying])
        if m is None or float(theta[1]) >= m:
            return theta
        # the bound is active: w0 = m, the rest unconstrained on the target less m u
        keep = varying.clone()
        keep[1] = False
        theta.zero_()
        theta[keep] = _lstsq(P[keep][:, keep], (h - m * P[:, 1])[keep])
        theta[1] = m
        return theta
    if m is not None:
        h = h - m * P[:, 1]
    free = torch.zeros(h.shape, dtype=torch.bool)
    free[0] = True
    free[1] = m is None
    theta[varying] = nnls_gram(P[varying][:, varying], h[varying], free[varying])
    if m is not None:
        theta[1] += m
    return theta


def _lstsq(P: Tensor, h: Tensor) -> Tensor:
    """The minimum-norm solution of ``P theta = h`` (rank-revealing: the Gram matrix is
    singular when the largest stops never slip, their features then collinear with u)."""
    return torch.linalg.lstsq(P, h[:, None], driver="gelsd").solution[:, 0]


def fit_stop_pi(
    x: Tensor,
    y: Tensor,
    thresholds: Tensor,
    *,
    segments: int = 4,
    ridge: float = 0.0,
    nonnegative: bool = True,
    min_linear_weight: float | None = None,
    center: float | None = None,
    warmup: int = 0,
    mask: Tensor | None = None,
) -> StopPrandtlIshlinskii:
    """Identify a :class:`StopPrandtlIshlinskii` model by penalised least squares:

        min  mean_t (y[t] - offset - w0 u[t] - a[t] @ W.flatten())**2 + ridge * |W|**2,

    a[t] the segment features of the stops of ``u = x - center`` (each row's plays start at
    0), subject to ``W >= 0`` when ``nonnegative`` (every characteristic rises: the model's
    loops run clockwise in the (x, y) plane; fit ``-y`` and negate for the other
    orientation). Solved in float64 from the normal equations (Lawson-Hanson for the
    constrained fit, the offset and w0 free).

    Thresholds: :func:`~torchhys.identification.fitting.play_width_grid` of the input gives ``span
    (k/n)^p``, up to the input's span: with the default center (the midpoint of the fitted input's
    range) the stops of at least half the span never slip on the fitted samples (nor on the warm-up,
    when it stays inside that range) and make the memoryless (elastic) part of the model, the
    smaller ones the hysteresis. A segment the fitted samples never enter gets slope 0.
    Train a ``learnable`` copy further with :meth:`StopPrandtlIshlinskii.project_` after each
    step to keep the slopes non-negative.

    Args:
        x, y: input and target, (time,) or (batch, time) (rows are independent records).
        thresholds: stop thresholds r_i > 0, (N,).
        segments: K, equal segments of each characteristic (1: the classical model).
        ridge: Tikhonov weight on W (>= 0); choose it with :func:`select_stop_pi_ridge`.
        nonnegative: constrain W >= 0.
        min_linear_weight: None (w0 free), or a number >= 0: constrain ``w0 >=`` it. With
            ``nonnegative`` and a positive bound the output rises with the input at every
            state, also beyond the fitted range, where every stop slips and w0 is the slope
            left: the model then has an exact inverse (:meth:`StopPrandtlIshlinskii.inverse`,
            a compensator). Left free, w0 often comes out negative: the largest stops, which
            never slip on the fitted samples, carry the memoryless slope, and w0 trades off
            against them.
        center: the input value at which the stops start; default the midpoint of the fitted
            input's range.
        warmup: leading samples of each row left out of the fit (the stops still run).
        mask: the samples to fit, bool, the shape of ``x`` (False: left out of the fit and
            of the default center, the stops still run through them, e.g. a held-out block
            or a shorter row's padding); None: every sample (after ``warmup`` in both
            cases).

    Returns:
        The model, in the dtype of ``x`` (parameters detached).

    Raises:
        TypeError, ValueError: bad or mismatched arguments (each named).
    """
    xb, yb, segments = _check_data(x, y, thresholds, segments, warmup)
    ridge = check_penalty(ridge, "ridge")
    nonnegative = check_bool(nonnegative, "nonnegative")
    bound = _min_linear_weight(min_linear_weight)
    fitted = fitted_samples(mask, xb.shape, warmup)
    c = _center(xb, fitted, center)
    ((mom, varying),) = _moments(xb, yb, thresholds, segments, c, [fitted])
    return _fitted(mom, varying, ridge, nonnegative, bound, thresholds, segments, c, xb)


def _fitted(mom: Moments, varying: Tensor, ridge: float, nonnegative: bool,
            bound: float | None, thresholds: Tensor, segments: int, c: float,
            xb: Tensor) -> StopPrandtlIshlinskii:
    """The model of the solution of the moments (in x's dtype and device)."""
    theta = _solve(mom.gram / mom.count, mom.moment / mom.count, ridge, nonnegative, varying,
                   bound)
    if not bool(torch.isfinite(theta).all()):
        raise ValueError("the least-squares solution is not finite (degenerate data?)")
    n = thresholds.shape[0]
    dt = xb.dtype
    return StopPrandtlIshlinskii(
        thresholds.detach().to(dt), theta[2:].reshape(n, segments).to(dt), center=c,
        linear_weight=float(theta[1]), offset=float(theta[0])).to(xb.device)


def fit_stop_pi_signs(
    x: Tensor,
    y: Tensor,
    thresholds: Tensor,
    ridges: float | Sequence[float],
    *,
    signs: Sequence[float] = (1.0,),
    segments: int = 4,
    nonnegative: bool = True,
    validation: float = 0.25,
    mask: Tensor | None = None,
) -> list[tuple[float, StopPrandtlIshlinskii, float]]:
    """:func:`fit_stop_pi` of ``sign * y`` for each sign, its ridge chosen by
    :func:`select_stop_pi_ridge` when ``ridges`` is a sequence (one number: that ridge), the
    default center, no warm-up: the design's moments are formed once for all signs (a sign
    flips only ``A'y``). Equal to those calls up to rounding.

    Returns:
        ``(ridge, model, rmse)`` for each sign, in order: rmse the RMS error of the model
        against ``sign * y`` on the fitted samples, from the moments (no run of the model).
    """
    xb, yb, segments = _check_data(x, y, thresholds, segments, 0)
    nonnegative = check_bool(nonnegative, "nonnegative")
    select = not isinstance(ridges, (int, float, Tensor))
    fitted = fitted_samples(mask, xb.shape, 0)
    c = _center(xb, fitted, None)
    ((full, varying),) = _moments(xb, yb, thresholds, segments, c, [fitted])
    if select:
        train_part, held = fit_segments(xb.shape, 0, mask, check_validation(validation))
        (train, part_varying), (valid, _) = _moments(
            xb, yb, thresholds, segments, _center(xb, train_part, None), [train_part, held])
    out = []
    for sign in signs:
        if select:
            best, _ = select_on_holdout(
                train._replace(moment=sign * train.moment),
                valid._replace(moment=sign * valid.moment), ridges,
                lambda G, h, ridge: _solve(G, h, ridge, nonnegative, part_varying, None),
                name="ridges")
        else:
            best = check_penalty(ridges, "ridge")
        mom = full._replace(moment=sign * full.moment)
        model = _fitted(mom, varying, best, nonnegative, None, thresholds, segments, c, xb)
        theta = torch.cat([model.offset.detach().reshape(1),
                           model.linear_weight.detach().reshape(1),
                           model.weights.detach().flatten()]).double().cpu()
        out.append((best, model, moments_rmse(mom, theta)))
    return out


def select_stop_pi_ridge(
    x: Tensor,
    y: Tensor,
    thresholds: Tensor,
    ridges: Sequence[float],
    *,
    segments: int = 4,
    nonnegative: bool = True,
    min_linear_weight: float | None = None,
    center: float | None = None,
    validation: float = 0.25,
    warmup: int = 0,
    mask: Tensor | None = None,
) -> tuple[float, dict[float, float]]:
    """Choose the ``ridge`` of :func:`fit_stop_pi` on a time-ordered hold-out: each
    candidate is fitted on the first ``1 - validation`` of every row (after ``warmup``; with
    a ``mask``, of its masked samples) and scored by the RMS error on the rest (the stops run
    through the whole sequence; the center is taken from the fitted part).

    Returns:
        The ridge with the least hold-out RMS error (the first on ties), and the RMS error of
        each. Refit on all samples with ``fit_stop_pi(..., ridge=best)``.

    Raises:
        TypeError, ValueError: bad arguments, or no training sample before the split.
    """
    xb, yb, segments = _check_data(x, y, thresholds, segments, warmup)
    nonnegative = check_bool(nonnegative, "nonnegative")
    bound = _min_linear_weight(min_linear_weight)
    fitted, held = fit_segments(xb.shape, warmup, mask, check_validation(validation))
    c = _center(xb, fitted, center)
    (train, varying), (valid, _) = _moments(xb, yb, thresholds, segments, c, [fitted, held])

    def solve(G: Tensor, h: Tensor, ridge: float) -> Tensor:
        return _solve(G, h, ridge, nonnegative, varying, bound)

    return select_on_holdout(train, valid, ridges, solve, name="ridges")


def _stop_pi(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"n_widths", "power", "segments", "ridge", "nonnegative"})
    n = check_int(spec.get("n_widths", 20), "fit 'stop_pi': n_widths", minimum=1)
    power = check_positive(spec.get("power", 2.0), "fit 'stop_pi': power")
    segments = check_int(spec.get("segments", 4), "fit 'stop_pi': segments", minimum=1)
    nonnegative = check_bool(spec.get("nonnegative", True), "fit 'stop_pi': nonnegative")
    ridge = _penalty(spec, "ridge")
    _check_columns(spec, n * segments, f"n_widths={n} x segments={segments}")

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        _check_columns(spec, n * segments, f"n_widths={n} x segments={segments}", x.numel())
        scored, _ = _samples(x, warmup, mask)
        sx, t = _standardized(x, y, scored)
        u = x / sx
        thresholds = play_width_grid(u[scored], n, power=power)
        fits = []
        signs = (1.0, -1.0) if nonnegative else (1.0,)
        auto = ridge == "auto"
        models = fit_stop_pi_signs(u, t, thresholds, list(PENALTIES) if auto else ridge,
                                   signs=signs, segments=segments, nonnegative=nonnegative,
                                   validation=_holdout(scored) if auto else VALIDATION,
                                   mask=scored)
        for sign, (_, m, rmse) in zip(signs, models, strict=True):
            # the same model of the physical input x, times the sign
            m = StopPrandtlIshlinskii(
                m.thresholds * sx, sign * m.weights / sx, center=float(m.center) * sx,
                linear_weight=sign * float(m.linear_weight) / sx, offset=sign * float(m.offset))
            fits.append((rmse, m))
        rmse, m = min(fits, key=lambda f: f[0])
        return _checked(m, x, t, scored, "stop_pi", rmse=rmse)

    return StopPrandtlIshlinskii(torch.arange(1, n + 1) / n,
                                 torch.zeros(n, segments)).requires_grad_(False), fit


# --- the search -----------------------------------------------------------------------------
class StopSetting(NamedTuple):
    """A setting of :func:`stop_pi_settings` (ordered as a tuple, for ties)."""

    n_widths: int
    power: float
    segments: int
    sign: float
    """The target's sign the stops are fitted to (non-negative slopes: clockwise loops)."""
    ridge: float


def stop_pi_settings(x: Tensor, y: Tensor, warmup: int, cut: int, *,
                     n_widths: Sequence[int], powers: Sequence[float],
                     segments: Sequence[int]) -> Iterator[tuple[StopSetting, float]]:
    """Every setting of the ``stop_pi`` family's search (the number of thresholds on
    :func:`~torchhys.identification.fitting.play_width_grid` of the scored input, the grid
    power, the segments, the target's sign), each with the ridge of :data:`PENALTIES` that
    :func:`select_stop_pi_ridge` chooses on the hold-out ``cut:`` and that ridge's hold-out
    RMS error (arguments as
    :func:`~torchhys.identification.prandtl_ishlinskii.search_pi_nonneg`'s)."""
    for n in n_widths:
        for power in powers:
            thresholds = play_width_grid(x[:, warmup:], n, power=power)
            for k in segments:
                for sign in (1.0, -1.0):
                    ridge, scores = select_stop_pi_ridge(
                        x, sign * y, thresholds, PENALTIES, segments=k,
                        validation=holdout_share(x, cut), warmup=warmup)
                    yield StopSetting(n, power, k, sign, ridge), scores[ridge]


def fit_stop_setting(x: Tensor, y: Tensor, warmup: int, setting: StopSetting,
                     end: int) -> StopPrandtlIshlinskii:
    """:func:`fit_stop_pi` of ``setting.sign`` x target on samples [warmup, end) of every
    row, thresholds from the scored input's span (all samples after ``warmup``)."""
    thresholds = play_width_grid(x[:, warmup:], setting.n_widths, power=setting.power)
    return fit_stop_pi(x[:, :end], setting.sign * y[:, :end], thresholds,
                       segments=setting.segments, ridge=setting.ridge, warmup=warmup)


def search_stop_pi(x: Tensor, y: Tensor, warmup: int, cut: int, *,
                   n_widths: Sequence[int], powers: Sequence[float],
                   segments: Sequence[int]) -> Searched:
    """The ``stop_pi`` family's search: the setting of :func:`stop_pi_settings` with the
    least RMS error on the hold-out, refitted on every sample."""
    score, setting = min((score, setting) for setting, score in stop_pi_settings(
        x, y, warmup, cut, n_widths=n_widths, powers=powers, segments=segments))
    model = fit_stop_setting(x, y, warmup, setting, x.shape[1])
    return Searched(score, {"fit": "stop_pi", **setting._asdict()},
                    lambda v: setting.sign * model(v)[0])


register_family("stop_pi", _stop_pi, search=search_stop_pi)
