"""C templates of :mod:`torchhys.deploy.c` that order and index: ``sort``,
``searchsorted``, ``gather``, ``index_select``, ``scatter`` and ``index``. Registered in
:mod:`torchhys.deploy.c._templates`. Integer indices out of range (where torch raises) are
clamped to the tensor, so the C never reads outside an array."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from torchhys.deploy.c._pointwise import promoted
from torchhys.deploy.c._products import _block
from torchhys.deploy.c._views import Emitter, Operand, _dim, _unsqueeze, copy
from torchhys.deploy.c._writer import CTensor, Writer


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


INDEXING: dict[str, Emitter] = {
    "sort.default": _sort, "sort.stable": _sort, "searchsorted.Tensor": _searchsorted,
    "gather.default": _gather, "index.Tensor": _index, "index_select.default": _index_select,
    "scatter.src": _scatter, "scatter.value": _scatter,
}
