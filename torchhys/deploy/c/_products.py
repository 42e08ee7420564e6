"""C templates of :mod:`torchhys.deploy.c` that sum: reductions (``sum``, ``mean``,
``amax``, ``amin``, ``all``, ``any``), matrix products and ``cumsum``. Registered in
:mod:`torchhys.deploy.c._templates`.

Reductions and matrix products add in index order (BLAS may not: rounding-level
differences), except a long sum, added in partial sums (:func:`_reduce`), and a large constant
matrix whose rows are piecewise constant (a cumulative table), multiplied through its column
differences (:func:`_column_differences`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch

from torchhys.deploy.c._views import Emitter, Operand, _dim, _transpose, _unsqueeze
from torchhys.deploy.c._writer import CTensor, Writer, constant, contiguous_strides


def _block(w: Writer, lines: Callable[[], None]) -> None:
    w.emit("{")
    w._depth += 1
    lines()
    w._depth -= 1
    w.emit("}")


#: a sum of at least this many elements per output element is added in LANES partial sums
LANES_MIN = 16
LANES = 4


def _reduce(w: Writer, spec: CTensor, x: CTensor, dims: Sequence[int] | None, keepdim: bool,
            init: str | Callable[[list[str]], str], step: str, finish: str = "acc",
            lanes: bool = False) -> CTensor:
    """Reduce ``x`` over ``dims`` (None or []: all) in index order: ``acc = init`` (or
    ``init(index of the slice's first element)``), then ``acc = step`` (``{acc}``, ``{x}``)
    per element, then ``finish``. ``lanes`` (a sum, ``init`` its zero): where a slice has
    at least :data:`LANES_MIN` elements and its last reduced dim at least :data:`LANES`,
    element ``k`` of that dim is added to partial sum ``k % LANES`` (in index order), the
    partial sums added pairwise at the end: no chain of additions as long as the slice
    (torch's vectorized sums also add in partial sums; the rounding differs from the
    index-order sum's as theirs does)."""
    n = len(x.shape)
    red = sorted({_dim(d, n) for d in dims}) if dims else list(range(n))
    kept = [d for d in range(n) if d not in red]
    out = w.local(spec.dtype, spec.shape)
    out_kept = out.view([x.shape[d] for d in kept],
                        [s for d, s in zip(range(n), out.strides, strict=False) if d in kept]
                        if keepdim else out.strides, 0)
    t = w.ctype(spec.dtype)
    last = x.shape[red[-1]] if red else 0
    lanes = lanes and last >= LANES and math.prod(x.shape[d] for d in red) >= LANES_MIN
    with w.loop([x.shape[d] for d in kept]) as kidx:
        def full(ridx: Sequence[str]) -> list[str]:
            at = [""] * n
            for d, i in (*zip(kept, kidx, strict=True), *zip(red, ridx, strict=True)):
                at[d] = i
            return at

        def add(acc: str, ridx: list[str]) -> None:
            value = w.cast(w.read(x, full(ridx)), x.dtype, spec.dtype)
            w.emit(f"{acc} = " + step.format(acc=acc, x=value) + ";")

        def body() -> None:
            first = init(full(["0"] * len(red))) if callable(init) else init
            if not lanes:
                w.emit(f"{t} acc = {first};")
                with w.loop([x.shape[d] for d in red]) as ridx:
                    add("acc", ridx)
            else:
                w.emit(f"{t} lane[{LANES}] = {{{', '.join([first] * LANES)}}};")
                with w.loop([x.shape[d] for d in red[:-1]]) as ridx:
                    var, whole = f"i{w._loops}", last - last % LANES
                    w.emit(f"for (int {var} = 0; {var} < {whole}; {var} += {LANES}) {{")
                    w._depth += 1
                    for k in range(LANES):
                        add(f"lane[{k}]", [*ridx, f"{var} + {k}" if k else var])
                    w._depth -= 1
                    w.emit("}")
                    for j in range(whole, last):
                        add("lane[0]", [*ridx, str(j)])
                w.emit(f"{t} acc = {_tree([f'lane[{k}]' for k in range(LANES)])};")
            w.emit(f"{w.read(out_kept, kidx)} = {finish};")
        _block(w, body)
    return out


def _tree(terms: list[str]) -> str:
    """The sum of ``terms`` added pairwise (a balanced tree: no long chain of additions)."""
    if len(terms) == 1:
        return terms[0]
    half = len(terms) // 2
    return f"({_tree(terms[:half])} + {_tree(terms[half:])})"


def _sum(w: Writer, spec: CTensor, x: CTensor, dim: Sequence[int] | None = None,
         keepdim: bool = False, *, dtype: torch.dtype | None = None) -> CTensor:
    return _reduce(w, spec, x, dim, keepdim, w.literal(0, spec.dtype), "{acc} + {x}",
                   lanes=True)


def _mean(w: Writer, spec: CTensor, x: CTensor, dim: Sequence[int] | None = None,
          keepdim: bool = False, *, dtype: torch.dtype | None = None) -> CTensor:
    n = len(x.shape)
    count = math.prod(x.shape[_dim(d, n)] for d in dim) if dim else x.numel
    return _reduce(w, spec, x, dim, keepdim, w.literal(0, spec.dtype), "{acc} + {x}",
                   f"acc / {w.literal(count, spec.dtype)}", lanes=True)


def _extremum(kind: str) -> Emitter:
    def emit(w: Writer, spec: CTensor, x: CTensor, dim: Sequence[int] = (),
             keepdim: bool = False) -> CTensor:
        f = w.helper(kind, spec.dtype)
        return _reduce(w, spec, x, dim, keepdim, lambda at: w.read(x, at),  # max(a, a) = a
                       f + "({acc}, {x})")
    return emit


def _logical(kind: str) -> Emitter:
    """``all`` / ``any`` over ``dim`` (an int, a list, or None: every dim): an element is
    true where it is nonzero (a NaN is true, as in torch)."""
    init, op = ("1", "&&") if kind == "all" else ("0", "||")

    def emit(w: Writer, spec: CTensor, x: CTensor, dim: int | Sequence[int] | None = None,
             keepdim: bool = False) -> CTensor:
        dims = None if dim is None else [dim] if isinstance(dim, int) else list(dim)
        if x.numel == 0:
            return constant(torch.full(spec.shape, kind == "all", dtype=torch.bool))
        return _reduce(w, spec, x, dims, keepdim, init, f"({{acc}} {op} {{x}})")
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
        _blocked(w, spec, out, a2, b2, full)
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


#: a matrix product of a larger inner dimension runs over blocks of this many output columns
#: (their sums in registers)
BLOCK = 16


def _blocked(w: Writer, spec: CTensor, out: CTensor, a: CTensor, b: CTensor,
             full: list[int]) -> None:
    """``out = a @ b`` (2-d or more, ``full`` its shape) over blocks of :data:`BLOCK` output
    columns: each block's sums in a local array (registers), the inner dimension looped over
    once a block, each product added in index order from 0 (the rounding of the plain
    loop's). Where an LSTM's or a GRU's recurrent matrix has 64 rows, a third less time than
    sums kept in ``out`` (a load and a store a product)."""
    t, k, n = w.ctype(spec.dtype), a.shape[-1], full[-1]
    zero = w.literal(0, spec.dtype)
    with w.loop(full[:-1]) as rows:
        def block(first: str, width: int) -> None:
            w.emit(f"{t} acc[{width}] = {{{', '.join([zero] * width)}}};")
            with w.loop([k]) as (p,):
                lhs = _read_aligned(w, a, [*rows, p], spec.dtype)
                for c in range(width):
                    col = f"{first} + {c}" if c else first
                    rhs = _read_aligned(w, b, [*rows[:-1], p, col], spec.dtype)
                    w.emit(f"acc[{c}] += {lhs} * {rhs};")
            for c in range(width):
                col = f"{first} + {c}" if c else first
                w.emit(f"{w.read(out, [*rows, col])} = acc[{c}];")

        whole = n - n % BLOCK
        if whole:
            var = f"i{w._loops}"
            w._loops += 1
            w.emit(f"for (int {var} = 0; {var} < {whole}; {var} += {BLOCK}) {{")
            w._depth += 1
            block(var, BLOCK)
            w._depth -= 1
            w.emit("}")
            w._loops -= 1
        if n % BLOCK:
            _block(w, lambda: block(str(whole), n % BLOCK))


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
        # written out, one sum a column, the entries of one value summed pairwise before
        # their one product (no index tables, no long chain of additions; a table of
        # relays' +-1 times one weight each: the sums are exact in any order)
        def unrolled() -> None:
            w.emit(f"{t} acc = {w.literal(0, spec.dtype)};")
            for j in range(n):
                groups: dict[float, list[str]] = {}
                for e in sorted(range(len(rows)), key=lambda e: rows[e]):
                    if cols[e] == j:
                        groups.setdefault(float(values[e]), []).append(
                            w.cast(w.read(a, [*lead, str(rows[e])]), a.dtype, spec.dtype))
                terms = [f"{w.literal(value, spec.dtype)} * {_tree(reads)}"
                         for value, reads in groups.items()]
                if terms:
                    w.emit(f"acc += {_tree(terms)};")
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
    if weight.value is not None:  # a constant (a layer's weight): stored transposed
        return _matmul_core(w, spec, x, constant(weight.value.transpose(-2, -1)), bias)
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


PRODUCTS: dict[str, Emitter] = {
    "sum.dim_IntList": _sum, "sum.default": _sum, "mean.dim": _mean,
    "amax.default": _extremum("max"), "amin.default": _extremum("min"),
    "addmm.default": _addmm, "mm.default": _matmul_core, "bmm.default": _matmul_core,
    "matmul.default": _matmul_core, "mv.default": _matmul_core, "dot.default": _matmul_core,
    "linear.default": _linear, "cumsum.default": _cumsum,
    **{f"{k}.{v}": _logical(k) for k in ("all", "any") for v in ("default", "dim", "dims")},
}
