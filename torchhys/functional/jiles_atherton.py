"""The Jiles-Atherton model driven by the flux density: B (input) -> H (output).

The Jiles-Atherton (JA) model of a ferromagnetic core relates the field H, the magnetization
M and the flux density ``B = mu0 (H + M)`` through five parameters: the saturation
magnetization ``ms``, the anhysteretic shape ``a``, the pinning ``k``, the inter-domain
coupling ``alpha`` and the reversible share ``c``::

    He   = H + alpha M                               effective field
    Man  = ms L(He / a),  L(z) = coth z - 1/z        anhysteretic magnetization (Langevin)
    Mirr = (M - c Man) / (1 - c)                     irreversible magnetization
    dMirr/dHe = (Man - Mirr) / (k delta)             if delta (Man - Mirr) > 0, else 0
    dM/dH = X / (1 - alpha X),   X = (1 - c) dMirr/dHe + c dMan/dHe

with ``delta = sign(dH)`` (= sign(dB): B rises with H). For a compensator the flux is the
input: this module integrates ``dH/dB = 1 / (mu0 (1 + dM/dH))`` in B with H as the state, M
read from the state as ``B / mu0 - H`` (the inverse JA model of Sadowski et al.; the field,
small beside M in a soft core, is the integrated quantity, so the integration error is
relative to H). Each sample is ``substeps`` explicit Euler steps of equal size along the
straight path from the previous sample; the direction ``delta`` is that of the sample step.

Two guards keep every parameter value a valid model: ``X`` is clipped at 0 from below (it
is >= 0 for physical parameters), and ``1 - alpha X`` at 0.01 (where it
reaches 0 the susceptibility is infinite and the field stalls: ``dH/dB`` ~ 0).

The state ``(b, h)`` is the last sample's flux density and field; ``(0, 0)`` is the
demagnetised core. Units: B in tesla and H in A/m with the default ``mu0`` (4 pi 1e-7
H/m); for other units give ``mu0`` in (input unit) / (output unit).

References:
    D. C. Jiles and D. L. Atherton, "Theory of ferromagnetic hysteresis", Journal of
    Magnetism and Magnetic Materials 61, 1986; N. Sadowski, N. J. Batistela, J. P. A. Bastos
    and M. Lajoie-Mazenc, "An inverse Jiles-Atherton model to take into account hysteresis
    in time-stepping finite-element calculations", IEEE Transactions on Magnetics 38(2),
    2002; R. Szewczyk, "Computational problems connected with Jiles-Atherton model of
    magnetic hysteresis", Advances in Intelligent Systems and Computing 267, 2014.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["MU0", "jiles_atherton", "jiles_atherton_step", "langevin", "langevin_slope"]

MU0 = 4e-7 * math.pi
"""The magnetic constant in H/m (T per A/m)."""


def langevin(z: Tensor) -> Tensor:
    """``L(z) = coth z - 1/z`` (0 at 0, odd, -> +-1), elementwise; z (...) -> (...).

    A Taylor series for |z| < 0.1 (below it the closed form cancels in float32)."""
    small = z.abs() < 0.1
    zs = torch.where(small, torch.ones_like(z), z)  # no 1/0 in either branch or its gradient
    z2 = z * z
    series = z * (1 / 3 - z2 * (1 / 45 - z2 * (2 / 945)))
    return torch.where(small, series, 1 / torch.tanh(zs) - 1 / zs)


def langevin_slope(z: Tensor) -> Tensor:
    """``L'(z) = 1/z^2 - 1/sinh^2 z`` (1/3 at 0), elementwise; z (...) -> (...); a Taylor
    series for |z| < 0.1."""
    small = z.abs() < 0.1
    zs = torch.where(small, torch.ones_like(z), z)
    # 1/sinh^2 z = 4 e^(-2|z|) / (1 - e^(-2|z|))^2: no overflow for large |z|
    e = torch.exp(-2 * zs.abs())
    z2 = z * z
    series = 1 / 3 - z2 * (1 / 15 - z2 * (2 / 189))
    return torch.where(small, series, 1 / (zs * zs) - 4 * e / (1 - e) ** 2)


def _field_slope(b: Tensor, h: Tensor, direction: Tensor, ms: Tensor, a: Tensor, k: Tensor,
                 alpha: Tensor, c: Tensor, mu0: float) -> Tensor:
    """``dH/dB`` at the state (b, h) on a branch of the given direction (+-1)."""
    m = b / mu0 - h
    z = (h + alpha * m) / a
    man = ms * langevin(z)
    mirr = (m - c * man) / (1 - c)
    gap = man - mirr
    irreversible = torch.where(direction * gap > 0, direction * gap / k, torch.zeros_like(gap))
    x = ((1 - c) * irreversible + c * (ms / a) * langevin_slope(z)).clamp_min(0)
    chi = x / (1 - alpha * x).clamp_min(0.01)
    return 1 / (mu0 * (1 + chi))


def jiles_atherton_step(b: Tensor, b_prev: Tensor, h_prev: Tensor, ms: Tensor, a: Tensor,
                        k: Tensor, alpha: Tensor, c: Tensor, mu0: float,
                        substeps: int) -> Tensor:
    """One sample: the field at flux density ``b`` from the state ``(b_prev, h_prev)``.

    Shapes: b, b_prev, h_prev (...); the parameters broadcast against them. Returns h (...).
    Scriptable: the sequence path and the streaming step call it.
    """
    db = (b - b_prev) / substeps
    direction = torch.where(db >= 0, torch.ones_like(db), -torch.ones_like(db))
    h = h_prev
    bs = b_prev
    for _ in range(substeps):
        h = h + _field_slope(bs, h, direction, ms, a, k, alpha, c, mu0) * db
        bs = bs + db
    return h


def jiles_atherton(b: Tensor, ms: Tensor, a: Tensor, k: Tensor, alpha: Tensor, c: Tensor, *,
                   mu0: float = MU0, substeps: int = 2,
                   state: tuple[Tensor, Tensor] | None = None
                   ) -> tuple[Tensor, tuple[Tensor, Tensor]]:
    """The field H along a flux-density sequence B (the inverse Jiles-Atherton model).

    Args:
        b: flux density, (batch, time).
        ms, a, k, alpha, c: the JA parameters (positive; ``0 < c < 1``), 0-dim or (batch,).
        mu0: input units per output unit of free space (4 pi 1e-7 for T and A/m).
        substeps: Euler steps per sample (>= 1).
        state: ``(b, h)`` before the first sample, each (batch,); None: ``(0, 0)``, the
            demagnetised core.

    Returns:
        h (batch, time) and the state ``(b, h)`` at the last sample.

    The loop over time is a Python loop (each step depends on the last); it is meant for the
    short records of quasi-static B-H loops, and differentiable in every argument.
    """
    if state is None:
        b_prev, h_prev = b.new_zeros(b.shape[0]), b.new_zeros(b.shape[0])
    else:
        b_prev, h_prev = state
    out = []
    for b_t in b.unbind(1):
        h_prev = jiles_atherton_step(b_t, b_prev, h_prev, ms, a, k, alpha, c, mu0, substeps)
        b_prev = b_t
        out.append(h_prev)
    return torch.stack(out, 1), (b_prev, h_prev)
