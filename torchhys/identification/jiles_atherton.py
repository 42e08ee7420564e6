"""Identification of the Jiles-Atherton model: :func:`fit_jiles_atherton`
(Levenberg-Marquardt from several starts) and the Euler step count, :func:`substeps_for`, and
the ``jiles_atherton`` family of the configs.

``{"fit": "jiles_atherton", "mu0": 4e-7 pi, "starts": 8, "iterations": 60,
"substeps": None}``: :func:`torchhys.fit_jiles_atherton`, the inverse Jiles-Atherton model
of a magnetic core (the input the flux density B, the target the field H), fitted to the
target in its physical units (``mu0``: input units per target unit of free space, the
default for B in T and H in A/m). ``substeps`` (Euler steps per sample; None: enough that
a sample step of the 0.99 quantile moves the input by at most 1/32 of its range, so that
a few large jumps do not multiply the cost).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_int,
    check_positive,
    check_same_shape,
    check_warmup,
    fitted_samples,
)
from torchhys.functional.jiles_atherton import MU0, jiles_atherton
from torchhys.identification._family_spec import Fitter, _keys
from torchhys.identification.errors import FitError, _checked, _samples, _standardized
from torchhys.operators.jiles_atherton import JilesAtherton
from torchhys.registry import register_family

__all__ = ["fit_jiles_atherton", "substeps_for"]


def substeps_for(x: Tensor, resolution: int = 32, quantile: float = 1.0) -> int:
    """Euler steps per sample so that a sample step of x (rows, time) (its largest, or the
    given quantile of the absolute steps) moves x by at most 1/resolution of its range; at
    most 64."""
    span = float(x.max() - x.min())
    if x.shape[-1] < 2 or not span > 0:
        return 1
    step = float(torch.quantile(x.diff(dim=-1).abs().flatten(), quantile))
    return max(1, min(64, math.ceil(step * resolution / span)))


def fit_jiles_atherton(x: Tensor, y: Tensor, *, warmup: int = 0, mu0: float = MU0,
                       substeps: int | None = None, starts: int = 8, iterations: int = 60,
                       seed: int = 0, mask: Tensor | None = None) -> JilesAtherton:
    """Fit an inverse Jiles-Atherton model ``y = H[x]`` (B -> H) by least squares.

    Levenberg-Marquardt on the logarithms of the parameters (forward-difference Jacobians)
    from ``starts`` random starts scaled to the data (``ms`` from the largest |B|, ``a`` and
    ``k`` from the largest |H|), all starts in one batched run; the start with the least
    training error is returned. Every row runs from the demagnetised state; the first
    ``warmup`` samples of each row run the state but are not fitted.

    Args:
        x: flux density B, (time,) or (rows, time).
        y: field H, the shape of x.
        warmup: leading samples left out of the fit, in [0, time).
        mu0: as for :class:`JilesAtherton` (units).
        substeps: Euler steps per sample; None: enough that one step moves B by at most
            1/32 of its range (at most 64).
        starts, iterations: random starts and Levenberg-Marquardt iterations of each.
        seed: the starts' random generator seed.
        mask: the samples to fit, bool, the shape of ``x`` (False: left out of the fit, the
            state still runs through them, e.g. a held-out block or a shorter row's
            padding); None: every sample (after ``warmup`` in both cases).

    Returns:
        The fitted :class:`JilesAtherton` (float64 parameters).

    Raises:
        ValueError: shapes, non-finite values, a bad warmup, constant x or y, y falling
            with x, or no start with a finite error.
    """
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, xb, "y", "x")
    T = xb.shape[1]
    check_warmup(warmup, T)
    mu0 = check_positive(mu0, "mu0")
    starts = check_int(starts, "starts", minimum=1)
    iterations = check_int(iterations, "iterations", minimum=1)
    xb, yb = xb.to(torch.float64), yb.to(torch.float64)
    fitted = fitted_samples(mask, (xb.shape[0], T), warmup).to(xb.device)
    known = fitted_samples(mask, (xb.shape[0], T), 0).to(xb.device)  # the warm-up's too
    bmax, hmax = float(xb.abs().max()), float(yb[known].abs().max())
    xs, ys = xb[fitted], yb[fitted]  # the fitted samples
    if not (float(xb.std()) > 0 and float(ys.std()) > 0):
        raise ValueError("x and y must vary (a constant record has no loop to fit)")
    if float(((xs - xs.mean()) * (ys - ys.mean())).sum()) <= 0:
        raise ValueError("y must rise with x (the field H rises with the flux density B along "
                         "a loop), but it falls: check the sign of y, and that x is B and y H")
    K = substeps_for(xb) if substeps is None else check_int(substeps, "substeps", minimum=1)
    R = xb.shape[0]
    target = ys.reshape(-1)

    def losses(theta: Tensor) -> tuple[Tensor, Tensor]:
        """Residuals (P, n) and mean squared errors (P,) of P parameter rows (P, 5)."""
        P = theta.shape[0]
        p = theta.repeat_interleave(R, 0)
        ms, a, k, alpha = p[:, :4].exp().unbind(1)
        h, _ = jiles_atherton(xb.repeat(P, 1), ms, a, k, alpha, torch.sigmoid(p[:, 4]),
                              mu0=mu0, substeps=K)
        r = h.reshape(P, R, T)[:, fitted] - target
        mse = r.square().mean(1)
        return r, torch.where(torch.isfinite(mse), mse, torch.full_like(mse, math.inf))

    g = torch.Generator().manual_seed(seed)

    def uniform(lo: float, hi: float) -> Tensor:
        return lo + (hi - lo) * torch.rand(starts, generator=g, dtype=torch.float64)

    ms0 = bmax / mu0 * uniform(1.05, 1.6)
    a0, k0 = hmax * uniform(0.02, 0.5), hmax * uniform(0.02, 0.5)
    theta = torch.stack([ms0.log(), a0.log(), k0.log(), (a0 / ms0 * uniform(0.1, 3.0)).log(),
                         uniform(-4.0, 1.0)], 1)
    # log-parameters stay where exp() is a positive float64 and the logit where c is in
    # (0, 1): a degenerate optimum (no coupling, no pinning) is a small positive value
    lo = torch.tensor([-600.0] * 4 + [-30.0], dtype=torch.float64)
    hi = torch.tensor([600.0] * 4 + [30.0], dtype=torch.float64)
    eye, step = torch.eye(5, dtype=torch.float64), 1e-6
    with torch.no_grad():
        _, loss = losses(theta)
        damping = torch.full((starts,), 1e-3, dtype=torch.float64)
        for _ in range(iterations):
            probes = torch.cat([theta.unsqueeze(1) + step * eye, theta.unsqueeze(1)], 1)
            rp, _ = losses(probes.reshape(-1, 5))
            rp = rp.reshape(starts, 6, -1)
            J = ((rp[:, :5] - rp[:, 5:]) / step).transpose(1, 2)  # (starts, n, 5)
            r = rp[:, 5]
            A = J.transpose(1, 2) @ J
            grad = (J.transpose(1, 2) @ r.unsqueeze(2)).squeeze(2)
            scale = torch.diagonal(A, dim1=1, dim2=2).clamp_min(1e-12)
            system = A + damping[:, None, None] * torch.diag_embed(scale)
            delta = -torch.linalg.solve(system, grad.unsqueeze(2)).squeeze(2)
            delta = torch.where(torch.isfinite(delta), delta, torch.zeros_like(delta))
            moved = torch.minimum(torch.maximum(theta + delta, lo), hi)
            _, trial = losses(moved)
            better = trial < loss
            theta = torch.where(better[:, None], moved, theta)
            loss = torch.where(better, trial, loss)
            damping = torch.where(better, damping / 3, damping * 4).clamp(1e-12, 1e12)
            if bool((damping >= 1e12).all()):
                break
    best = int(loss.argmin())
    if not math.isfinite(float(loss[best])):
        raise ValueError("no Jiles-Atherton fit with a finite error: check the units (mu0) "
                         "and that x is the flux density and y the field")
    ms, a, k, alpha = (float(v) for v in theta[best, :4].exp())
    c = float(torch.sigmoid(theta[best, 4]))
    return JilesAtherton(ms, a, k, alpha, min(max(c, 1e-13), 1 - 1e-13), mu0=mu0, substeps=K)


def _substeps(x: Tensor) -> int:
    """Euler steps per sample from the 0.99 quantile of the sample steps
    (:func:`~torchhys.identification.jiles_atherton.substeps_for`). The largest steps are left
    out: a few jumps would set the count (and the cost of every fit) for all samples."""
    return substeps_for(x, quantile=0.99)


def _jiles_atherton(spec: Mapping[str, Any]) -> tuple[nn.Module, Fitter]:
    _keys(spec, {"mu0", "starts", "iterations", "substeps"})
    mu0 = check_positive(spec.get("mu0", MU0), "fit 'jiles_atherton': mu0")
    starts = check_int(spec.get("starts", 8), "fit 'jiles_atherton': starts", minimum=1)
    iterations = check_int(spec.get("iterations", 60), "fit 'jiles_atherton': iterations",
                           minimum=1)
    substeps = spec.get("substeps")
    if substeps is not None:
        substeps = check_int(substeps, "fit 'jiles_atherton': substeps", minimum=1)

    def fit(x: Tensor, y: Tensor, warmup: int, mask: Tensor | None = None) -> nn.Module:
        scored, _ = _samples(x, warmup, mask)
        _, t = _standardized(x, y, scored)
        try:
            m = fit_jiles_atherton(x, y, warmup=warmup, mask=mask, mu0=mu0, starts=starts,
                                   iterations=iterations,
                                   substeps=_substeps(x) if substeps is None else substeps)
        except (ValueError, torch.linalg.LinAlgError) as err:
            raise FitError(f"jiles_atherton: {err}") from None
        ys = y[scored]
        return _checked(m, x, t, scored, "jiles_atherton", float(ys.mean()), float(ys.std()))

    return JilesAtherton(mu0=mu0).requires_grad_(False), fit


register_family("jiles_atherton", _jiles_atherton)
