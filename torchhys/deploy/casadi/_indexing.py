"""Indexing and sorting translations of :mod:`torchhys.deploy.casadi` (see
:mod:`torchhys.deploy.casadi._ops`). An index that depends on the sample (a ``gather``,
``index`` or ``scatter`` at a state's counter, a ``searchsorted`` of the sample) becomes a
sum of ``if_else`` over the positions it can take; a sort of symbolic values is one by
ranks."""

from __future__ import annotations

import functools
import math
import operator
from typing import Any

import numpy as np

from torchhys.deploy.casadi._pointwise import Translation
from torchhys.deploy.casadi._values import (
    Sym,
    Unsupported,
    as_array,
    axis,
    casadi,
    objects,
    select,
    shaped,
)


def _pick(values: list[Any], index: Any) -> Any:
    """``values[index]``: a known index (an SX constant) picks at once, a symbolic one sums
    ``if_else(index == j, values[j], 0)`` (0 where it is out of range)."""
    ca = casadi()
    if isinstance(index, ca.SX) and index.is_constant():
        k = int(float(ca.evalf(index)))
        return values[k] if -len(values) <= k < len(values) else ca.SX(math.nan)
    terms = [select(ca.eq(index, j), v, 0) for j, v in enumerate(values)]
    return functools.reduce(operator.add, terms) if terms else ca.SX(0)


def _gather(spec: Any, x: Any, dim: int, index: Any, *, sparse_grad: bool = False) -> Sym:
    a, idx = as_array(x), as_array(index)
    d = axis(dim, a.ndim)
    out = []
    for p in np.ndindex(idx.shape):
        line = a[p[:d] + (slice(None),) + p[d + 1:]] if a.ndim else a.reshape(1)
        out.append(_pick(list(line.flat), idx[p]))
    return shaped(objects(out, idx.shape), spec)


def _index_select(spec: Any, x: Any, dim: int, index: Any) -> Sym:
    a, idx = as_array(x), as_array(index).reshape(-1)
    d = axis(dim, max(a.ndim, 1))
    moved = np.moveaxis(a.reshape(a.shape or (1,)), d, -1)
    out = np.empty(moved.shape[:-1] + (len(idx),), dtype=object)
    for p in np.ndindex(moved.shape[:-1]):
        line = list(moved[p].flat)
        for k, i in enumerate(idx):
            out[p + (k,)] = _pick(line, i)
    return shaped(np.moveaxis(out, -1, d), spec)


def _scatter(spec: Any, x: Any, dim: int, index: Any, src: Any, **kwargs: Any) -> Sym:
    if kwargs.get("reduce") is not None:
        raise Unsupported("scatter with reduce has no CasADi translation")
    ca = casadi()
    a, idx, s = as_array(x).copy(), as_array(index), as_array(src)
    if not isinstance(s, np.ndarray):
        s = np.broadcast_to(objects([s], ()), idx.shape)
    d = axis(dim, a.ndim)
    for p in np.ndindex(idx.shape):
        i = idx[p]
        for j in range(a.shape[d]):
            q = p[:d] + (j,) + p[d + 1:]
            if isinstance(i, ca.SX) and i.is_constant():
                if int(float(ca.evalf(i))) == j:
                    a[q] = s[p]
            else:
                a[q] = select(ca.eq(i, j), s[p], a[q])
    return shaped(a, spec)


def _index(spec: Any, x: Any, indices: list) -> Sym:
    """``x[i0, i1, ...]`` with index tensors at consecutive dimensions (None: the whole
    dimension): their positions flattened into one and picked."""
    a = as_array(x)
    given = [k for k, i in enumerate(indices) if i is not None]
    if given != list(range(given[0], given[-1] + 1)):
        raise Unsupported("index tensors at dimensions apart have no CasADi translation")
    k0, k1 = given[0], given[-1] + 1
    idx = np.broadcast_arrays(*[as_array(indices[k]) for k in given])
    dims = a.shape[k0:k1]
    strides = [math.prod(dims[j + 1:]) for j in range(len(dims))]
    flat = a.reshape(a.shape[:k0] + (math.prod(dims),) + a.shape[k1:])
    moved = np.moveaxis(flat, k0, -1)
    out = np.empty(moved.shape[:-1] + idx[0].shape, dtype=object)
    for p in np.ndindex(moved.shape[:-1]):
        line = list(moved[p].flat)
        for q in np.ndindex(idx[0].shape):
            linear = sum((i[q] * st for i, st in zip(idx, strides, strict=True)), 0)
            out[p + q] = _pick(line, linear)
    n, rest = len(idx[0].shape), moved.ndim - 1  # the index's dimensions at k0
    return shaped(np.moveaxis(out, list(range(rest, rest + n)), list(range(k0, k0 + n))), spec)


def _searchsorted(spec: Any, seq: Any, values: Any, *, out_int32: bool = False,
                  right: bool = False, side: str | None = None, sorter: Any = None) -> Sym:
    """The number of the row's sorted values below each value (``<=`` with right)."""
    if sorter is not None:
        raise Unsupported("searchsorted with a sorter has no CasADi translation")
    ca = casadi()
    s, v = as_array(seq), as_array(values)
    below = ca.le if (right or side == "right") else ca.lt
    out = np.empty(v.shape, dtype=object)
    for p in np.ndindex(v.shape):
        row = s if s.ndim == 1 else s[p[:-1]]
        out[p] = functools.reduce(operator.add, [below(e, v[p]) for e in row.flat], ca.SX(0))
    return shaped(out, spec)


def _sort(spec: list, x: Any, dim: int = -1, descending: bool = False, *,
          stable: bool | None = None) -> list[Sym]:
    """Values and indices by rank: element i's rank is the number of elements before it
    (smaller, or equal and earlier: a stable sort), and position k sums ``if_else(rank_i
    == k, ...)`` over i (``n^2`` comparisons a line)."""
    ca = casadi()
    a = as_array(x)
    d = axis(dim, max(a.ndim, 1))
    moved = np.moveaxis(a.reshape(a.shape or (1,)), d, -1)
    values, indices = np.empty(moved.shape, dtype=object), np.empty(moved.shape, dtype=object)
    before = ca.gt if descending else ca.lt
    for p in np.ndindex(moved.shape[:-1]):
        line = list(moved[p].flat)
        ranks = [functools.reduce(operator.add, [
            before(e, f) if j > i else ca.logic_or(before(e, f), ca.eq(e, f))
            for j, e in enumerate(line) if j != i], ca.SX(0)) for i, f in enumerate(line)]
        for k in range(len(line)):
            hit = [ca.eq(r, k) for r in ranks]
            values[p + (k,)] = functools.reduce(
                operator.add, [select(h, f, 0) for h, f in zip(hit, line, strict=True)])
            indices[p + (k,)] = functools.reduce(
                operator.add, [select(h, i, 0) for i, h in enumerate(hit)])
    return [shaped(np.moveaxis(values, -1, d), spec[0]),
            shaped(np.moveaxis(indices, -1, d), spec[1])]


INDEXING: dict[str, Translation] = {
    "sort.default": _sort, "sort.stable": lambda s, x, *, stable=None, dim=-1,
    descending=False: _sort(s, x, dim, descending),
    "gather.default": _gather, "index_select.default": _index_select,
    "scatter.src": _scatter, "scatter.value": _scatter, "index.Tensor": _index,
    "searchsorted.Tensor": _searchsorted,
}
