"""The conditions' polynomial basis: a tensor-product Legendre basis of conditions scaled to
[-1, 1] over their training ranges, and its products with a model's features (pure tensor
functions; multiplications and additions only, so the C and ONNX steps have them)."""

import itertools

import torch
from torch import Tensor

__all__ = ["condition_products", "legendre_basis", "scaled_conditions", "total_degree",
           "varying_range"]


def total_degree(n: int, degree: int) -> list[list[int]]:
    """The multi-indices of total degree <= ``degree`` in ``n`` variables, by degree (the
    constant first; none for ``n = 0``)."""
    if n == 0:
        return []
    out = [e for e in itertools.product(range(degree + 1), repeat=n) if sum(e) <= degree]
    return [list(e) for e in sorted(out, key=lambda e: (sum(e), tuple(-v for v in e)))]


def legendre_basis(c: Tensor, exponents: list[list[int]], degree: int) -> Tensor:
    """The tensor-product Legendre basis of scaled conditions ``c`` (..., n) in [-1, 1]:
    (..., len(exponents)), column k the product over i of ``P_{exponents[k][i]}(c_i)``
    (Bonnet's recurrence)."""
    per: list[list[Tensor]] = []
    for i in range(c.shape[-1]):
        ci = c[..., i]
        ps = [torch.ones_like(ci), ci]
        for k in range(1, degree):
            ps.append(((2 * k + 1) * ci * ps[k] - k * ps[k - 1]) / (k + 1))
        per.append(ps)
    cols: list[Tensor] = []
    for e in exponents:
        col = per[0][e[0]]
        for i in range(1, len(e)):
            col = col * per[i][e[i]]
        cols.append(col)
    return torch.stack(cols, -1)


def scaled_conditions(c: Tensor, low: Tensor, high: Tensor) -> Tensor:
    """Conditions ``c`` (..., n) mapped from [low, high] (n,) to [-1, 1]."""
    lo, hi = low.to(c.dtype), high.to(c.dtype)
    return 2 * (c - lo) / (hi - lo) - 1


def condition_products(features: Tensor, c: Tensor, exponents: list[list[int]],
                       degree: int) -> Tensor:
    """The products ``phi_j b_k`` of ``phi = [1, features...]`` and the basis ``b`` of the
    scaled conditions ``c`` (..., n), j-major, the constant ``phi_0 b_0`` left out:
    (..., (nf + 1) * nb - 1) of features (..., nf)."""
    b = legendre_basis(c, exponents, degree)
    phi = torch.cat([torch.ones_like(features[..., :1]), features], -1)
    prod = phi.unsqueeze(-1) * b.unsqueeze(-2)
    return prod.flatten(-2)[..., 1:]


def varying_range(c: Tensor, message: str) -> tuple[Tensor, Tensor]:
    """``(low, high)`` (n,) of conditions ``c`` (samples, n), each of which must vary: a
    constant column i is a ``ValueError`` of ``message.format(i=i, value=...)`` (a constant
    condition scales or schedules nothing)."""
    lo, hi = c.amin(0), c.amax(0)
    flat = [i for i in range(c.shape[-1]) if not bool(hi[i] > lo[i])]
    if flat:
        raise ValueError(message.format(i=flat[0], value=float(lo[flat[0]])))
    return lo, hi
