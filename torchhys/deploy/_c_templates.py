"""One small C template per aten operation, for :mod:`torchhys.deploy.export_c`.

:data:`TEMPLATES` maps an op overload (``torch.ops.aten.addmm.default``) to an emitter
``emit(w, spec, *args, **kwargs)``: ``w`` is the :class:`~torchhys.deploy._c_writer.Writer`,
``spec`` the node's output (a :class:`~torchhys.deploy._c_writer.CTensor` of its dtype and shape,
or a list of them), the arguments are the node's, tensors as
:class:`~torchhys.deploy._c_writer.CTensor`. It writes C and returns the output's CTensor(s).
The pointwise ones are in :mod:`torchhys.deploy._c_pointwise`; here: views (no code), joins,
reductions, matrix products, sorting and indexing.

Reductions and matrix products add in index order (BLAS may not: rounding-level
differences), except a large constant matrix whose rows are piecewise constant (a cumulative
table), multiplied through its column differences (:func:`_column_differences`). Integer
indices out of range (where torch raises) are clamped to the tensor, so the C never reads
outside an array.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Sequence
from typing import Any

import torch

from torchhys.deploy._c_pointwise import POINTWISE, promoted
from torchhys.deploy._c_writer import CTensor, Writer, constant, contiguous_strides

__all__ = ["POINTWISE_OPS", "SHAPE_ONLY", "TEMPLATES", "copy"]

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
}


# --- joins, reductions, products, indexing ----------------------------------------------------


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
    return _cat(w, spec, [_unsqueeze(w, spec, x, d) for x in tensors], d)


def _block(w: Writer, lines: Callable[[], None]) -> None:
    w.emit("{")
    w._depth += 1
    lines()
    w._depth -= 1
    w.emit("}")


def _reduce(w: Writer, spec: CTensor, x: CTensor, dims: Sequence[int] | None, keepdim: bool,
            init: str | Callable[[list[str]], str], step: str, finish: str = "acc"
            ) -> CTensor:
    """Reduce ``x`` over ``dims`` (None or []: all) in index order: ``acc = init`` (or
    ``init(index of the slice's first element)``), then ``acc = step`` (``{acc}``, ``{x}``)
    per element, then ``finish``."""
    n = len(x.shape)
    red = sorted({_dim(d, n) for d in dims}) if dims else list(range(n))
    kept = [d for d in range(n) if d not in red]
    out = w.local(spec.dtype, spec.shape)
    out_kept = out.view([x.shape[d] for d in kept],
                        [s for d, s in zip(range(n), out.strides, strict=False) if d in kept]
                        if keepdim else out.strides, 0)
    t = w.ctype(spec.dtype)
    with w.loop([x.shape[d] for d in kept]) as kidx:
        def full(ridx: Sequence[str]) -> list[str]:
            at = [""] * n
            for d, i in (*zip(kept, kidx, strict=True), *zip(red, ridx, strict=True)):
                at[d] = i
            return at

        def body() -> None:
            first = init(full(["0"] * len(red))) if callable(init) else init
            w.emit(f"{t} acc = {first};")
            with w.loop([x.shape[d] for d in red]) as ridx:
                value = w.cast(w.read(x, full(ridx)), x.dtype, spec.dtype)
                w.emit("acc = " + step.format(acc="acc", x=value) + ";")
            w.emit(f"{w.read(out_kept, kidx)} = {finish};")
        _block(w, body)
    return out


def _sum(w: Writer, spec: CTensor, x: CTensor, dim: Sequence[int] | None = None,
         keepdim: bool = False, *, dtype: torch.dtype | None = None) -> CTensor:
    return _reduce(w, spec, x, dim, keepdim, w.literal(0, spec.dtype), "{acc} + {x}")


def _mean(w: Writer, spec: CTensor, x: CTensor, dim: Sequence[int] | None = None,
          keepdim: bool = False, *, dtype: torch.dtype | None = None) -> CTensor:
    n = len(x.shape)
    count = math.prod(x.shape[_dim(d, n)] for d in dim) if dim else x.numel
    return _reduce(w, spec, x, dim, keepdim, w.literal(0, spec.dtype), "{acc} + {x}",
                   f"acc / {w.literal(count, spec.dtype)}")


def _extremum(kind: str) -> Emitter:
    def emit(w: Writer, spec: CTensor, x: CTensor, dim: Sequence[int] = (),
             keepdim: bool = False) -> CTensor:
        f = w.helper(kind, spec.dtype)
        return _reduce(w, spec, x, dim, keepdim, lambda at: w.read(x, at),  # max(a, a) = a
                       f + "({acc}, {x})")
    return emit


#: matrix products whose inner dimension is at most this are written out, one statement an
#: output element
UNROLL = 32


def _matmul_core(w: Writer, spec: CTensor, a: CTensor, b: CTensor,
                 bias: Operand | None = None, beta: float = 1, alpha: float = 1) -> CTensor:
    """``alpha * (a @ b) + beta * bias`` (torch.matmul's shapes). Each dot product adds in
    index order from 0, then the bias; the loops run over the output's columns innermost
    (contiguous rows of ``b``, which the compiler vectorizes without reordering a sum). An
    inner dimension of at most :data:`UNROLL` is written out (the sum in a register)."""
    a2 = a if len(a.shape) >= 2 else _unsqueeze(w, spec, a, 0)
    b2 = b if len(b.shape) >= 2 else _unsqueeze(w, spec, b, -1)
    batch = list(torch.broadcast_shapes(a2.shape[:-2], b2.shape[:-2]))
    full = [*batch, a2.shape[-2], b2.shape[-1]]
    out = w.local(spec.dtype, full)
    if 0 < a2.shape[-1] <= UNROLL:
        # one statement an element, the products written out in index order: the compiler
        # keeps the sum in a register and vectorizes over the columns
        def element(idx: list[str]) -> str:
            rows, j = idx[:-1], idx[-1]
            value = " + ".join([w.literal(0, spec.dtype)] + [
                f"{_read_aligned(w, a2, [*rows, str(p)], spec.dtype)} * "
                f"{_read_aligned(w, b2, [*rows[:-1], str(p), j], spec.dtype)}"
                for p in range(a2.shape[-1])])
            if alpha != 1:
                value = f"{w.literal(alpha, spec.dtype)} * ({value})"
            if bias is not None and beta != 0:
                c = w.read_broadcast(bias, idx, spec.dtype)
                value = f"({value}) + " + (c if beta == 1 else
                                          f"{w.literal(beta, spec.dtype)} * {c}")
            return value
        w.assign(out, element)
        return out.view(spec.shape, contiguous_strides(spec.shape), 0)
    diff = _column_differences(b2, spec.dtype) if all(n == 1 for n in full[:-1]) else None
    if diff is not None:
        _sparse_cumsum(w, spec, out, a2, *diff)
    else:
        w.assign(out, lambda idx: w.literal(0, spec.dtype))
        with (w.loop(full[:-1]) as rows, w.loop([a2.shape[-1]]) as (p,),
              w.loop(full[-1:]) as (j,)):
            lhs = _read_aligned(w, a2, [*rows, p], spec.dtype)
            rhs = _read_aligned(w, b2, [*rows[:-1], p, j], spec.dtype)
            w.emit(f"{w.read(out, [*rows, j])} += {lhs} * {rhs};")
    if alpha != 1 or (bias is not None and beta != 0):
        def element(idx: list[str]) -> str:
            value = w.read(out, idx)
            if alpha != 1:
                value = f"{w.literal(alpha, spec.dtype)} * {value}"
            if bias is not None and beta != 0:
                c = w.read_broadcast(bias, idx, spec.dtype)
                value += f" + {c}" if beta == 1 else f" + {w.literal(beta, spec.dtype)} * {c}"
            return value
        w.assign(out, element)
    return out.view(spec.shape, contiguous_strides(spec.shape), 0)


#: a constant matrix of at least this many elements is multiplied through its column
#: differences where they have at most a quarter of its nonzeros
SPARSE_MIN = 4096
#: ... and written out, one statement a column, up to this many nonzeros
SPARSE_UNROLL = 4096


def _column_differences(b: CTensor, dtype: torch.dtype
                        ) -> tuple[list[int], list[int], torch.Tensor] | None:
    """For a constant matrix ``b`` (K, N) whose rows are piecewise constant (a cumulative
    table, such as the Preisach inverse's jumps summed level by level): the nonzeros of
    its column differences ``d`` (``b[:, j] = d[:, 0] + ... + d[:, j]`` exactly in
    ``dtype``), as rows, columns and values, interleaved so that consecutive entries add to
    different columns; None where that does not hold or saves little."""
    if (b.value is None or len(b.shape) != 2 or not dtype.is_floating_point
            or b.numel < SPARSE_MIN):
        return None
    m = b.value.to(dtype)
    d = torch.diff(m, dim=1, prepend=torch.zeros_like(m[:, :1]))
    rebuilt = d.clone()
    for j in range(1, m.shape[1]):  # the C's order: a running sum over the columns
        rebuilt[:, j] = rebuilt[:, j - 1] + d[:, j]
    nnz = int((d != 0).sum())
    if not torch.equal(rebuilt, m) or 4 * nnz > int((m != 0).sum()):
        return None
    rows, cols = (d != 0).nonzero(as_tuple=True)
    rank = torch.zeros_like(rows)
    for j in range(m.shape[1]):
        at = (cols == j).nonzero(as_tuple=True)[0]
        rank[at] = torch.arange(at.numel())
    order = sorted(range(nnz), key=lambda e: (int(rank[e]), int(cols[e])))
    rows, cols = rows[order], cols[order]
    return rows.tolist(), cols.tolist(), d[rows, cols]


def _sparse_cumsum(w: Writer, spec: CTensor, out: CTensor, a: CTensor, rows: list[int],
                   cols: list[int], values: torch.Tensor) -> None:
    """``out = a @ b`` (a one row) as the running sum over the columns of ``a @ d``, ``d``
    the column differences of ``b`` (:func:`_column_differences`), added entry by entry:
    3 operations a nonzero of ``d`` where the dense product takes one a element of ``b``.
    The rounding differs from the dense sum's (as BLAS's does); a non-finite element of
    ``a`` spreads to the columns of its row's runs only."""
    t, n = w.ctype(spec.dtype), out.shape[-1]
    values = values.to(spec.dtype)
    lead = ["0"] * (len(a.shape) - 1)
    at_out = ["0"] * (len(out.shape) - 1)
    if len(rows) <= SPARSE_UNROLL:
        # written out, one sum a column, the entries of one value summed before their one
        # product (no index tables; a table of relays' +-1 times one weight each: the sums
        # are exact)
        def unrolled() -> None:
            w.emit(f"{t} acc = {w.literal(0, spec.dtype)};")
            for j in range(n):
                groups: dict[float, list[str]] = {}
                for e in sorted(range(len(rows)), key=lambda e: rows[e]):
                    if cols[e] == j:
                        groups.setdefault(float(values[e]), []).append(
                            w.cast(w.read(a, [*lead, str(rows[e])]), a.dtype, spec.dtype))
                terms = [f"{w.literal(value, spec.dtype)} * ({' + '.join(reads)})"
                         for value, reads in groups.items()]
                if terms:
                    w.emit(f"acc += {w.literal(0, spec.dtype)} + " + " + ".join(terms) + ";")
                w.emit(f"{w.read(out, [*at_out, str(j)])} = acc;")
        _block(w, unrolled)
        return
    v = w.array(constant(values))
    r = w.array(constant(torch.tensor(rows, dtype=torch.int32)))
    c = w.array(constant(torch.tensor(cols, dtype=torch.int32)))

    def body() -> None:
        w.emit(f"{t} bins[{n}];")
        w.emit(f"{t} acc = {w.literal(0, spec.dtype)};")
        w.emit(f"for (int j = 0; j < {n}; ++j) bins[j] = {w.literal(0, spec.dtype)};")
        lhs = w.cast(w.read(a, [*lead, f"{r}[e]"]), a.dtype, spec.dtype)
        w.emit(f"for (int e = 0; e < {len(rows)}; ++e) bins[{c}[e]] += {lhs} * {v}[e];")
        w.emit(f"for (int j = 0; j < {n}; ++j) {{")
        w.emit("    acc += bins[j];")
        w.emit(f"    {w.read(out, [*at_out, 'j'])} = acc;")
        w.emit("}")
    _block(w, body)


def _read_aligned(w: Writer, x: CTensor, idx: list[str], dtype: torch.dtype) -> str:
    """``x`` at ``idx`` (the last dims of an n-dim index; a batch dim of size 1 broadcast)."""
    lead = len(idx) - len(x.shape)
    own = ["0" if x.shape[d] == 1 else idx[lead + d] for d in range(len(x.shape))]
    return w.cast(w.read(x, own), x.dtype, dtype)


def _addmm(w: Writer, spec: CTensor, bias: Operand, a: CTensor, b: CTensor, *,
           beta: float = 1, alpha: float = 1) -> CTensor:
    return _matmul_core(w, spec, a, b, bias, beta, alpha)


def _linear(w: Writer, spec: CTensor, x: CTensor, weight: CTensor, bias: CTensor | None = None
            ) -> CTensor:
    return _matmul_core(w, spec, x, _transpose(w, spec, weight, -2, -1), bias)


def _cumsum(w: Writer, spec: CTensor, x: CTensor, dim: int, *,
            dtype: torch.dtype | None = None) -> CTensor:
    d = _dim(dim, len(x.shape))
    out, t = w.local(spec.dtype, spec.shape), w.ctype(spec.dtype)
    others = [n if i != d else 1 for i, n in enumerate(x.shape)]
    with w.loop(others) as idx:
        def body() -> None:
            w.emit(f"{t} acc = {w.literal(0, spec.dtype)};")
            with w.loop([x.shape[d]]) as (k,):
                at = [*idx[:d], k, *idx[d + 1:]]
                w.emit(f"acc += {w.cast(w.read(x, at), x.dtype, spec.dtype)};")
                w.emit(f"{w.read(out, at)} = acc;")
        _block(w, body)
    return out


def _sort(w: Writer, spec: list, x: CTensor, dim: int = -1, descending: bool = False, *,
          stable: bool | None = None) -> list[CTensor]:
    """A stable insertion sort along ``dim`` (NaN last, first when descending, as torch):
    ``(values, indices)``; quadratic in the dim's size."""
    d = _dim(dim, len(x.shape))
    n, t = x.shape[d], w.ctype(x.dtype)
    values, index = copy(w, x), w.local(torch.int64, x.shape)
    w.assign(index, lambda idx: idx[d])
    before = ("(k > v) || (k != k && v == v)" if descending else
              "(k < v) || (v != v && k == k)")
    if not x.dtype.is_floating_point:
        before = "k > v" if descending else "k < v"
    others = [1 if i == d else m for i, m in enumerate(x.shape)]
    with w.loop(others) as idx:
        def at(tensor: CTensor, e: str) -> str:
            return w.read(tensor, [*idx[:d], e, *idx[d + 1:]])

        def body() -> None:
            w.emit(f"for (int sa = 1; sa < {n}; ++sa) {{")
            w.emit(f"    {t} k = {at(values, 'sa')}, v;")
            w.emit(f"    int64_t ki = {at(index, 'sa')};")
            w.emit("    int sb = sa - 1;")
            w.emit(f"    while (sb >= 0 && (v = {at(values, 'sb')}, {before})) {{")
            w.emit(f"        {at(values, 'sb + 1')} = v;")
            w.emit(f"        {at(index, 'sb + 1')} = {at(index, 'sb')};")
            w.emit("        --sb;")
            w.emit("    }")
            w.emit(f"    {at(values, 'sb + 1')} = k;")
            w.emit(f"    {at(index, 'sb + 1')} = ki;")
            w.emit("}")
        if n > 1:
            _block(w, body)
    return [values, index]


def _bounded(w: Writer, expr: str, n: int, wrap: bool) -> str:
    """An index into a dim of ``n``: negative ones wrapped (``wrap``), then clamped."""
    i = f"(({expr}) < 0 ? ({expr}) + {n} : ({expr}))" if wrap else f"({expr})"
    return f"({i} < 0 ? 0 : ({i} > {n - 1} ? {n - 1} : {i}))"


def _searchsorted(w: Writer, spec: CTensor, seq: CTensor, values: CTensor, *,
                  out_int32: bool = False, right: bool = False, side: str | None = None,
                  sorter: CTensor | None = None) -> CTensor:
    if sorter is not None:
        raise ValueError("searchsorted with a sorter has no template")
    right = right or side == "right"
    out, n = w.local(spec.dtype, spec.shape), seq.shape[-1]
    compute = promoted(seq, values)
    test = ">" if right else ">="
    with w.loop(values.shape) as idx:
        def body() -> None:
            v = w.cast(w.read(values, idx), values.dtype, compute)
            w.emit(f"{w.ctype(spec.dtype)} c = 0;")
            with w.loop([n]) as (k,):
                at = [k] if len(seq.shape) == 1 else [*idx[:-1], k]
                w.emit(f"c += !({w.cast(w.read(seq, at), seq.dtype, compute)} {test} {v});")
            w.emit(f"{w.read(out, idx)} = c;")
        _block(w, body)
    return out


def _gather(w: Writer, spec: CTensor, x: CTensor, dim: int, index: CTensor, *,
            sparse_grad: bool = False) -> CTensor:
    d = _dim(dim, len(x.shape))
    out = w.local(spec.dtype, spec.shape)

    def element(idx: list[str]) -> str:
        at = list(idx)
        at[d] = _bounded(w, w.read(index, idx), x.shape[d], wrap=False)
        return w.read(x, at)

    w.assign(out, element)
    return out


def _index_select(w: Writer, spec: CTensor, x: CTensor, dim: int, index: CTensor
                  ) -> CTensor:
    d = _dim(dim, len(x.shape))
    index = index if index.shape else _unsqueeze(w, spec, index, 0)
    out = w.local(spec.dtype, spec.shape)

    def element(idx: list[str]) -> str:
        at = list(idx)
        at[d] = _bounded(w, w.read(index, [idx[d]]), x.shape[d], wrap=False)
        return w.read(x, at)

    w.assign(out, element)
    return out


def _scatter(w: Writer, spec: CTensor, x: CTensor, dim: int, index: CTensor, src: Operand, *,
             reduce: str | None = None) -> CTensor:
    """scatter.src / scatter.value: ``x`` with ``out[..., index[i], ...] = src[i]``, in index
    order (a repeated index: the last write stays, as on torch's CPU)."""
    if reduce is not None:
        raise ValueError(f"scatter(reduce={reduce!r}) has no template")
    d = _dim(dim, len(x.shape))
    out = copy(w, x)
    if index.numel:
        with w.loop(index.shape) as idx:
            at = list(idx)
            at[d] = _bounded(w, w.read(index, idx), x.shape[d], wrap=False)
            value = (w.cast(w.read(src, idx), src.dtype, spec.dtype)
                     if isinstance(src, CTensor) else w.literal(src, spec.dtype))
            w.emit(f"{w.read(out, at)} = {value};")
    return out


def _index(w: Writer, spec: CTensor, x: CTensor, indices: Sequence[CTensor | None]
           ) -> CTensor:
    given = [i for i, t in enumerate(indices) if t is not None]
    if given != list(range(given[0], given[-1] + 1)) or any(
            indices[i].dtype == torch.bool for i in given):
        raise ValueError("index.Tensor with non-adjacent or boolean indices has no template")
    first = given[0]
    nb = len(torch.broadcast_shapes(*[indices[i].shape for i in given]))
    out = w.local(spec.dtype, spec.shape)

    def element(idx: list[str]) -> str:
        b = idx[first:first + nb]
        at = [*idx[:first]]
        for i in given:
            at.append(_bounded(w, w.read_broadcast(indices[i], b, torch.int64),
                               x.shape[i], wrap=True))
        return w.read(x, at + idx[first + nb:])

    w.assign(out, element)
    return out


OTHERS: dict[str, Emitter] = {
    "cat.default": _cat, "stack.default": _stack,
    "sum.dim_IntList": _sum, "sum.default": _sum, "mean.dim": _mean,
    "amax.default": _extremum("max"), "amin.default": _extremum("min"),
    "addmm.default": _addmm, "mm.default": _matmul_core, "bmm.default": _matmul_core,
    "matmul.default": _matmul_core, "mv.default": _matmul_core, "dot.default": _matmul_core,
    "linear.default": _linear, "cumsum.default": _cumsum,
    "sort.default": _sort, "sort.stable": _sort, "searchsorted.Tensor": _searchsorted,
    "gather.default": _gather, "index.Tensor": _index, "index_select.default": _index_select,
    "scatter.src": _scatter, "scatter.value": _scatter,
}


def _resolve(table: dict[str, Emitter]) -> dict[Any, Emitter]:
    """Op overloads of the names that this torch has."""
    out: dict[Any, Emitter] = {}
    for name, emit in table.items():
        packet, overload = name.split(".")
        op = getattr(getattr(torch.ops.aten, packet, None), overload, None)
        if op is not None:
            out[op] = emit
    return out


#: the pointwise ops (their results may be deferred into the loop of their reader)
POINTWISE_OPS = frozenset(_resolve(POINTWISE))

#: the op templates: op overload -> emitter
TEMPLATES: dict[Any, Emitter] = {
    **_resolve(POINTWISE), **_resolve(VIEWS), **_resolve(OTHERS),
    operator.getitem: lambda w, spec, xs, i: xs[i],
}

#: ops whose result depends on their tensor arguments' shapes and dtypes only (computed when
#: the C is written, with zeros for those arguments); ``empty`` ones become zeros
SHAPE_ONLY = set(_resolve({n: _identity for n in (
    "zeros_like.default", "ones_like.default", "full_like.default", "empty_like.default",
    "new_zeros.default", "new_ones.default", "new_full.default", "new_empty.default",
    "zeros.default", "ones.default", "full.default", "empty.memory_format", "arange.default",
    "arange.start", "arange.start_step", "scalar_tensor.default", "fill.Scalar",
)}))
