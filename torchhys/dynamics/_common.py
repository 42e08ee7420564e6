"""Shared pieces of the linear dynamic blocks: argument checks, carried states, the input
layout of multi-input blocks and the stable second-order-section parametrization."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from torchhys._checks import (
    as_batched_sequence,
    check_finite,
    check_floating,
    check_tensor,
)


def radius(value: float, name: str) -> float:
    """``value`` as a float in (0, 1), else a ValueError naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
        raise ValueError(f"{name} must be a float in (0, 1), got {value!r}")
    return float(value)


def start(state: Tensor | None, xb: Tensor, shape: int | tuple[int, ...]) -> Tensor | None:
    """The carried state as (batch, *shape) in x's dtype: None, ``shape`` or
    ``(batch, *shape)``, with batch ``xb.shape[0]``."""
    if state is None:
        return None
    if not isinstance(state, Tensor):
        raise TypeError(f"state must be a torch.Tensor or None, got {type(state).__name__}")
    check_floating(state, "state")
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    B = xb.shape[0]
    if state.shape not in (torch.Size(shape), torch.Size((B, *shape))):
        raise ValueError(f"state must have shape {shape} or {(B, *shape)} for batch {B}, got "
                         f"shape {tuple(state.shape)}")
    check_finite(state, "state")
    return state.to(xb.dtype).expand((B, *shape))


def batched_inputs(x: Tensor, n_inputs: int, name: str = "x") -> tuple[Tensor, bool]:
    """Check the input of a block with ``n_inputs`` inputs and return it as (batch, time, m).

    One input: x (time,) or (batch, time). m > 1 inputs: x (time, m) or (batch, time, m).

    Returns:
        The tensor as (batch, time, m) and whether a batch dimension was added.
    """
    if n_inputs == 1:
        xb, squeezed = as_batched_sequence(x, name)
        return xb.unsqueeze(-1), squeezed
    check_tensor(x, name)
    check_floating(x, name)
    if x.dim() not in (2, 3) or x.shape[-1] != n_inputs:
        raise ValueError(f"{name} must have shape (time, n_inputs) or (batch, time, n_inputs) "
                         f"with n_inputs = {n_inputs}, got shape {tuple(x.shape)}")
    if x.shape[-2] == 0:
        raise ValueError(f"{name} must hold at least one sample, got shape {tuple(x.shape)}")
    check_finite(x, name)
    return (x.unsqueeze(0), True) if x.dim() == 2 else (x, False)


def as_float64(v: object, name: str, dims: int | None = None) -> np.ndarray:
    """``v`` (a tensor, array or sequence) as a float64 array; ``dims`` dimensions if given."""
    arr = np.asarray(v.detach().cpu() if isinstance(v, Tensor) else v, dtype=np.float64)
    if (dims is not None and arr.ndim != dims) or arr.size == 0:
        want = "non-empty" if dims is None else f"non-empty with {dims} dimension(s)"
        raise ValueError(f"{name} must be {want}, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


# --- second-order sections -----------------------------------------------------------------------


def section_parameters(a1: Tensor, a2: Tensor, r: float) -> tuple[Tensor, Tensor]:
    """(alpha, beta) of sections ``1 + a1 z^-1 + a2 z^-2`` with poles inside radius r."""
    c2 = a2 / r**2
    return torch.atanh(c2), torch.atanh(a1 / r / (1 + c2))


def initial_sections(order: int, r: float, dtype: torch.dtype
                     ) -> tuple[Tensor, Tensor, Tensor]:
    """(alpha (n2,), beta (n2,), gamma (order % 2,)) in ``dtype``: poles of modulus 0.5
    spread in angle (the blocks' initialization)."""
    n2 = order // 2
    angles = torch.arange(1, n2 + 1, dtype=torch.float64) * math.pi / (2 * n2 + 2)
    alpha, beta = section_parameters(-torch.cos(angles), torch.full((n2,), 0.25), r)
    pole = torch.full((order % 2,), 0.5, dtype=dtype)  # a first-order section's real pole
    return alpha.to(dtype), beta.to(dtype), torch.atanh(-pole / r)


def section_polynomial(alpha: Tensor, beta: Tensor, gamma: Tensor, r: float) -> Tensor:
    """The denominator ``a`` (..., order + 1), ``a[..., 0] = 1``: the product of the sections.

    ``c2 = tanh(alpha)``, ``a1 = r (1 + c2) tanh(beta)``, ``a2 = r^2 c2`` for each
    second-order section (alpha, beta (..., n2)), ``r tanh(gamma)`` for a first-order one
    (gamma (..., order % 2)).
    """
    c2 = torch.tanh(alpha)
    a1, a2 = r * (1 + c2) * torch.tanh(beta), r**2 * c2
    a = torch.ones((*alpha.shape[:-1], 1), dtype=alpha.dtype, device=alpha.device)
    sections = [(a1[..., i], a2[..., i]) for i in range(a1.shape[-1])]
    sections += [(r * torch.tanh(gamma[..., i]),) for i in range(gamma.shape[-1])]
    for s in sections:
        # a * (1 + s[0] z^-1 + ...), the coefficients of a product of polynomials
        a = F.pad(a, (0, len(s))) + sum(F.pad(c.unsqueeze(-1) * a, (k + 1, len(s) - k - 1))
                                        for k, c in enumerate(s))
    return a


# --- from coefficients ----------------------------------------------------------------------------


def causal_rational(b: object, a: object, where: str = "") -> tuple[np.ndarray, np.ndarray]:
    """``(b, a)`` as 1-D float64 arrays; ValueError unless finite, non-empty and ``a[0] != 0``.
    ``where`` prefixes the messages (the entry of a matrix)."""
    bn, an = as_float64(b, f"{where}b", 1), as_float64(a, f"{where}a", 1)
    if an[0] == 0:
        raise ValueError(f"{where}a[0] must be non-zero: with a[0] = 0 the output y[t] would "
                         f"not be defined by past outputs (a non-causal block), got a = {an}")
    return bn, an


def padded(bn: np.ndarray, an: np.ndarray, order: int, feedthrough: bool, where: str = ""
           ) -> tuple[np.ndarray, np.ndarray]:
    """``(b, a) / a[0]``, zero-padded to ``order + 1``; ``b[0] = 0`` checked without
    feedthrough."""
    bn = np.pad(bn, (0, order + 1 - len(bn))) / an[0]
    an = np.pad(an, (0, order + 1 - len(an))) / an[0]
    if not feedthrough and bn[0] != 0:
        raise ValueError(f"{where}b[0] must be 0 without feedthrough, got b[0] = {bn[0]:.6g}")
    return bn, an


def stable_poles(an: np.ndarray, where: str = "") -> tuple[np.ndarray, float]:
    """The roots of ``an`` and their largest modulus; ValueError if one is on or outside the
    unit circle."""
    poles = np.roots(an)
    m = float(np.abs(poles).max()) if len(poles) else 0.0
    if m >= 1:
        worst = poles[np.abs(poles).argmax()]
        raise ValueError(f"{where}a is not stable: it has a pole of magnitude {m:.6g} (at "
                         f"{worst:.6g}); poles must lie strictly inside the unit circle")
    return poles, m


def pole_radius(max_pole_radius: float | None, m: float) -> float:
    """The bound r kept in training: ``max(0.999, (1 + m) / 2)`` by default; it must exceed
    the largest pole modulus m."""
    r = max(0.999, (1 + m) / 2) if max_pole_radius is None else max_pole_radius
    if radius(r, "max_pole_radius") <= m:
        raise ValueError(f"max_pole_radius must exceed the largest pole magnitude {m:.6g},"
                         f" got {r!r}")
    return float(r)


def pole_sections(poles: np.ndarray, order: int, r: float) -> tuple[Tensor, Tensor, Tensor]:
    """(alpha, beta, gamma), float64, of sections with these ``order`` poles (complex
    conjugates together, real ones paired in ascending order, a leftover real one first
    order)."""
    pairs = sorted(poles[poles.imag > 0], key=lambda p: (abs(p), p.imag))
    real = np.sort(poles[poles.imag == 0].real)
    twos = real[: len(real) // 2 * 2].reshape(-1, 2)
    a1 = [-2 * p.real for p in pairs] + list(-twos.sum(1))
    a2 = [abs(p) ** 2 for p in pairs] + list(twos.prod(1))
    alpha, beta = section_parameters(torch.tensor(a1, dtype=torch.float64),
                                     torch.tensor(a2, dtype=torch.float64), r)
    gamma = torch.tensor(-real[-1:] / r if order % 2 else [], dtype=torch.float64).atanh()
    return alpha, beta, gamma
