"""Identification of the Preisach operator by penalised non-negative least squares:
:func:`fit_preisach` and the choice of its penalty on a hold-out, :func:`select_penalty`, and
the ``preisach`` family of the configs.

``{"fit": "preisach", "n": 20, "smoothness": "auto", "grading": None,
"direction": "direct"}``: :func:`torchhys.fit_preisach` of the target from the input on a
grid over the input's training range (``direct``), or of the input from the target, then
its exact inverse (``inverse``, :class:`torchhys.PreisachInverse`: a magnetic core's flux
density from its field, inverted into the compensator); both signs of the target fitted,
the better kept. ``grading``: None for an even grid, or a graded one whose ``scale`` is
that fraction of half the grid's span (:class:`torchhys.Preisach`).

Its search (:data:`torchhys.registry.SEARCHES`, the real-data benchmark's row):
:func:`search_preisach`.
"""

from __future__ import annotations

import copy
import functools
import math
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_choice,
    check_int,
    check_penalty,
    check_positive,
    check_warmup,
    fitted_samples,
)
from torchhys._memory import check_memory
from torchhys.functional.preisach import (
    _real,
    _relay_chunks,
    graded_input,
)
from torchhys.identification._family_spec import (
    PENALTIES,
    VALIDATION,
    Fitter,
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
from torchhys.identification.errors import FitError, _checked, _rmse, _samples, _standardized
from torchhys.operators.preisach import Preisach, PreisachInverse
from torchhys.registry import Searched, register_family

__all__ = ["SMOOTHNESS", "check_fit_memory", "fit_preisach", "fit_preisach_signs",
           "search_preisach", "select_penalty"]

FIT_MATRICES = 10
"""The (relays, relays) float64 matrices a fit holds at its peak, about (measured: the
moments of the training and hold-out samples and their sum, the penalised copy, the
solver's, the difference operator, two such, and its Gram matrix, and temporaries)."""


def check_fit_memory(n: int, what: str = "fit_preisach") -> None:
    """Refuse a fit of an n-level grid whose matrices (:data:`FIT_MATRICES` of
    ``K x K`` float64, ``K = n (n + 1) / 2`` relays: they grow as n**4) exceed the memory
    limit (:func:`torchhys._memory.check_memory`), before anything is allocated.

    Raises:
        ValueError: naming ``what``, n, the relays, the estimate and the limit.
    """
    K = n * (n + 1) // 2
    check_memory(FIT_MATRICES * 8.0 * (K + 2) ** 2, f"{what}: n={n} ({K} relays)",
                 "lower n (the fit's matrices grow as n**4)")


def fit_preisach(
    x: Tensor,
    y: Tensor,
    *,
    lo: float | None = None,
    hi: float | None = None,
    n: int = 20,
    ridge: float = 0.0,
    smoothness: float = 0.0,
    linear: bool = True,
    warmup: int = 0,
    scale: float | None = None,
    mask: Tensor | None = None,
) -> Preisach:
    """Identify a :class:`Preisach` model (demagnetised start, hard relays) by penalised
    non-negative least squares of the density, with a free offset and linear term:

        min  mean_t (y[t] - offset - linear x[t] - r[t] @ w)**2
             + ridge * |w|**2 + smoothness * |D w|**2        subject to w >= 0,

    D the differences between neighbouring relays of the grid (alpha or beta one level
    apart). Solved in float64 from the normal equations (accumulated chunk by chunk) with the
    Lawson-Hanson active-set method, the free variables always in the passive set.

    Args:
        x, y: input and output, (time,) or (batch, time) (each row starts demagnetised).
        lo, hi: grid range; default the range of x. Samples outside saturate the relays
            (one warning gives their share; with a ``mask``, of the masked samples).
        n: levels per axis; ridge, smoothness: penalties (>= 0); linear: fit the linear term.
        warmup: samples at the start of each row left out of the fit (their relays still
            run), to forget the assumed initial state.
        scale: None (an even grid), or a graded grid's scale (:class:`Preisach`).
        mask: the samples to fit, bool, the shape of ``x`` (False: left out of the fit, the
            relays still run through them, e.g. a held-out block or a shorter row's
            padding); None: every sample (after ``warmup`` in both cases).

    Returns:
        The fitted model, in x's dtype.

    Raises:
        ValueError: NaN/inf in x or y, shapes differ, a bad grid, warmup >= time, a negative
            penalty.

    Warns:
        RuntimeWarning: once, with the share of samples of x outside [lo, hi].
    """
    xb, yb, model, samples = _prepare(x, y, lo, hi, n, linear, warmup, None, scale, mask)
    (G, h, _, count), = _normal_equations(xb, yb, model, samples)
    theta = _solve(G / count, h / count, model, check_penalty(ridge, "ridge"),
                   check_penalty(smoothness, "smoothness"))
    return _set(model, theta)


def select_penalty(
    x: Tensor,
    y: Tensor,
    penalties: list[float],
    *,
    kind: str = "smoothness",
    validation: float = 0.25,
    lo: float | None = None,
    hi: float | None = None,
    n: int = 20,
    linear: bool = True,
    warmup: int = 0,
    scale: float | None = None,
    mask: Tensor | None = None,
) -> tuple[float, dict[float, float]]:
    """Choose the ``kind`` penalty (``"ridge"`` or ``"smoothness"``, the other 0) of
    :func:`fit_preisach` on a time-ordered hold-out: fit on the first ``1 - validation`` of
    each row (after ``warmup``; with a ``mask``, of its masked samples), score the RMS error
    on the rest (the relays run through the whole sequence).

    Returns:
        The penalty with the least validation RMS error (the first on ties), and the RMS
        error of each. Refit on all samples with ``fit_preisach(..., smoothness=best)``
        (or ``ridge=best``).
    """
    if kind not in ("ridge", "smoothness"):
        raise ValueError(f"kind must be one of ('ridge', 'smoothness'), got {kind!r}")
    xb, yb, model, samples = _prepare(x, y, lo, hi, n, linear, warmup,
                                      check_validation(validation), scale, mask)
    train, valid = _normal_equations(xb, yb, model, samples)
    return select_on_holdout(train, valid, penalties, _warm_solver(model, kind))


def _warm_solver(model: Preisach, kind: str) -> Callable[[Tensor, Tensor, float], Tensor]:
    """``solve(G, h, penalty)`` of :func:`select_on_holdout` for the ``kind`` penalty, each
    penalty's fit started from the previous one's solution."""
    last: Tensor | None = None

    def solve(G: Tensor, h: Tensor, p: float) -> Tensor:
        nonlocal last
        last = _solve(G, h, model, *((p, 0.0) if kind == "ridge" else (0.0, p)), init=last)
        return last

    return solve


def fit_preisach_signs(
    x: Tensor,
    y: Tensor,
    penalties: float | Sequence[float],
    *,
    signs: Sequence[float] = (1.0,),
    kind: str = "smoothness",
    validation: float = 0.25,
    lo: float | None = None,
    hi: float | None = None,
    n: int = 20,
    linear: bool = True,
    warmup: int = 0,
    scale: float | None = None,
    mask: Tensor | None = None,
) -> list[tuple[float, Preisach, float]]:
    """:func:`fit_preisach` of ``sign * y`` for each sign, its ``kind`` penalty chosen by
    :func:`select_penalty` when ``penalties`` is a sequence (one number: that penalty), from
    one pass of the relays over x: the fit on all samples takes the sum of the training and
    hold-out moments, and a sign flips only ``A'y``. Equal to those calls up to rounding.

    Returns:
        ``(penalty, model, rmse)`` for each sign, in order: rmse the RMS error of the model
        against ``sign * y`` on the fitted samples, from the moments (no run of the model).
    """
    if kind not in ("ridge", "smoothness"):
        raise ValueError(f"kind must be one of ('ridge', 'smoothness'), got {kind!r}")
    select = not isinstance(penalties, (int, float, Tensor))
    xb, yb, model, samples = _prepare(x, y, lo, hi, n, linear, warmup,
                                      check_validation(validation) if select else None, scale,
                                      mask)
    segments = _normal_equations(xb, yb, model, samples)
    out = []
    for sign in signs:
        parts = [Moments(m.gram, sign * m.moment, m.yy, m.count) for m in segments]
        if select:
            best, _ = select_on_holdout(*parts, penalties, _warm_solver(model, kind))
        else:
            best = check_penalty(penalties, kind)
        G, h = sum(m.gram for m in parts), sum(m.moment for m in parts)
        count = sum(m.count for m in parts)
        theta = _solve(G / count, h / count, model,
                       *((best, 0.0) if kind == "ridge" else (0.0, best)))
        fitted = _set(copy.deepcopy(model), theta)
        theta = torch.cat([fitted.weights.detach().reshape(-1), fitted.linear.detach().reshape(-1)
                           if isinstance(model.linear, nn.Parameter) else theta[:0],
                           fitted.offset.detach().reshape(-1)]).double()
        total = Moments(G, h, sum(m.yy for m in parts), count)
        out.append((best, fitted, moments_rmse(total, theta)))
    return out


def _prepare(x: Tensor, y: Tensor, lo: float | None, hi: float | None, n: int, linear: bool,
             warmup: int, validation: float | None, scale: float | None,
             mask: Tensor | None) -> tuple[Tensor, Tensor, Preisach, list[Tensor]]:
    """Check the data, warn about samples outside [lo, hi]; the model and the samples of
    each segment (:func:`~torchhys.identification._nnls.fit_segments`)."""
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    if xb.shape != yb.shape:
        raise ValueError(f"x and y must have the same shape, got {tuple(x.shape)} and "
                         f"{tuple(y.shape)}")
    T = xb.shape[1]
    check_warmup(warmup, T)
    if lo is None and hi is None and not float(xb.max()) > float(xb.min()):
        raise ValueError(f"x is constant ({float(xb.min()):.6g}): its range gives no grid; "
                         "give lo and hi")
    lo = float(xb.min()) if lo is None else _real(lo, "lo")
    hi = float(xb.max()) if hi is None else _real(hi, "hi")
    if isinstance(n, int):  # Preisach checks other values
        check_fit_memory(n)
    model = Preisach(lo, hi, n, linear=linear, scale=scale).to(xb.dtype)
    samples = fit_segments(tuple(xb.shape), warmup, mask, validation)
    xs = xb if mask is None else xb[fitted_samples(mask, tuple(xb.shape), 0).to(xb.device)]
    outside = float(((xs < lo) | (xs > hi)).double().mean())
    if outside > 0:
        where = "samples" if mask is None else "masked samples"
        warnings.warn(f"{outside:.2%} of the {where} of x lie outside [lo, hi] = [{lo:.6g}, "
                      f"{hi:.6g}]: the relays saturate there", RuntimeWarning, stacklevel=3)
    return xb, yb, model, samples


def _normal_equations(x: Tensor, y: Tensor, model: Preisach,
                      samples: list[Tensor]) -> list[Moments]:
    """The :class:`~torchhys.identification._nnls.Moments` ``(A'A, A'y, y'y, rows)`` in float64 of
    the design ``A = [relays, x, 1]`` over the samples of each segment (a (rows, time) bool
    mask)."""
    K, m = model.n_relays, model.n_relays + 1 + isinstance(model.linear, nn.Parameter)
    out = [[x.new_zeros(m, m, dtype=torch.float64), x.new_zeros(m, dtype=torch.float64),
            x.new_zeros((), dtype=torch.float64), 0] for _ in samples]
    r0 = model.initial_relays.to(torch.float64).expand(x.shape[0], K)
    for start, stop, r in _relay_chunks(x, model.alpha, model.beta, r0):
        for seg, mask in zip(out, samples, strict=True):
            chunk = mask[:, start:stop].to(x.device)
            if not bool(chunk.any()):
                continue
            xs = graded_input(x[:, start:stop][chunk].unsqueeze(0).to(torch.float64),
                              model.center, model.scale)
            cols = [r[:, chunk]]
            cols += [xs] if m > K + 1 else []
            A = torch.cat(cols + [torch.ones_like(xs)])
            ys = y[:, start:stop][chunk].to(torch.float64)
            seg[0] += A @ A.T
            seg[1] += A @ ys
            seg[2] += ys @ ys
            seg[3] += ys.numel()
    return [Moments(*seg) for seg in out]


@functools.lru_cache(maxsize=8)
def _difference_gram(n: int) -> Tensor:
    """``D'D`` (K, K), float64, of the first differences D of the density between
    neighbouring relays of an n-level grid (along alpha and along beta); read only."""
    K = n * (n + 1) // 2
    i, j = torch.tril_indices(n, n)
    k = torch.arange(K)
    pairs = [(k[i < n - 1], (i * (i + 1) // 2 + i + 1 + j)[i < n - 1]), (k[j < i], k[j < i] + 1)]
    first = torch.cat([p[0] for p in pairs])
    second = torch.cat([p[1] for p in pairs])
    D = torch.zeros(first.numel(), K, dtype=torch.float64)
    D[torch.arange(first.numel()), first] = -1.0
    D[torch.arange(first.numel()), second] = 1.0
    return D.T @ D


def _solve(G: Tensor, h: Tensor, model: Preisach, ridge: float, smoothness: float,
           init: Tensor | None = None) -> Tensor:
    """The penalised NNLS solution: density (K,), then the free linear term and offset
    (``init``: a warm start, :func:`~torchhys.identification._nnls.nnls_gram`)."""
    K, m = model.n_relays, G.shape[0]
    P = G.clone()
    P[:K, :K] += ridge * torch.eye(K, dtype=torch.float64) + smoothness * _difference_gram(model.n)
    free = torch.arange(m) >= K
    return nnls_gram(P, h, free, init)


def _set(model: Preisach, theta: Tensor) -> Preisach:
    K = model.n_relays
    with torch.no_grad():
        model.weights.copy_(theta[:K].clamp_min(0.0))
        if isinstance(model.linear, nn.Parameter):
            model.linear.copy_(theta[K])
        model.offset.copy_(theta[-1])
    return model


def _preisach(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"n", "smoothness", "grading", "direction"})
    n = check_int(spec.get("n", 20), "fit 'preisach': n", minimum=2)
    check_fit_memory(n, "fit 'preisach'")
    smoothness = _penalty(spec, "smoothness")
    grading = spec.get("grading")
    if grading is not None:
        grading = check_positive(grading, "fit 'preisach': grading (or null)")
    direction = check_choice(spec.get("direction", "direct"), "fit 'preisach': direction",
                             ["direct", "inverse"])

    def fitted(u: Tensor, out: Tensor, scored: Tensor, known: Tensor,
               signs: tuple[float, ...]) -> list[tuple[float, Preisach, float]]:
        """The Preisach models of ``sign * out`` from ``u`` on a grid over u's (known) range,
        one pass of the relays for all signs."""
        lo, hi = float(u[known].min()), float(u[known].max())
        scale = None if grading is None else grading * 0.5 * (hi - lo)
        penalties = list(PENALTIES) if smoothness == "auto" else smoothness
        validation = _holdout(scored) if smoothness == "auto" else VALIDATION
        return fit_preisach_signs(
            u, out, penalties, signs=signs, kind="smoothness", validation=validation, lo=lo,
            hi=hi, n=n, mask=scored, scale=scale)

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        scored, known = _samples(x, warmup, mask)
        sx, t = _standardized(x, y, scored)
        mx = float(x[scored].mean())
        fits = []
        direct = fitted(x, t, scored, known, (1.0, -1.0)) if direction == "direct" else None
        for i, sign in enumerate((1.0, -1.0)):
            if direct is not None:
                _, m, rmse = direct[i]  # its RMS error from the fit's moments
                fits.append((rmse, sign, m))
                continue
            # the model of the centred, scaled input from sign x the target, mapped back to
            # the physical input, then inverted
            (_, forward, _), = fitted(sign * t, (x - mx) / sx, scored, known, (1.0,))
            with torch.no_grad():
                forward.weights.mul_(sx)
                forward.linear.mul_(sx)
                forward.offset.mul_(sx).add_(mx)
            try:
                m = forward.inverse()
            except ValueError:
                continue
            fits.append((_rmse(m, x, sign * t, scored), sign, m))
        if not fits:
            raise FitError(f"preisach ({direction}): no invertible fit of either sign")
        rmse, sign, m = min(fits, key=lambda f: f[0])
        return _checked(m, x, sign * t, scored, "preisach", rmse=rmse)

    placeholder = Preisach(0.0, 1.0, n) if direction == "direct" else PreisachInverse(n)
    return placeholder.requires_grad_(False), fit


SMOOTHNESS = (0.0, 1e-8, 1e-6, 1e-4, 1e-2)
"""The smoothness grid of :func:`search_preisach`."""


def search_preisach(x: Tensor, y: Tensor, warmup: int, cut: int, *,
                    levels: Sequence[int]) -> Searched:
    """The ``preisach`` family's search: :func:`fit_preisach` (direct) on a grid over the
    input's range, the number of ``levels``, the smoothness penalty (:data:`SMOOTHNESS`, by
    :func:`select_penalty`) and the target's sign (a non-negative density draws loops of
    one orientation; its free linear term lets the negated fit draw the other) with the
    least RMS error on the hold-out, each fitted on the samples before it; then refitted on
    every sample (arguments as
    :func:`~torchhys.identification.prandtl_ishlinskii.search_pi_nonneg`'s).
    """
    best = (math.inf, 0, 0.0, 0.0)
    for n in levels:
        for sign in (1.0, -1.0):
            p, scores = select_penalty(x, sign * y, list(SMOOTHNESS), kind="smoothness",
                                       validation=holdout_share(x, cut), n=n, warmup=warmup)
            best = min(best, (scores[p], n, sign, p))
    score, n, sign, p = best
    model = fit_preisach(x, sign * y, n=n, smoothness=p, warmup=warmup)
    return Searched(score, {"fit": "preisach", "n": n, "smoothness": p, "sign": sign},
                    lambda v: sign * model(v)[0])


register_family("preisach", _preisach, search=search_preisach)
