"""One CasADi translation per aten operation, for :mod:`torchhys.deploy.casadi`.

:func:`translations` maps an op overload (``torch.ops.aten.addmm.default``) to
``translate(spec, *args, **kwargs)``: ``spec`` is the node's output as torch traced it (a
fake tensor of its dtype and shape, or a list of them), the arguments are the node's, a
symbolic tensor a :class:`~torchhys.deploy.casadi._values.Sym`, a known one a torch tensor
(a node whose tensors are all known is computed by torch, not here). It returns the output's
Sym (or a list). The tables: pointwise (:mod:`torchhys.deploy.casadi._pointwise`), views and
joins, reductions and products, normalisation, indexing (here). An index that depends on the
sample (a ``gather``, ``index`` or ``scatter`` at a state's counter, a ``searchsorted`` of
the sample) becomes a sum of ``if_else`` over the positions it can take.
"""

from __future__ import annotations

import functools
import math
import operator
from typing import Any

import numpy as np
import torch

from torchhys.deploy.casadi._pointwise import POINTWISE, Translation
from torchhys.deploy.casadi._values import (
    Sym,
    Unsupported,
    as_array,
    casadi,
    objects,
    select,
    sx,
)


def _sym(a: Any, spec: Any) -> Sym:
    """``a`` (an object array, or the bare element numpy returns for a 0-dim result) as a
    Sym of ``spec``'s shape and dtype."""
    a = a if isinstance(a, np.ndarray) else objects([a], ())
    return Sym(sx(a.astype(object).reshape(tuple(spec.shape))), spec.dtype)


def _dim(d: int, n: int) -> int:
    return d + n if d < 0 else d


# --- views and joins ----------------------------------------------------------------------


def _same_order(spec: Any, x: Any, *args: Any, **kwargs: Any) -> Sym:
    """A view that keeps the elements' row-major order: the output's shape."""
    return _sym(as_array(x), spec)


def _slice(spec: Any, x: Any, dim: int = 0, start: int | None = None, end: int | None = None,
           step: int = 1) -> Sym:
    a = as_array(x)
    index = [slice(None)] * a.ndim
    index[_dim(dim, a.ndim)] = slice(start, end, step)
    return _sym(a[tuple(index)], spec)


def _narrow(spec: Any, x: Any, dim: int, start: int, length: int) -> Sym:
    n = as_array(x).shape[_dim(dim, len(spec.shape))]
    start = _dim(start, n)
    return _slice(spec, x, dim, start, start + length)


def _select(spec: Any, x: Any, dim: int, index: int) -> Sym:
    a = as_array(x)
    return _sym(np.take(a, index, axis=_dim(dim, a.ndim)), spec)


def _pieces(spec: list, x: Any, *args: Any, dim: int | None = None, **kwargs: Any
            ) -> list[Sym]:
    """split / split_with_sizes / chunk / unbind: the pieces of ``spec``'s sizes along
    ``dim`` (the op's last positional argument where not given by name)."""
    a = as_array(x)
    if dim is None:
        dim = args[-1] if len(args) > 1 else 0
    d = _dim(dim, a.ndim)
    out, at = [], 0
    for s in spec:
        n = 1 if len(s.shape) < a.ndim else s.shape[d]
        piece = np.take(a, range(at, at + n), axis=d)
        out.append(_sym(piece, s))
        at += n
    return out


def _join(spec: Any, tensors: list, dim: int = 0, *, stack: bool = False) -> Sym:
    arrays = [as_array(t) for t in tensors]
    if stack:
        return _sym(np.stack(arrays, axis=_dim(dim, len(spec.shape))), spec)
    # torch's legacy rule: a 1-D empty tensor joins anything
    arrays = [a for a in arrays if not (a.ndim == 1 and a.shape[0] == 0)] or arrays[:1]
    return _sym(np.concatenate(arrays, axis=_dim(dim, arrays[0].ndim)), spec)


VIEWS: dict[str, Translation] = {
    **{n: _same_order for n in (
        "unsqueeze.default", "squeeze.default", "squeeze.dim", "squeeze.dims",
        "reshape.default", "view.default", "_unsafe_view.default", "unflatten.int",
        "flatten.using_ints", "alias.default", "clone.default", "contiguous.default",
        "detach.default", "lift_fresh_copy.default")},
    "slice.Tensor": _slice, "narrow.default": _narrow, "select.int": _select,
    "transpose.int": lambda s, x, d0, d1: _sym(np.swapaxes(as_array(x), d0, d1), s),
    "t.default": lambda s, x: _sym(as_array(x).T, s),
    "mT.default": lambda s, x: _sym(np.swapaxes(as_array(x), -1, -2), s),
    "numpy_T.default": lambda s, x: _sym(as_array(x).T, s),
    "permute.default": lambda s, x, dims: _sym(np.transpose(as_array(x), dims), s),
    "movedim.int": lambda s, x, a, b: _sym(np.moveaxis(as_array(x), a, b), s),
    "expand.default": lambda s, x, *a, **k: _sym(np.broadcast_to(as_array(x), s.shape), s),
    "expand_as.default": lambda s, x, o: _sym(np.broadcast_to(as_array(x), s.shape), s),
    **{n: _pieces for n in ("split.Tensor", "split_with_sizes.default", "chunk.default",
                            "unsafe_chunk.default", "unsafe_split.Tensor",
                            "unsafe_split_with_sizes.default", "tensor_split.sections",
                            "tensor_split.indices")},
    "unbind.int": lambda s, x, dim=0: _pieces(s, x, dim=dim),
    "reshape_as.default": _same_order, "view_as.default": _same_order,
    "flip.default": lambda s, x, dims: _sym(np.flip(as_array(x), axis=tuple(dims)), s),
    "diagonal.default": lambda s, x, offset=0, dim1=0, dim2=1: _sym(
        np.diagonal(as_array(x), offset, dim1, dim2), s),
    "cat.default": _join,
    "stack.default": lambda s, ts, dim=0: _join(s, ts, dim, stack=True),
}


# --- reductions and products ----------------------------------------------------------------


def _axes(dim: Any, ndim: int) -> tuple[int, ...]:
    if dim is None or (isinstance(dim, (list, tuple)) and len(dim) == 0):
        return tuple(range(ndim))
    dims = [dim] if isinstance(dim, int) else list(dim)
    return tuple(sorted({_dim(d, max(ndim, 1)) for d in dims}))


def _sum(spec: Any, x: Any, dim: Any = None, keepdim: bool = False, *, dtype: Any = None
         ) -> Sym:
    a = as_array(x)
    return _sym(np.sum(a, axis=_axes(dim, a.ndim), keepdims=keepdim), spec)


def _mean(spec: Any, x: Any, dim: Any = None, keepdim: bool = False, *, dtype: Any = None
          ) -> Sym:
    a = as_array(x)
    axes = _axes(dim, a.ndim)
    n = math.prod(a.shape[d] for d in axes)
    return _sym(np.sum(a, axis=axes, keepdims=keepdim) / n, spec)


def _extreme(fn_name: str) -> Translation:
    """amax / amin: ``fmax`` / ``fmin`` over the axes, one axis at a time."""
    def translate(spec: Any, x: Any, dim: Any = (), keepdim: bool = False) -> Sym:
        fn = np.frompyfunc(getattr(casadi(), fn_name), 2, 1)
        a = as_array(x)
        for d in sorted(_axes(dim, a.ndim), reverse=True):
            a = fn.reduce(a, axis=d, keepdims=keepdim)
            a = np.asarray(a, dtype=object) if isinstance(a, np.ndarray) else objects([a], ())
        return _sym(a, spec)
    return translate


def _cumsum(spec: Any, x: Any, dim: int, *, dtype: Any = None) -> Sym:
    a = as_array(x)
    return _sym(np.cumsum(a, axis=_dim(dim, a.ndim), dtype=object), spec)


def _matmul(spec: Any, a: Any, b: Any) -> Sym:
    return _sym(np.matmul(as_array(a), as_array(b)), spec)


def _addmm(spec: Any, bias: Any, m1: Any, m2: Any, *, beta: float = 1, alpha: float = 1
           ) -> Sym:
    prod = np.matmul(as_array(m1), as_array(m2))
    prod = prod if alpha == 1 else alpha * prod
    c = as_array(bias)
    return _sym((c if beta == 1 else beta * c) + prod, spec)


def _linear(spec: Any, x: Any, w: Any, b: Any = None) -> Sym:
    out = np.matmul(as_array(x), np.swapaxes(as_array(w), -1, -2))
    return _sym(out if b is None else out + as_array(b), spec)


def _logical(fn_name: str) -> Translation:
    """all / any: ``logic_and`` / ``logic_or`` over the axes (nonzero is true)."""
    def translate(spec: Any, x: Any, dim: Any = None, keepdim: bool = False) -> Sym:
        ca = casadi()
        fn = np.frompyfunc(getattr(ca, fn_name), 2, 1)
        a = np.frompyfunc(lambda e: ca.ne(e, 0), 1, 1)(as_array(x))
        a = np.asarray(a, dtype=object) if isinstance(a, np.ndarray) else objects([a], ())
        if a.ndim == 0:
            return _sym(a, spec)
        for d in sorted(_axes(dim, a.ndim), reverse=True):
            a = fn.reduce(a, axis=d, keepdims=keepdim)
            a = np.asarray(a, dtype=object) if isinstance(a, np.ndarray) else objects([a], ())
        return _sym(a, spec)
    return translate


PRODUCTS: dict[str, Translation] = {
    "all.default": _logical("logic_and"), "all.dim": _logical("logic_and"),
    "all.dims": _logical("logic_and"), "any.default": _logical("logic_or"),
    "any.dim": _logical("logic_or"), "any.dims": _logical("logic_or"),
    "sum.dim_IntList": _sum, "sum.default": lambda s, x, *, dtype=None: _sum(s, x),
    "mean.dim": _mean, "mean.default": lambda s, x, *, dtype=None: _mean(s, x),
    "amax.default": _extreme("fmax"), "amin.default": _extreme("fmin"),
    "cumsum.default": _cumsum,
    "matmul.default": _matmul, "mm.default": _matmul, "bmm.default": _matmul,
    "dot.default": _matmul, "mv.default": _matmul,
    "addmm.default": _addmm, "linear.default": _linear,
}


# --- normalisation ----------------------------------------------------------------------------


def _softmax(log: bool) -> Translation:
    def translate(spec: Any, x: Any, dim: int, half_to_float: bool = False) -> Sym:
        ca = casadi()
        a = as_array(x)
        d = _dim(dim, a.ndim)
        top = np.frompyfunc(ca.fmax, 2, 1).reduce(a, axis=d, keepdims=True)
        shifted = a - top
        e = np.frompyfunc(ca.exp, 1, 1)(shifted)
        total = np.sum(e, axis=d, keepdims=True)
        out = shifted - np.frompyfunc(ca.log, 1, 1)(total) if log else e / total
        return _sym(out, spec)
    return translate


def _layer_norm(spec: list, x: Any, shape: list[int], weight: Any = None, bias: Any = None,
                eps: float = 1e-5, cudnn_enable: bool = True) -> Sym:
    ca = casadi()
    a = as_array(x)
    axes = tuple(range(a.ndim - len(shape), a.ndim))
    n = math.prod(shape)
    mean = np.sum(a, axis=axes, keepdims=True) / n
    centred = a - mean
    var = np.sum(centred * centred, axis=axes, keepdims=True) / n
    out = centred * np.frompyfunc(lambda v: 1 / ca.sqrt(v + eps), 1, 1)(var)
    if weight is not None:
        out = out * as_array(weight)
    if bias is not None:
        out = out + as_array(bias)
    return _sym(out, spec)


def _rms_norm(spec: Any, x: Any, shape: list[int], weight: Any = None,
              eps: float | None = None) -> Sym:
    ca = casadi()
    a = as_array(x)
    axes = tuple(range(a.ndim - len(shape), a.ndim))
    eps = torch.finfo(spec.dtype).eps if eps is None else eps
    ms = np.sum(a * a, axis=axes, keepdims=True) / math.prod(shape)
    out = a * np.frompyfunc(lambda v: 1 / ca.sqrt(v + eps), 1, 1)(ms)
    return _sym(out if weight is None else out * as_array(weight), spec)


def _batch_norm(spec: Any, x: Any, weight: Any, bias: Any, mean: Any, var: Any,
                training: bool, momentum: float, eps: float, cudnn_enabled: bool) -> Sym:
    """An eval-mode batch norm: a per-channel (dimension 1) scale and shift."""
    ca = casadi()
    if training or mean is None or var is None:
        raise Unsupported("a batch norm in training mode (batch statistics) has no CasADi "
                          "translation: call model.eval() first")
    a = as_array(x)
    shape = (1, -1) + (1,) * (a.ndim - 2)
    inv = np.frompyfunc(lambda v: 1 / ca.sqrt(v + eps), 1, 1)(as_array(var)).reshape(shape)
    out = (a - as_array(mean).reshape(shape)) * inv
    if weight is not None:
        out = out * as_array(weight).reshape(shape)
    if bias is not None:
        out = out + as_array(bias).reshape(shape)
    return _sym(out, spec)


def _dropout(spec: Any, x: Any, p: float, train: bool | None) -> Sym:
    if train:
        raise Unsupported("dropout in training mode has no CasADi translation: call "
                          "model.eval() first")
    return _same_order(spec, x)


NORMS: dict[str, Translation] = {
    "rms_norm.default": _rms_norm, "batch_norm.default": _batch_norm,
    "dropout.default": _dropout,
    "log_sigmoid.default": lambda s, x: _sym(np.frompyfunc(
        lambda e: casadi().fmin(e, 0) - casadi().log1p(casadi().exp(-casadi().fabs(e))), 1,
        1)(as_array(x)), s),
    "softmax.int": _softmax(False), "_softmax.default": _softmax(False),
    "log_softmax.int": _softmax(True), "_log_softmax.default": _softmax(True),
    "layer_norm.default": _layer_norm,
}


# --- indexing ---------------------------------------------------------------------------------


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
    d = _dim(dim, a.ndim)
    out = []
    for p in np.ndindex(idx.shape):
        line = a[p[:d] + (slice(None),) + p[d + 1:]] if a.ndim else a.reshape(1)
        out.append(_pick(list(line.flat), idx[p]))
    return _sym(objects(out, idx.shape), spec)


def _index_select(spec: Any, x: Any, dim: int, index: Any) -> Sym:
    a, idx = as_array(x), as_array(index).reshape(-1)
    d = _dim(dim, max(a.ndim, 1))
    moved = np.moveaxis(a.reshape(a.shape or (1,)), d, -1)
    out = np.empty(moved.shape[:-1] + (len(idx),), dtype=object)
    for p in np.ndindex(moved.shape[:-1]):
        line = list(moved[p].flat)
        for k, i in enumerate(idx):
            out[p + (k,)] = _pick(line, i)
    return _sym(np.moveaxis(out, -1, d), spec)


def _scatter(spec: Any, x: Any, dim: int, index: Any, src: Any, **kwargs: Any) -> Sym:
    if kwargs.get("reduce") is not None:
        raise Unsupported("scatter with reduce has no CasADi translation")
    ca = casadi()
    a, idx, s = as_array(x).copy(), as_array(index), as_array(src)
    if not isinstance(s, np.ndarray):
        s = np.broadcast_to(objects([s], ()), idx.shape)
    d = _dim(dim, a.ndim)
    for p in np.ndindex(idx.shape):
        i = idx[p]
        for j in range(a.shape[d]):
            q = p[:d] + (j,) + p[d + 1:]
            if isinstance(i, ca.SX) and i.is_constant():
                if int(float(ca.evalf(i))) == j:
                    a[q] = s[p]
            else:
                a[q] = select(ca.eq(i, j), s[p], a[q])
    return _sym(a, spec)


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
    return _sym(np.moveaxis(out, list(range(rest, rest + n)), list(range(k0, k0 + n))), spec)


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
    return _sym(out, spec)


def _sort(spec: list, x: Any, dim: int = -1, descending: bool = False, *,
          stable: bool | None = None) -> list[Sym]:
    """Values and indices by rank: element i's rank is the number of elements before it
    (smaller, or equal and earlier: a stable sort), and position k sums ``if_else(rank_i
    == k, ...)`` over i (``n^2`` comparisons a line)."""
    ca = casadi()
    a = as_array(x)
    d = _dim(dim, max(a.ndim, 1))
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
    return [_sym(np.moveaxis(values, -1, d), spec[0]),
            _sym(np.moveaxis(indices, -1, d), spec[1])]


INDEXING: dict[str, Translation] = {
    "sort.default": _sort, "sort.stable": lambda s, x, *, stable=None, dim=-1,
    descending=False: _sort(s, x, dim, descending),
    "gather.default": _gather, "index_select.default": _index_select,
    "scatter.src": _scatter, "scatter.value": _scatter, "index.Tensor": _index,
    "searchsorted.Tensor": _searchsorted,
}


def _resolve(table: dict[str, Translation]) -> dict[Any, Translation]:
    """Op overloads of the names that this torch has."""
    out: dict[Any, Translation] = {}
    for name, fn in table.items():
        packet, overload = name.split(".")
        op = getattr(getattr(torch.ops.aten, packet, None), overload, None)
        if op is not None:
            out[op] = fn
    return out


@functools.cache
def translations() -> dict[Any, Translation]:
    """Every translation: op overload -> ``translate(spec, *args, **kwargs)``."""
    return {**_resolve({**POINTWISE(), **VIEWS, **PRODUCTS, **NORMS, **INDEXING}),
            operator.getitem: lambda spec, xs, i: xs[i]}


def is_symbolic(value: Any) -> bool:
    """Whether ``value`` (an argument, possibly nested) holds a symbolic tensor."""
    if isinstance(value, Sym):
        return True
    if isinstance(value, (list, tuple)):
        return any(is_symbolic(v) for v in value)
    if isinstance(value, dict):
        return any(is_symbolic(v) for v in value.values())
    return False


def zeros_for(value: Any) -> Any:
    """``value`` with each symbolic tensor replaced by zeros of its shape and dtype (for the
    ops whose result depends on shapes only)."""
    if isinstance(value, Sym):
        return torch.zeros(value.shape, dtype=value.dtype)
    if isinstance(value, (list, tuple)):
        return type(value)(zeros_for(v) for v in value)
    return value

