"""Recursive updates of an affine readout's weights from one new (features, target) pair: the
recursive least squares (RLS) and normalized least-mean-squares (NLMS) steps of an adaptive
compensator.

Each is one pure tensor function of a batch of rows, with no data-dependent Python control
flow (a skipped update is a ``torch.where``; no keyword-only arguments), so the same step
runs eagerly, under TorchScript and through the exporters' graph. Each row's update is
skipped (its weights and covariance kept) where:

- a feature or the target is NaN or inf;
- the prediction error is within the dead zone (``|e| <= dead_zone``: noise);
- the features have not changed since the last pair (``|z - z_prev|_inf <= excitation``): a
  still period carries no information, and RLS's covariance would wind up over it.

An applied update keeps the weights within a box around a reference (the offline fit):
``|w - w_ref| <= bound`` elementwise. RLS's covariance is bounded by its trace: a
covariance whose trace exceeds ``trace_max`` is scaled down to it (the forgetting factor
cannot blow it up however long the excitation lapses).
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["nlms_update", "rls_update"]


def _skip(z: Tensor, z_prev: Tensor, target: Tensor, e: Tensor, dead_zone: float,
          excitation: float) -> Tensor:
    """(batch,) bool: the rows whose update is applied."""
    finite = (z - z).eq(0).all(-1) & (target - target).eq(0)
    moved = (z - z_prev).abs().amax(-1) > excitation
    return finite & moved & (e.abs() > dead_zone)


def rls_update(w: Tensor, P: Tensor, z: Tensor, z_prev: Tensor, target: Tensor,
               w_ref: Tensor, bound: Tensor, forgetting: float = 1.0, dead_zone: float = 0.0,
               excitation: float = 0.0, trace_max: float = float("inf"),
               ) -> tuple[Tensor, Tensor, Tensor]:
    """One RLS step of the readout ``target ~ z . w``.

    Args:
        w: weights (batch, m); P: covariance (batch, m, m); z: features (batch, m); z_prev:
            the features of the last pair (batch, m); target: (batch,).
        w_ref, bound: the box ``|w - w_ref| <= bound`` (each (m,) or (batch, m)).
        forgetting: lambda in (0, 1]: the weight of a pair decays as lambda^age (1: plain
            least squares).
        dead_zone, excitation, trace_max: the skip rules and the covariance bound (module
            docstring).

    Returns:
        ``(w, P, applied)``: the new weights and covariance, and (batch,) bool, the rows
        updated.

    With ``forgetting=1``, no skip and no bound, ``n`` steps from ``w0``, ``P0 = I / delta``
    give the ridge solution ``argmin sum (t_i - z_i . w)^2 + delta |w - w0|^2``.
    """
    e = target - (z * w).sum(-1)
    ok = _skip(z, z_prev, target, e, dead_zone, excitation)
    Pz = torch.matmul(P, z.unsqueeze(-1)).squeeze(-1)
    denom = forgetting + (z * Pz).sum(-1, keepdim=True)
    inv = 1.0 / denom
    w_new = w + Pz * (e.unsqueeze(-1) * inv)
    # (P - Pz Pz^T / denom) / forgetting: symmetric bit for bit where P is (Pz_i Pz_j ==
    # Pz_j Pz_i), so no symmetrization pass
    P_new = (P - (Pz.unsqueeze(-1) * Pz.unsqueeze(-2)) * inv.unsqueeze(-1)) * (1.0 / forgetting)
    trace = torch.diagonal(P_new, dim1=-2, dim2=-1).sum(-1)
    scale = torch.where(trace > trace_max, trace_max / trace, torch.ones_like(trace))
    P_new = P_new * scale.unsqueeze(-1).unsqueeze(-1)
    w_new = torch.minimum(torch.maximum(w_new, w_ref - bound), w_ref + bound)
    okw = ok.unsqueeze(-1)
    return (torch.where(okw, w_new, w), torch.where(okw.unsqueeze(-1), P_new, P), ok)


def nlms_update(w: Tensor, z: Tensor, z_prev: Tensor, target: Tensor, w_ref: Tensor,
                bound: Tensor, step: float = 0.5, eps: float = 1e-6, dead_zone: float = 0.0,
                excitation: float = 0.0) -> tuple[Tensor, Tensor]:
    """One NLMS step of the readout ``target ~ z . w``: ``w + step e z / (eps + |z|^2)``,
    state O(m) (RLS's is O(m^2)); the skip rules and the box as :func:`rls_update`'s.

    Returns:
        ``(w, applied)``.
    """
    e = target - (z * w).sum(-1)
    ok = _skip(z, z_prev, target, e, dead_zone, excitation)
    gain = step * e / (eps + z.square().sum(-1))
    w_new = w + gain.unsqueeze(-1) * z
    w_new = torch.minimum(torch.maximum(w_new, w_ref - bound), w_ref + bound)
    return torch.where(ok.unsqueeze(-1), w_new, w), ok
