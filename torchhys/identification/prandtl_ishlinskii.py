"""The Prandtl-Ishlinskii families of the configs, identified on the training split (the
least squares they run: :mod:`torchhys.identification.fitting`):

- ``{"fit": "plays", "n": 16, "power": 1.0, "span_fraction": 1.0, "learnable": False}``:
  :class:`torchhys.Backlash` of the input, full widths
  ``span_fraction * span(x_train) (k / n)^power``, ``k = 1..n`` (or explicit ``widths``:
  nothing to fit);
- ``{"fit": "pi_ls", "n_widths": 30, "power": 3.0, "ridge": 0.0, "learnable": False}``:
  the least-squares Prandtl-Ishlinskii model of the target from the input
  (:func:`torchhys.identification.fitting.fit_prandtl_ishlinskii` on
  :func:`~torchhys.identification.fitting.play_width_grid`);
- ``{"fit": "pi_nonneg", "n_widths": 10, "power": 2.0, "ridge": "auto",
  "direction": "direct"}``: a Prandtl-Ishlinskii model with non-negative weights
  (:func:`torchhys.identification.fitting.fit_prandtl_ishlinskii` with
  ``nonnegative=True``) of the target from the input (``direct``), or of the input from the
  target, then its exact inverse
  (``inverse``). Such a model draws loops of one orientation only, so the target's sign is
  chosen by the training fit (both signs are fitted).

Their searches (:data:`torchhys.registry.SEARCHES`, the real-data benchmark's rows):
:func:`search_pi_nonneg` chooses the direction, the target's sign, the number of widths, the
grid power and the ridge on a time-ordered hold-out, :func:`search_pi_ls` the number of
widths, the power and the ridge.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import check_int, check_nonnegative, check_positive
from torchhys.identification._family_spec import (
    PENALTIES,
    Fitter,
    _check_columns,
    _grid,
    _holdout,
    _keys,
    _penalty,
    holdout_rmse,
    holdout_share,
)
from torchhys.identification.errors import FitError, _checked, _rmse, _samples, _standardized
from torchhys.identification.fitting import fit_prandtl_ishlinskii, play_width_grid, select_pi_ridge
from torchhys.operators.backlash import Backlash
from torchhys.operators.generalized_pi import GeneralizedPIInverse, GeneralizedPrandtlIshlinskii
from torchhys.operators.prandtl_ishlinskii import PrandtlIshlinskii
from torchhys.registry import Searched, register_family

__all__ = ["search_pi_ls", "search_pi_nonneg"]


def _positive_int(spec: Mapping[str, Any], key: str, default: int) -> int:
    return check_int(spec.get(key, default), f"fit {spec['fit']!r}: {key}", minimum=1)


def _flag(spec: Mapping[str, Any], key: str) -> bool:
    value = spec.get(key, False)
    if not isinstance(value, bool):
        raise ValueError(f"fit {spec['fit']!r}: {key} must be true or false, got {value!r}")
    return value


def _known(x: Tensor, mask: Tensor | None) -> Tensor:
    """The samples of x (batch, time) in ``mask`` (None: all)."""
    return x if mask is None else x[mask]


def _plays(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter | None]:
    _keys(spec, {"n", "power", "span_fraction", "learnable", "widths"})
    learnable = _flag(spec, "learnable")
    if spec.get("widths") is not None:
        widths = torch.as_tensor(spec["widths"], dtype=torch.get_default_dtype())
        return Backlash(widths, learnable=learnable), None
    n = _positive_int(spec, "n", 16)
    power = check_positive(spec.get("power", 1.0), "fit 'plays': power")
    fraction = check_positive(spec.get("span_fraction", 1.0), "fit 'plays': span_fraction")

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        return Backlash(fraction * play_width_grid(_known(x, mask), n, power=power),
                        learnable=learnable)

    return Backlash(torch.arange(1, n + 1) / n, learnable=learnable), fit


register_family("plays", _plays)


def _pi_ls(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"n_widths", "power", "ridge", "learnable"})
    n = _positive_int(spec, "n_widths", 30)
    power = check_positive(spec.get("power", 3.0), "fit 'pi_ls': power")
    ridge = check_nonnegative(spec.get("ridge", 0.0), "fit 'pi_ls': ridge")
    learnable = _flag(spec, "learnable")

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        widths = play_width_grid(_known(x, mask), n, power=power)
        return fit_prandtl_ishlinskii(x, y, widths, ridge=ridge, learnable=learnable,
                                      warmup=warmup, mask=mask)

    placeholder = PrandtlIshlinskii(torch.arange(1, n + 1) / n, torch.zeros(n),
                                    learnable=learnable)
    return placeholder, fit


def _pi_fit(u: Tensor, out: Tensor, widths: Tensor, ridge: float | str,
            scored: Tensor) -> PrandtlIshlinskii:
    if ridge == "auto":
        ridge, _ = select_pi_ridge(u, out, widths, PENALTIES, nonnegative=True,
                                   validation=_holdout(scored), mask=scored)
    return fit_prandtl_ishlinskii(u, out, widths, ridge=ridge, mask=scored, nonnegative=True)


def _pi_nonneg(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"n_widths", "power", "ridge", "direction"})
    n, power, direction = _grid(spec, 10)
    ridge = _penalty(spec, "ridge")

    def one_sign(x: Tensor, t: Tensor, sx: float, scored: Tensor, known: Tensor) -> nn.Module:
        """The PI model of t from x (physical input units)."""
        if direction == "direct":
            m = _pi_fit(x / sx, t, play_width_grid((x / sx)[known], n, power=power), ridge,
                        scored)
            return PrandtlIshlinskii(m.get_widths() * sx, m.weights / sx,
                                     linear_weight=float(m.linear_weight) / sx)
        # the forward model of the centred, scaled input (a PI model has no offset), and its
        # exact inverse after the input map (x - mx) / sx: a GeneralizedPIInverse whose g is
        # the affine map sx v + mx
        mx = float(x[scored].mean())
        forward = _pi_fit(t, (x - mx) / sx, play_width_grid(t[known], n, power=power), ridge,
                          scored)
        try:
            return GeneralizedPrandtlIshlinskii(
                forward.get_widths(), forward.weights, centers=[], gain=sx, offset=mx,
                linear_weight=float(forward.linear_weight)).inverse()
        except ValueError as err:
            raise FitError(f"pi_nonneg inverse: {err}") from None

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        _check_columns(spec, n, f"n_widths={n}", x.numel())
        scored, known = _samples(x, warmup, mask)
        sx, t = _standardized(x, y, scored)
        fits = []
        for sign in (1.0, -1.0):
            try:
                m = one_sign(x, sign * t, sx, scored, known)
            except FitError:
                continue
            with torch.no_grad():
                m.weights.mul_(sign)
                m.linear_weight.mul_(sign)
            fits.append((_rmse(m, x, t, scored), sign, m))
        if not fits:
            raise FitError(f"pi_nonneg ({direction}): no invertible fit of either sign")
        rmse, _, m = min(fits, key=lambda f: f[0])
        return _checked(m, x, t, scored, "pi_nonneg", rmse=rmse)

    placeholder: nn.Module = (PrandtlIshlinskii(torch.arange(1, n + 1) / n, torch.zeros(n))
                              if direction == "direct" else GeneralizedPIInverse(n, 0))
    return placeholder, fit


# --- the searches ---------------------------------------------------------------------------
Choice = tuple[float, int, float, float]
"""(hold-out RMSE, number of widths, grid power, ridge); n = 0: no candidate."""


def _pi_choice(x: Tensor, y: Tensor, warmup: int, cut: int, n_widths: Sequence[int],
               powers: Sequence[float], nonnegative: bool, sign: float = 1.0) -> Choice:
    """The best PI model of ``sign`` x target from the input (ridge by ``select_pi_ridge``
    over :data:`PENALTIES`)."""
    best = (math.inf, 0, 0.0, 0.0)
    for n in n_widths:
        for power in powers:
            widths = play_width_grid(x, n, power=power)
            ridge, scores = select_pi_ridge(x, sign * y, widths, PENALTIES,
                                            nonnegative=nonnegative,
                                            validation=holdout_share(x, cut), warmup=warmup)
            best = min(best, (scores[ridge], n, power, ridge))
    return best


def _inverse_pi(x: Tensor, y: Tensor, warmup: int, sign: float, n: int, power: float,
                ridge: float, end: int) -> Callable[[Tensor], Tensor]:
    """``sign`` x the exact inverse of the non-negative PI model of the input from ``sign`` x
    target, fitted on samples [warmup, end) of every row (widths from the span there)."""
    t = sign * y[:, :end]
    forward = fit_prandtl_ishlinskii(t, x[:, :end], play_width_grid(t, n, power=power),
                                     ridge=ridge, warmup=warmup, nonnegative=True)
    inverse = forward.inverse()
    return lambda v: sign * inverse(v)[0]


def _inverse_pi_choice(x: Tensor, y: Tensor, warmup: int, cut: int, n_widths: Sequence[int],
                       powers: Sequence[float], sign: float) -> Choice:
    """The best exact inverse of a non-negative PI model of the input from ``sign`` x target
    (every ridge of :data:`PENALTIES` scored on the hold-out)."""
    best = (math.inf, 0, 0.0, 0.0)
    for n in n_widths:
        for power in powers:
            for ridge in PENALTIES:
                try:
                    f = _inverse_pi(x, y, warmup, sign, n, power, ridge, cut)
                except ValueError:  # no strictly increasing loading curve: no inverse
                    continue
                best = min(best, (holdout_rmse(f, x, y, cut), n, power, ridge))
    return best


def search_pi_nonneg(x: Tensor, y: Tensor, warmup: int, cut: int, *,
                     n_widths: Sequence[int], powers: Sequence[float]) -> Searched:
    """The ``pi_nonneg`` family's search: the direction (``direct``: of the target from the
    input; ``inverse``: of the input from the target, then its exact inverse), the target's
    sign (a non-negative model draws loops of one orientation), the number of widths, the
    grid power and the ridge (:data:`PENALTIES`) with the least RMS error on the hold-out,
    each fitted on the samples before it; then refitted on every sample.

    Args:
        x, y: input and target, (rows, time).
        warmup: leading samples of each row neither fitted nor scored.
        cut: the hold-out's first sample in every row.
        n_widths, powers: the grids of the number of widths and of the grid power
            (:func:`~torchhys.identification.fitting.play_width_grid`).
    """
    best = min((_pi_choice(x, y, warmup, cut, n_widths, powers, True, sign), False, sign)
               for sign in (1.0, -1.0))
    best = min(best, *((_inverse_pi_choice(x, y, warmup, cut, n_widths, powers, sign), True,
                        sign) for sign in (1.0, -1.0)))
    (score, n, power, ridge), inverse, sign = best
    options = {"fit": "pi_nonneg", "direction": "inverse" if inverse else "direct",
               "n_widths": n, "power": power, "ridge": ridge, "sign": sign}
    if inverse:
        return Searched(score, options, _inverse_pi(x, y, warmup, sign, n, power, ridge,
                                                    x.shape[1]))
    model = fit_prandtl_ishlinskii(x, sign * y, play_width_grid(x, n, power=power),
                                   ridge=ridge, warmup=warmup, nonnegative=True)
    return Searched(score, options, lambda v: sign * model(v)[0])


def search_pi_ls(x: Tensor, y: Tensor, warmup: int, cut: int, *,
                 n_widths: Sequence[int], powers: Sequence[float]) -> Searched:
    """The ``pi_ls`` family's search: the number of widths, the grid power and the ridge
    (:data:`PENALTIES`) with the least RMS error on the hold-out (arguments as
    :func:`search_pi_nonneg`'s); then refitted on every sample."""
    score, n, power, ridge = _pi_choice(x, y, warmup, cut, n_widths, powers, nonnegative=False)
    model = fit_prandtl_ishlinskii(x, y, play_width_grid(x, n, power=power), ridge=ridge,
                                   warmup=warmup)
    return Searched(score, {"fit": "pi_ls", "n_widths": n, "power": power, "ridge": ridge},
                    lambda v: model(v)[0])


register_family("pi_ls", _pi_ls, search=search_pi_ls)
register_family("pi_nonneg", _pi_nonneg, search=search_pi_nonneg)
