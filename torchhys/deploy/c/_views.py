"""C templates of :mod:`torchhys.deploy.c` that move no arithmetic: views (a new
shape, strides and offset over the same array: no code), a copy into a contiguous local,
and the joins (``cat``, ``stack``). Registered in :mod:`torchhys.deploy.c._templates`."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from torchhys.deploy.c._writer import CTensor, Writer, constant, contiguous_strides

Emitter = Callable[..., Any]
Operand = CTensor | float | int | bool


# --- views: no code ---------------------------------------------------------------------------


def _dim(d: int, n: int) -> int:
    return d % n if n else 0


def _identity(w: Writer, spec: Any, x: CTensor, *args: Any, **kwargs: Any) -> CTensor:
    return x


def _unsqueeze(w: Writer, spec: CTensor, x: CTensor, dim: int) -> CTensor:
    d = _dim(dim, len(x.shape) + 1)
    return x.view(x.shape[:d] + (1,) + x.shape[d:], x.strides[:d] + (0,) + x.strides[d:],
                  x.offset)


def _squeeze(w: Writer, spec: CTensor, x: CTensor, dim: int | Sequence[int] | None = None
             ) -> CTensor:
    dims = range(len(x.shape)) if dim is None else [dim] if isinstance(dim, int) else dim
    drop = {_dim(d, len(x.shape)) for d in dims}
    keep = [d for d in range(len(x.shape)) if not (d in drop and x.shape[d] == 1)]
    return x.view([x.shape[d] for d in keep], [x.strides[d] for d in keep], x.offset)


def _narrow(w: Writer, spec: CTensor, x: CTensor, dim: int, start: int, length: int
            ) -> CTensor:
    d = _dim(dim, len(x.shape))
    start = start + x.shape[d] if start < 0 else start
    shape = list(x.shape)
    shape[d] = length
    return x.view(shape, x.strides, x.offset + start * x.strides[d])


def _select(w: Writer, spec: CTensor, x: CTensor, dim: int, index: int) -> CTensor:
    d = _dim(dim, len(x.shape))
    index = index + x.shape[d] if index < 0 else index
    return x.view(x.shape[:d] + x.shape[d + 1:], x.strides[:d] + x.strides[d + 1:],
                  x.offset + index * x.strides[d])


def _slice(w: Writer, spec: CTensor, x: CTensor, dim: int = 0, start: int | None = None,
           end: int | None = None, step: int = 1) -> CTensor:
    d = _dim(dim, len(x.shape))
    first, last, _ = slice(start, end).indices(x.shape[d])
    shape, strides = list(x.shape), list(x.strides)
    shape[d] = max(0, -(-(last - first) // step))
    strides[d] *= step
    return x.view(shape, strides, x.offset + first * x.strides[d])


def _split_sizes(w: Writer, spec: list, x: CTensor, sizes: Sequence[int], dim: int = 0
                 ) -> list[CTensor]:
    out, start = [], 0
    for n in sizes:
        out.append(_narrow(w, spec, x, dim, start, n))
        start += n
    return out


def _split(w: Writer, spec: list, x: CTensor, size: int, dim: int = 0) -> list[CTensor]:
    n = x.shape[_dim(dim, len(x.shape))]
    return _split_sizes(w, spec, x, [min(size, n - s) for s in range(0, n, size)], dim)


def _chunk(w: Writer, spec: list, x: CTensor, chunks: int, dim: int = 0) -> list[CTensor]:
    """torch.chunk: pieces of ``ceil(n / chunks)`` along ``dim``, the last one shorter (an
    LSTM's or a GRU's gates)."""
    n = x.shape[_dim(dim, len(x.shape))]
    return _split(w, spec, x, max(1, -(-n // chunks)), dim)


def _tensor_split(w: Writer, spec: list, x: CTensor, sections: int | Sequence[int],
                  dim: int = 0) -> list[CTensor]:
    """torch.tensor_split: ``sections`` pieces (the first ``n % sections`` one longer), or
    the pieces between the given indices."""
    n = x.shape[_dim(dim, len(x.shape))]
    if isinstance(sections, int):
        q, r = divmod(n, sections)
        return _split_sizes(w, spec, x, [q + (k < r) for k in range(sections)], dim)
    bounds = [min(max(i + n if i < 0 else i, 0), n) for i in sections]
    starts, ends = [0, *bounds], [*bounds, n]
    return [_narrow(w, spec, x, dim, a, max(0, b - a)) for a, b in zip(starts, ends,
                                                                        strict=True)]


def _unbind(w: Writer, spec: list, x: CTensor, dim: int = 0) -> list[CTensor]:
    d = _dim(dim, len(x.shape))
    return [_select(w, spec, x, d, i) for i in range(x.shape[d])]


def _permute(w: Writer, spec: CTensor, x: CTensor, dims: Sequence[int]) -> CTensor:
    order = [_dim(d, len(x.shape)) for d in dims]
    return x.view([x.shape[d] for d in order], [x.strides[d] for d in order], x.offset)


def _transpose(w: Writer, spec: CTensor, x: CTensor, d0: int, d1: int) -> CTensor:
    order = list(range(len(x.shape)))
    a, b = _dim(d0, len(x.shape)), _dim(d1, len(x.shape))
    order[a], order[b] = order[b], order[a]
    return _permute(w, spec, x, order)


def _expand(w: Writer, spec: CTensor, x: CTensor, size: Sequence[int], *, implicit: bool = False
            ) -> CTensor:
    lead = len(size) - len(x.shape)
    shape = [int(n) if d < lead or n != -1 else x.shape[d - lead] for d, n in enumerate(size)]
    strides = [0 if d < lead or x.shape[d - lead] != shape[d] else x.strides[d - lead]
               for d in range(len(size))]
    return x.view(shape, strides, x.offset)


def _flip(w: Writer, spec: CTensor, x: CTensor, dims: Sequence[int]) -> CTensor:
    strides, offset = list(x.strides), x.offset
    for d in {_dim(d, len(x.shape)) for d in dims}:
        offset += (x.shape[d] - 1) * strides[d]
        strides[d] = -strides[d]
    return x.view(x.shape, strides, offset)


def _movedim(w: Writer, spec: CTensor, x: CTensor, source: int | Sequence[int],
             destination: int | Sequence[int]) -> CTensor:
    n = len(x.shape)
    src = [_dim(d, n) for d in ([source] if isinstance(source, int) else source)]
    dst = [_dim(d, n) for d in ([destination] if isinstance(destination, int) else destination)]
    rest = iter(d for d in range(n) if d not in src)
    placed = dict(zip(dst, src, strict=True))
    return _permute(w, spec, x, [placed[d] if d in placed else next(rest) for d in range(n)])


def _diagonal(w: Writer, spec: CTensor, x: CTensor, offset: int = 0, dim1: int = 0,
              dim2: int = 1) -> CTensor:
    """torch.diagonal: ``dim1`` and ``dim2`` dropped, their diagonal (``offset`` above the
    main one when > 0, below when < 0) appended as the last dim."""
    n = len(x.shape)
    a, b = _dim(dim1, n), _dim(dim2, n)
    start = x.offset + (offset * x.strides[b] if offset >= 0 else -offset * x.strides[a])
    size = max(0, min(x.shape[a] - max(-offset, 0), x.shape[b] - max(offset, 0)))
    rest = [d for d in range(n) if d not in (a, b)]
    return x.view([x.shape[d] for d in rest] + [size],
                  [x.strides[d] for d in rest] + [x.strides[a] + x.strides[b]],
                  start if size else x.offset)


def _dropout(w: Writer, spec: CTensor, x: CTensor, p: float = 0.5, train: bool | None = False
             ) -> CTensor:
    """Dropout of a module in eval mode: ``x``; in training mode (random) no template."""
    if train:
        raise ValueError("dropout in training mode has no template (call model.eval() first)")
    return x


def copy(w: Writer, x: CTensor) -> CTensor:
    """``x`` into a new contiguous local."""
    out = w.local(x.dtype, x.shape)
    w.assign(out, lambda idx: w.read(x, idx))
    return out


def _reshape(w: Writer, spec: CTensor, x: CTensor, *args: Any) -> CTensor:
    if not x.is_contiguous():
        x = copy(w, x)
    return x.view(spec.shape, contiguous_strides(spec.shape), x.offset)


VIEWS: dict[str, Emitter] = {
    **{n: _identity for n in ("alias.default", "detach.default", "clone.default",
                              "contiguous.default", "lift_fresh_copy.default")},
    "unsqueeze.default": _unsqueeze, "squeeze.dim": _squeeze, "squeeze.dims": _squeeze,
    "squeeze.default": _squeeze, "narrow.default": _narrow, "select.int": _select,
    "slice.Tensor": _slice, "split_with_sizes.default": _split_sizes,
    "split.Tensor": _split, "unbind.int": _unbind, "permute.default": _permute,
    "transpose.int": _transpose, "t.default": lambda w, s, x: _permute(
        w, s, x, list(range(len(x.shape)))[::-1]),
    "mT.default": lambda w, s, x: _transpose(w, s, x, -2, -1),
    "numpy_T.default": lambda w, s, x: _permute(w, s, x, list(range(len(x.shape)))[::-1]),
    "expand.default": _expand, "flip.default": _flip, "view.default": _reshape,
    "reshape.default": _reshape,
    "_unsafe_view.default": _reshape, "flatten.using_ints": _reshape,
    "unflatten.int": _reshape, "view_as.default": _reshape, "reshape_as.default": _reshape,
    "expand_as.default": lambda w, s, x, other: _expand(w, s, x, other.shape),
    "movedim.int": _movedim, "diagonal.default": _diagonal, "dropout.default": _dropout,
    "chunk.default": _chunk,
    "unsafe_chunk.default": _chunk,
    "unsafe_split.Tensor": _split, "unsafe_split_with_sizes.default": _split_sizes,
    "tensor_split.sections": _tensor_split, "tensor_split.indices": _tensor_split,
}


# --- joins ------------------------------------------------------------------------------------


def _cat(w: Writer, spec: CTensor, tensors: Sequence[CTensor], dim: int = 0) -> CTensor:
    out = w.local(spec.dtype, spec.shape)
    d, start = _dim(dim, len(spec.shape)), 0
    for x in tensors:
        if len(x.shape) != len(spec.shape):  # a legacy empty (0,) tensor: skipped
            continue
        dst = _narrow(w, out, out, d, start, x.shape[d])
        w.assign(dst, lambda idx, x=x: w.read_broadcast(x, idx, spec.dtype))
        start += x.shape[d]
    return out


def _stack(w: Writer, spec: CTensor, tensors: Sequence[CTensor], dim: int = 0) -> CTensor:
    d = _dim(dim, len(spec.shape))
    # a constant stays one (a view of it would lose its values)
    return _cat(w, spec, [constant(x.value.unsqueeze(d)) if x.value is not None
                          else _unsqueeze(w, spec, x, d) for x in tensors], d)


JOINS: dict[str, Emitter] = {"cat.default": _cat, "stack.default": _stack}
