"""The symbolic tensors of :mod:`torchhys.deploy.casadi`: a :class:`Sym` is a numpy object
array of CasADi ``SX`` scalars with the torch dtype it stands for (CasADi computes in
float64 only: an int64 or a bool tensor holds whole numbers, resp. 0 and 1), and the helpers
that the translations (:mod:`torchhys.deploy.casadi._ops`) build on: operands as arrays,
elementwise maps with numpy's broadcasting, the selects and the casts."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


class Unsupported(ValueError):
    """A translation refuses these arguments (named with the operation, as a missing one)."""


def casadi() -> Any:
    """The ``casadi`` module, or ImportError naming the extra that installs it."""
    try:
        import casadi as ca
    except ImportError:
        raise ImportError('the CasADi export needs casadi: pip install "torchhys[casadi]"'
                          ) from None
    return ca


@dataclass
class Sym:
    """A tensor of symbolic elements: ``a`` a numpy object array of ``SX`` (1x1), ``dtype``
    the torch dtype of the tensor it stands for."""

    a: np.ndarray
    dtype: torch.dtype

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.a.shape)


def objects(elements: list[Any], shape: tuple[int, ...]) -> np.ndarray:
    """A numpy object array of ``shape`` holding ``elements`` in row-major order (filled
    element by element: numpy must not look into a CasADi matrix)."""
    out = np.empty(len(elements), dtype=object)
    for i, e in enumerate(elements):
        out[i] = e
    return out.reshape(shape)


def as_array(v: Any) -> Any:
    """An operand as a numpy object array of SX (a known tensor's values and a Python
    number as constants)."""
    ca = casadi()
    if isinstance(v, Sym):
        return v.a
    if isinstance(v, torch.Tensor):
        flat = v.detach().to(torch.float64).reshape(-1).tolist()
        return objects([ca.SX(x) for x in flat], tuple(v.shape))
    if isinstance(v, (bool, int, float)):  # a 0-dim array: numpy must not see a bare SX
        return objects([ca.SX(float(v))], ())
    return v


def dtype_of(v: Any) -> torch.dtype:
    if isinstance(v, (Sym, torch.Tensor)):
        return v.dtype
    if isinstance(v, bool):
        return torch.bool
    return torch.int64 if isinstance(v, int) else torch.float64


def elementwise(fn: Callable[..., Any], spec: Any, *operands: Any) -> Sym:
    """``fn`` of the operands' elements, broadcast as numpy (and torch) broadcast, as a
    :class:`Sym` of ``spec``'s dtype and shape."""
    arrays = [as_array(v) for v in operands]
    out = np.frompyfunc(fn, len(arrays), 1)(*arrays)
    out = np.asarray(out, dtype=object) if isinstance(out, np.ndarray) else objects([out], ())
    shape = tuple(spec.shape)
    if out.shape != shape:
        out = np.broadcast_to(out, shape).copy()
    return Sym(out, spec.dtype)


def select(c: Any, a: Any, b: Any) -> Any:
    """``c ? a : b`` of SX scalars (CasADi's ``if_else``: the unselected branch's NaN or inf
    does not leak, as torch.where's)."""
    return casadi().if_else(c, a, b)


def trunc(x: Any) -> Any:
    """Rounding toward zero (CasADi has floor and ceil)."""
    ca = casadi()
    return ca.if_else(x < 0, ca.ceil(x), ca.floor(x))


def cast(x: Sym, dtype: torch.dtype) -> Sym:
    """``x`` as torch casts it to ``dtype``: to bool nonzero, a float to an integer toward
    zero, otherwise the same numbers."""
    ca = casadi()
    if dtype == x.dtype:
        return x
    if dtype == torch.bool:
        return Sym(apply(lambda e: ca.ne(e, 0), x.a), dtype)
    if not dtype.is_floating_point and x.dtype.is_floating_point:
        return Sym(apply(trunc, x.a), dtype)
    return Sym(x.a, dtype)


def apply(fn: Callable[[Any], Any], a: np.ndarray) -> np.ndarray:
    """``fn`` of each element of the object array ``a`` (any shape, 0-dim included)."""
    return objects([fn(e) for e in a.flat], a.shape)


def sx(a: np.ndarray) -> np.ndarray:
    """``a`` with its Python numbers (a reduction's empty sum) made SX constants."""
    ca = casadi()
    return apply(lambda e: e if isinstance(e, ca.SX) else ca.SX(float(e)), a)


def finite(e: Any) -> Any:
    """1 where the SX scalar ``e`` is finite, 0 where NaN or inf: ``fabs(e) < inf`` (false
    for NaN), which CasADi keeps (its ``e - e`` is simplified to 0)."""
    ca = casadi()
    return ca.fabs(e) < ca.inf


def shaped(a: Any, spec: Any) -> Sym:
    """``a`` (an object array, or the bare element numpy returns for a 0-dim result) as a
    Sym of ``spec``'s shape and dtype."""
    a = a if isinstance(a, np.ndarray) else objects([a], ())
    return Sym(sx(a.astype(object).reshape(tuple(spec.shape))), spec.dtype)


def axis(d: int, n: int) -> int:
    """A dimension ``d`` of an ``n``-dimensional tensor, counted from 0."""
    return d + n if d < 0 else d
