"""Identification of the generalized Prandtl-Ishlinskii model: :func:`fit_generalized_pi`
(a least-squares PI start, then full-batch training of the output function), and the ``gpi``
family of the configs.

``{"fit": "gpi", "n_widths": 10, "power": 2.0, "ridge": "auto", "units": 4,
"epochs": 1000, "sample_iterations": 1e7, "direction": "direct"}``:
:func:`torchhys.fit_generalized_pi` of the target (times the sign that makes it rise with
the input) from the input, or of the input from it, then
:class:`torchhys.GeneralizedPIInverse`. Its L-BFGS iterations are at most ``epochs`` and
at most ``sample_iterations`` over the fitted samples (at least 20): a long record gets
fewer (100 on 1e5 fitted samples), records up to 1e4 samples all of them. With ``ridge:
"auto"``, whose fit can stop at a poor local optimum, the next best ridges on the hold-out
are tried in turn when the fit fails, unless it ended on the straight line itself
(:attr:`~torchhys.identification.errors.NoBetterThanLine.on_the_line`).

Its search (:data:`torchhys.registry.SEARCHES`, the real-data benchmark's row):
:func:`search_gpi`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_int,
    check_penalty,
    check_positive,
    check_same_shape,
    fitted_samples,
)
from torchhys.identification._family_spec import (
    PENALTIES,
    Fitter,
    _check_columns,
    _grid,
    _holdout,
    _keys,
    _penalty,
    holdout_rmse,
)
from torchhys.identification.errors import (
    FitError,
    NoBetterThanLine,
    _checked,
    _samples,
    _standardized,
)
from torchhys.identification.fitting import (
    fit_full_batch,
    fit_prandtl_ishlinskii,
    play_width_grid,
    select_pi_ridge,
)
from torchhys.identification.prandtl_ishlinskii import _inverse_pi_choice, _pi_choice
from torchhys.operators.backlash import _inverse_softplus
from torchhys.operators.generalized_pi import GeneralizedPIInverse, GeneralizedPrandtlIshlinskii
from torchhys.registry import Searched, register_family

__all__ = ["fit_generalized_pi", "search_gpi"]


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


GPI_SAMPLE_ITERATIONS = 1e7
"""The ``gpi`` family's bound on L-BFGS iterations times fitted samples (its
``sample_iterations``)."""


def _gpi_iterations(epochs: int, work: float, scored: int) -> int:
    """The L-BFGS iterations of a ``gpi`` fit on ``scored`` samples."""
    return min(epochs, max(20, int(work / scored)))


def fit_key(spec: Mapping[str, Any], x: Tensor, warmup: int,
            mask: Tensor | None) -> dict[str, Any]:
    """The spec as it determines the fit on these data (for sharing fits between
    candidates, :mod:`torchhys.identification._fit_cache`): a ``gpi`` spec with ``epochs`` the
    iterations it runs on these samples and no ``sample_iterations`` (on a long record the
    spec with ``epochs: 200`` and the default one run the same fit); others as given."""
    key = dict(spec)
    if key.get("fit") == "gpi":
        scored, _ = _samples(x.reshape(-1, x.shape[-1]), warmup, mask)
        work = key.pop("sample_iterations", GPI_SAMPLE_ITERATIONS)
        key["epochs"] = _gpi_iterations(key.get("epochs", 1000), work, int(scored.sum()))
    return key


def _gpi(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"n_widths", "power", "ridge", "units", "epochs", "sample_iterations",
                 "direction"})
    n, power, direction = _grid(spec, 10)
    ridge = _penalty(spec, "ridge")
    units = check_int(spec.get("units", 4), "fit 'gpi': units", minimum=0)
    _check_columns(spec, n + units, f"n_widths={n} + units={units}")
    epochs = check_int(spec.get("epochs", 1000), "fit 'gpi': epochs", minimum=1)
    work = check_positive(spec.get("sample_iterations", GPI_SAMPLE_ITERATIONS),
                          "fit 'gpi': sample_iterations")

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        _check_columns(spec, n + units, f"n_widths={n} + units={units}", x.numel())
        scored, known = _samples(x, warmup, mask)
        sx, t = _standardized(x, y, scored)
        xs, ts = (x / sx)[scored], t[scored]
        t = t if float(((xs - xs.mean()) * ts).sum()) >= 0 else -t  # rising with x
        mx = float(x[scored].mean())  # the inverse route fits the centred input
        u, out = (x / sx, t) if direction == "direct" else (t, (x - mx) / sx)
        widths = play_width_grid(u[known], n, power=power)
        ridges = [ridge]
        if ridge == "auto":
            _, scores = select_pi_ridge(u, out, widths, PENALTIES, nonnegative=True,
                                        validation=_holdout(scored), mask=scored)
            # the local optimum of the fit depends on its start (the initial PI fit): if the
            # fit with the best ridge fails, the next best start it elsewhere
            ridges = sorted(scores, key=lambda r: scores[r])[:3]
        errors = []
        for r in ridges:
            try:
                return fitted(x, t, u, out, widths, r, sx, mx, scored, known)
            except (ValueError, FloatingPointError) as err:  # FitError, diverged, no inverse
                errors.append(f"ridge {r:g}: {err}")
                if isinstance(err, NoBetterThanLine) and err.on_the_line:
                    errors.append("the fit ended on the line: no other start tried")
                    break
        raise FitError(f"gpi ({direction}): " + "; ".join(errors))

    def fitted(x: Tensor, t: Tensor, u: Tensor, out: Tensor, widths: Tensor, r: float,
               sx: float, mx: float, scored: Tensor, known: Tensor) -> nn.Module:
        iterations = _gpi_iterations(epochs, work, int(scored.sum()))
        m = fit_generalized_pi(u, out, widths, units=units, ridge=r, lbfgs_epochs=iterations,
                               mask=scored)
        pw, w, w0, a, c, b, s, off = (v.detach() for v in m.parameters_effective())
        if direction == "direct":  # the same model of the physical input x
            return _checked(GeneralizedPrandtlIshlinskii(
                pw * sx, w / sx, linear_weight=float(w0) / sx, centers=b, slopes=s,
                unit_weights=c, gain=float(a), offset=float(off)), x, t, scored, "the model")
        # The same model, rewritten for a well-conditioned inverse: the PI part divided by k
        # (its training std), g(k v) in its place, scaled by sx and shifted by mx so that it
        # maps to the physical input. g^-1 is bounded to the PI part's training
        # range with a margin of half its span on each side.
        with torch.no_grad():
            p = m.prandtl_ishlinskii()(u)[0]
        k = float(p[known].std().clamp_min(1e-300))
        scaled = GeneralizedPrandtlIshlinskii(
            pw, w / k, linear_weight=float(w0) / k, centers=b / k, slopes=s * k,
            unit_weights=c * sx, gain=float(a) * k * sx, offset=float(off) * sx + mx)
        return _checked(scaled.bounded_inverse(u[known], pi_output=(p / k)[known]), x, t,
                        scored, "the inverse")

    if direction == "direct":
        placeholder: nn.Module = GeneralizedPrandtlIshlinskii(
            torch.arange(1, n + 1) / n, centers=torch.zeros(units))
    else:
        placeholder = GeneralizedPIInverse(n, units)
    return placeholder.requires_grad_(False), fit


# --- the search -----------------------------------------------------------------------------
def _rising(x: Tensor, y: Tensor, warmup: int, end: int) -> float:
    """+1 if the target rises with the input on the scored samples before ``end``, else -1."""
    xs, ys = x[:, warmup:end], y[:, warmup:end]
    return 1.0 if float(((xs - xs.mean()) * ys).sum()) >= 0 else -1.0


def _gpi_fit(x: Tensor, y: Tensor, warmup: int, inverse: bool, n: int, power: float,
             ridge: float, units: int, end: int, epochs: int) -> Callable[[Tensor], Tensor]:
    """Generalized PI model of t = sign x target from the input, fitted on samples [0, end)
    of every row, or the inverse of one of the input from t; ``sign`` makes t rise with the
    input."""
    sign = _rising(x, y, warmup, end)
    t = sign * y[:, :end]
    u, out = (t, x[:, :end]) if inverse else (x[:, :end], t)
    model = fit_generalized_pi(u, out, play_width_grid(u, n, power=power), units=units,
                               ridge=ridge, lbfgs_epochs=epochs, warmup=warmup)
    if not inverse:
        return lambda v: sign * model(v)[0]
    exact = model.bounded_inverse(u)  # g^-1 within the PI part's training range +- half
    return lambda v: sign * exact(v)[0]


def search_gpi(x: Tensor, y: Tensor, warmup: int, cut: int, *, n_widths: Sequence[int],
               powers: Sequence[float], units: Sequence[int], epochs: int) -> Searched:
    """The ``gpi`` family's search: :func:`fit_generalized_pi` of the target times the sign
    that makes it rise with the input, in either direction (the inverse: the exact inverse
    bounded to the PI part's training range plus half its span on each side), on the widths
    and ridge the ``pi_nonneg`` search chooses for that direction and sign; the direction
    and the number of tanh ``units`` with the least RMS error on the hold-out, each fitted
    on the samples before it (a fit that diverges or has no inverse is passed over); then
    refitted on every sample, the next best setting where that refit diverges.

    Args:
        x, y, warmup, cut: as
            :func:`~torchhys.identification.prandtl_ishlinskii.search_pi_nonneg`'s.
        n_widths, powers: the grids of the PI part's widths.
        units: the grid of tanh units.
        epochs: L-BFGS iterations of each fit.

    Raises:
        FloatingPointError: every setting's refit diverged.
    """
    sign = _rising(x, y, warmup, cut)
    candidates = []
    for inverse, (_, n, power, ridge) in (
            (False, _pi_choice(x, y, warmup, cut, n_widths, powers, True, sign)),
            (True, _inverse_pi_choice(x, y, warmup, cut, n_widths, powers, sign))):
        for k in units if n else ():
            try:
                score = holdout_rmse(_gpi_fit(x, y, warmup, inverse, n, power, ridge, k, cut,
                                              epochs), x, y, cut)
            except (FloatingPointError, ValueError):  # diverged, or no inverse
                continue
            candidates.append((score, inverse, n, power, ridge, k))
    end = x.shape[1]
    for skipped, (score, inverse, n, power, ridge, k) in enumerate(sorted(candidates)):
        try:  # the best candidate whose refit on every sample converges
            f = _gpi_fit(x, y, warmup, inverse, n, power, ridge, k, end, epochs)
        except FloatingPointError:
            continue
        options = {"fit": "gpi", "direction": "inverse" if inverse else "direct",
                   "n_widths": n, "power": power, "ridge": ridge, "units": k,
                   "epochs": epochs, "sign": _rising(x, y, warmup, end)}
        return Searched(score, options, f, skipped)
    raise FloatingPointError("every generalized PI candidate diverged")


register_family("gpi", _gpi, search=search_gpi)
