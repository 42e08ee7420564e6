"""One CasADi translation per aten operation, for :mod:`torchhys.deploy.casadi`.

:func:`translations` maps an op overload (``torch.ops.aten.addmm.default``) to
``translate(spec, *args, **kwargs)``: ``spec`` is the node's output as torch traced it (a
fake tensor of its dtype and shape, or a list of them), the arguments are the node's, a
symbolic tensor a :class:`~torchhys.deploy.casadi._values.Sym`, a known one a torch tensor
(a node whose tensors are all known is computed by torch, not here). It returns the output's
Sym (or a list). The tables: pointwise (:mod:`torchhys.deploy.casadi._pointwise`), views and
joins, reductions and products, normalisation (here), indexing and sorting
(:mod:`torchhys.deploy.casadi._indexing`).
"""

from __future__ import annotations

import functools
import math
import operator
from typing import Any

import numpy as np
import torch

from torchhys.deploy.casadi._indexing import INDEXING
from torchhys.deploy.casadi._pointwise import POINTWISE, Translation
from torchhys.deploy.casadi._values import (
    Sym,
    Unsupported,
    as_array,
    axis,
    casadi,
    objects,
    shaped,
)

# --- views and joins ----------------------------------------------------------------------


def _same_order(spec: Any, x: Any, *args: Any, **kwargs: Any) -> Sym:
    """A view that keeps the elements' row-major order: the output's shape."""
    return shaped(as_array(x), spec)


def _slice(spec: Any, x: Any, dim: int = 0, start: int | None = None, end: int | None = None,
           step: int = 1) -> Sym:
    a = as_array(x)
    index = [slice(None)] * a.ndim
    index[axis(dim, a.ndim)] = slice(start, end, step)
    return shaped(a[tuple(index)], spec)


def _narrow(spec: Any, x: Any, dim: int, start: int, length: int) -> Sym:
    n = as_array(x).shape[axis(dim, len(spec.shape))]
    start = axis(start, n)
    return _slice(spec, x, dim, start, start + length)


def _select(spec: Any, x: Any, dim: int, index: int) -> Sym:
    a = as_array(x)
    return shaped(np.take(a, index, axis=axis(dim, a.ndim)), spec)


def _pieces(spec: list, x: Any, *args: Any, dim: int | None = None, **kwargs: Any
            ) -> list[Sym]:
    """split / split_with_sizes / chunk / unbind: the pieces of ``spec``'s sizes along
    ``dim`` (the op's last positional argument where not given by name)."""
    a = as_array(x)
    if dim is None:
        dim = args[-1] if len(args) > 1 else 0
    d = axis(dim, a.ndim)
    out, at = [], 0
    for s in spec:
        n = 1 if len(s.shape) < a.ndim else s.shape[d]
        piece = np.take(a, range(at, at + n), axis=d)
        out.append(shaped(piece, s))
        at += n
    return out


def _join(spec: Any, tensors: list, dim: int = 0, *, stack: bool = False) -> Sym:
    arrays = [as_array(t) for t in tensors]
    if stack:
        return shaped(np.stack(arrays, axis=axis(dim, len(spec.shape))), spec)
    # torch's legacy rule: a 1-D empty tensor joins anything
    arrays = [a for a in arrays if not (a.ndim == 1 and a.shape[0] == 0)] or arrays[:1]
    return shaped(np.concatenate(arrays, axis=axis(dim, arrays[0].ndim)), spec)


VIEWS: dict[str, Translation] = {
    **{n: _same_order for n in (
        "unsqueeze.default", "squeeze.default", "squeeze.dim", "squeeze.dims",
        "reshape.default", "view.default", "_unsafe_view.default", "unflatten.int",
        "flatten.using_ints", "alias.default", "clone.default", "contiguous.default",
        "detach.default", "lift_fresh_copy.default")},
    "slice.Tensor": _slice, "narrow.default": _narrow, "select.int": _select,
    "transpose.int": lambda s, x, d0, d1: shaped(np.swapaxes(as_array(x), d0, d1), s),
    "t.default": lambda s, x: shaped(as_array(x).T, s),
    "mT.default": lambda s, x: shaped(np.swapaxes(as_array(x), -1, -2), s),
    "numpy_T.default": lambda s, x: shaped(as_array(x).T, s),
    "permute.default": lambda s, x, dims: shaped(np.transpose(as_array(x), dims), s),
    "movedim.int": lambda s, x, a, b: shaped(np.moveaxis(as_array(x), a, b), s),
    "expand.default": lambda s, x, *a, **k: shaped(np.broadcast_to(as_array(x), s.shape), s),
    "expand_as.default": lambda s, x, o: shaped(np.broadcast_to(as_array(x), s.shape), s),
    **{n: _pieces for n in ("split.Tensor", "split_with_sizes.default", "chunk.default",
                            "unsafe_chunk.default", "unsafe_split.Tensor",
                            "unsafe_split_with_sizes.default", "tensor_split.sections",
                            "tensor_split.indices")},
    "unbind.int": lambda s, x, dim=0: _pieces(s, x, dim=dim),
    "reshape_as.default": _same_order, "view_as.default": _same_order,
    "flip.default": lambda s, x, dims: shaped(np.flip(as_array(x), axis=tuple(dims)), s),
    "diagonal.default": lambda s, x, offset=0, dim1=0, dim2=1: shaped(
        np.diagonal(as_array(x), offset, dim1, dim2), s),
    "cat.default": _join,
    "stack.default": lambda s, ts, dim=0: _join(s, ts, dim, stack=True),
}


# --- reductions and products ----------------------------------------------------------------


def _axes(dim: Any, ndim: int) -> tuple[int, ...]:
    if dim is None or (isinstance(dim, (list, tuple)) and len(dim) == 0):
        return tuple(range(ndim))
    dims = [dim] if isinstance(dim, int) else list(dim)
    return tuple(sorted({axis(d, max(ndim, 1)) for d in dims}))


def _sum(spec: Any, x: Any, dim: Any = None, keepdim: bool = False, *, dtype: Any = None
         ) -> Sym:
    a = as_array(x)
    return shaped(np.sum(a, axis=_axes(dim, a.ndim), keepdims=keepdim), spec)


def _mean(spec: Any, x: Any, dim: Any = None, keepdim: bool = False, *, dtype: Any = None
          ) -> Sym:
    a = as_array(x)
    axes = _axes(dim, a.ndim)
    n = math.prod(a.shape[d] for d in axes)
    return shaped(np.sum(a, axis=axes, keepdims=keepdim) / n, spec)


def _extreme(fn_name: str) -> Translation:
    """amax / amin: ``fmax`` / ``fmin`` over the axes, one axis at a time."""
    def translate(spec: Any, x: Any, dim: Any = (), keepdim: bool = False) -> Sym:
        fn = np.frompyfunc(getattr(casadi(), fn_name), 2, 1)
        a = as_array(x)
        for d in sorted(_axes(dim, a.ndim), reverse=True):
            a = fn.reduce(a, axis=d, keepdims=keepdim)
            a = np.asarray(a, dtype=object) if isinstance(a, np.ndarray) else objects([a], ())
        return shaped(a, spec)
    return translate


def _cumsum(spec: Any, x: Any, dim: int, *, dtype: Any = None) -> Sym:
    a = as_array(x)
    return shaped(np.cumsum(a, axis=axis(dim, a.ndim), dtype=object), spec)


def _matmul(spec: Any, a: Any, b: Any) -> Sym:
    return shaped(np.matmul(as_array(a), as_array(b)), spec)


def _addmm(spec: Any, bias: Any, m1: Any, m2: Any, *, beta: float = 1, alpha: float = 1
           ) -> Sym:
    prod = np.matmul(as_array(m1), as_array(m2))
    prod = prod if alpha == 1 else alpha * prod
    c = as_array(bias)
    return shaped((c if beta == 1 else beta * c) + prod, spec)


def _linear(spec: Any, x: Any, w: Any, b: Any = None) -> Sym:
    out = np.matmul(as_array(x), np.swapaxes(as_array(w), -1, -2))
    return shaped(out if b is None else out + as_array(b), spec)


def _logical(fn_name: str) -> Translation:
    """all / any: ``logic_and`` / ``logic_or`` over the axes (nonzero is true)."""
    def translate(spec: Any, x: Any, dim: Any = None, keepdim: bool = False) -> Sym:
        ca = casadi()
        fn = np.frompyfunc(getattr(ca, fn_name), 2, 1)
        a = np.frompyfunc(lambda e: ca.ne(e, 0), 1, 1)(as_array(x))
        a = np.asarray(a, dtype=object) if isinstance(a, np.ndarray) else objects([a], ())
        if a.ndim == 0:
            return shaped(a, spec)
        for d in sorted(_axes(dim, a.ndim), reverse=True):
            a = fn.reduce(a, axis=d, keepdims=keepdim)
            a = np.asarray(a, dtype=object) if isinstance(a, np.ndarray) else objects([a], ())
        return shaped(a, spec)
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
        d = axis(dim, a.ndim)
        top = np.frompyfunc(ca.fmax, 2, 1).reduce(a, axis=d, keepdims=True)
        shifted = a - top
        e = np.frompyfunc(ca.exp, 1, 1)(shifted)
        total = np.sum(e, axis=d, keepdims=True)
        out = shifted - np.frompyfunc(ca.log, 1, 1)(total) if log else e / total
        return shaped(out, spec)
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
    return shaped(out, spec)


def _rms_norm(spec: Any, x: Any, shape: list[int], weight: Any = None,
              eps: float | None = None) -> Sym:
    ca = casadi()
    a = as_array(x)
    axes = tuple(range(a.ndim - len(shape), a.ndim))
    eps = torch.finfo(spec.dtype).eps if eps is None else eps
    ms = np.sum(a * a, axis=axes, keepdims=True) / math.prod(shape)
    out = a * np.frompyfunc(lambda v: 1 / ca.sqrt(v + eps), 1, 1)(ms)
    return shaped(out if weight is None else out * as_array(weight), spec)


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
    return shaped(out, spec)


def _dropout(spec: Any, x: Any, p: float, train: bool | None) -> Sym:
    if train:
        raise Unsupported("dropout in training mode has no CasADi translation: call "
                          "model.eval() first")
    return _same_order(spec, x)


NORMS: dict[str, Translation] = {
    "rms_norm.default": _rms_norm, "batch_norm.default": _batch_norm,
    "dropout.default": _dropout,
    "log_sigmoid.default": lambda s, x: shaped(np.frompyfunc(
        lambda e: casadi().fmin(e, 0) - casadi().log1p(casadi().exp(-casadi().fabs(e))), 1,
        1)(as_array(x)), s),
    "softmax.int": _softmax(False), "_softmax.default": _softmax(False),
    "log_softmax.int": _softmax(True), "_log_softmax.default": _softmax(True),
    "layer_norm.default": _layer_norm,
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

