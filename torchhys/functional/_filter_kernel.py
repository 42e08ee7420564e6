"""Compiled CPU kernels for linear recursions (DF2T filter, state-space recurrence).

Loops of plain C, compiled once with the system C compiler into the user cache directory
(``$TORCHHYS_CACHE``, default ``~/.cache/torchhys``) and loaded with :mod:`ctypes`, in the
manner of :mod:`torchhys.functional._kernel`: no torch headers, compiled in well under a
second, ``-ffp-contract=off`` so that each multiply and add rounds as in the eager torch step.

- ``df2t``: the direct form II transposed recursion of ``scipy.signal.lfilter``, written with
  the operations of :func:`~torchhys.functional.linear_filter.df2t_step` in the same order,
  so that the two agree bit for bit; one filter for all rows, or F filters (row r uses
  filter ``r % F``).
- ``linrec``: ``s[t] = A s[t-1] + w[t]`` for a small dense ``A``.
- ``df2t_adjoint`` and ``linrec_adjoint``: their backward passes, each one reverse pass that
  also reduces the gradients of the coefficients (sums over time in float64).

Where no compiler is found, on devices other than the CPU, for dtypes other than
float32/float64, inside :func:`filter_kernel_enabled(False) <filter_kernel_enabled>` or with
the environment variable ``TORCHHYS_DISABLE_KERNEL=1``, the callers use the pure-torch
chunked scan of :mod:`torchhys.functional._linear_scan` and a backward written with tensor
operations instead.

Each is also a custom op, ``torch.ops.torchhys.df2t``, ``linrec``, ``df2t_adjoint`` and
``linrec_adjoint``, with a fake implementation and a ``vmap`` rule, making the kernel-or-scan
choice when it runs; :func:`df2t`, :func:`linrec`, :func:`df2t_adjoint` and
:func:`linrec_adjoint` call the op where the call is traced or transformed
(:func:`~torchhys.functional._compile.dispatched`) and the implementation directly in plain
eager calls. The autograd formula of ``df2t`` and ``linrec`` is their adjoint op (without a
graph) or, when a graph of the gradient is asked for, the tensor-operation adjoint over the
op itself (differentiable again); the adjoint ops are first-order only and say so when
differentiated.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
from collections.abc import Iterator

import torch
from torch import Tensor

from torchhys.functional._compile import SUFFIX as _SUFFIX
from torchhys.functional._compile import build, cpu_float, dispatched, loop_vmap, servable
from torchhys.functional._linear_scan import (
    _df2t_scan_filters,
    df2t_adjoint_torch,
    linrec_adjoint_torch,
    recurrence_scan,
)

_enabled = True

MAX_FUSED_ORDER = 64
"""Largest filter order of the fused DF2T adjoint (larger orders use the torch backward)."""


@contextlib.contextmanager
def filter_kernel_enabled(enabled: bool) -> Iterator[None]:
    """Context manager that switches the compiled filter kernels on or off (tests, benchmarks)."""
    global _enabled
    previous, _enabled = _enabled, bool(enabled)
    try:
        yield
    finally:
        _enabled = previous


_SOURCE = r"""
#define MAXN 64 /* MAX_FUSED_ORDER */
#define FILTER_DEFINE(T, SUF)                                                            \
void df2t_##SUF(const T* x, const T* b, const T* a, const T* zi, T* y, T* zf,          \
                long R, long Tn, long n, long F) {                                      \
    for (long r = 0; r < R; ++r) {                                                      \
        const T* xr = x + r * Tn;                                                       \
        const T* bf = b + (r % F) * (n + 1);                                            \
        const T* af = a + (r % F) * n;                                                  \
        T* yr = y + r * Tn;                                                             \
        T* z = zf + r * n;                                                              \
        for (long i = 0; i < n; ++i) z[i] = zi[r * n + i];                              \
        for (long t = 0; t < Tn; ++t) {                                                 \
            const T xt = xr[t];                                                         \
            const T yt = bf[0] * xt + z[0];                                             \
            for (long i = 0; i + 1 < n; ++i) z[i] = bf[i + 1] * xt + z[i + 1] - af[i] * yt; \
            z[n - 1] = bf[n] * xt + (T)0 - af[n - 1] * yt;                              \
            yr[t] = yt;                                                                 \
        }                                                                               \
    }                                                                                   \
}                                                                                       \
void linrec_##SUF(const T* A, const T* w, const T* s0, T* s, long R, long Tn, long n) { \
    for (long r = 0; r < R; ++r) {                                                      \
        const T* prev = s0 + r * n;                                                     \
        for (long t = 0; t < Tn; ++t) {                                                 \
            const T* wt = w + (r * Tn + t) * n;                                         \
            T* st = s + (r * Tn + t) * n;                                               \
            for (long i = 0; i < n; ++i) {                                              \
                T acc = 0;                                                              \
                for (long j = 0; j < n; ++j) acc += A[i * n + j] * prev[j];             \
                st[i] = acc + wt[i];                                                    \
            }                                                                           \
            prev = st;                                                                  \
        }                                                                               \
    }                                                                                   \
}                                                                                       \
void df2t_adjoint_##SUF(const T* x, const T* y, const T* gy, const T* gzf, const T* b,  \
                        const T* a, T* gx, double* gb, double* ga, T* gzi, T* lam,       \
                        long R, long Tn, long n, long F) {                              \
    double sb[MAXN + 1], sa[MAXN + 1];                                                  \
    for (long r = 0; r < R; ++r) {                                                      \
        const long f = r % F;                                                           \
        const T* bf = b + f * (n + 1);                                                  \
        const T* af = a + f * n;                                                        \
        double* gbf = gb + f * (n + 1);                                                 \
        double* gaf = ga + f * (n + 1);                                                 \
        for (long k = 0; k <= n; ++k) { sb[k] = gbf[k]; sa[k] = gaf[k]; }               \
        const T* xr = x + r * Tn; const T* yr = y + r * Tn; const T* gr = gy + r * Tn;  \
        T* gxr = gx + r * Tn;                                                           \
        for (long i = 0; i < n; ++i) lam[Tn + i] = gzf[r * n + i];                      \
        for (long t = Tn - 1; t >= 0; --t) {                                            \
            T l = gr[t];                                                                \
            for (long k = 1; k <= n; ++k) l -= af[k - 1] * lam[t + k];                  \
            lam[t] = l;                                                                 \
        }                                                                               \
        for (long t = 0; t < Tn; ++t) {                                                 \
            const double xt = xr[t], yt = yr[t];                                        \
            T acc = 0;                                                                  \
            for (long k = 0; k <= n; ++k) {                                             \
                const T lk = lam[t + k];                                                \
                acc += bf[k] * lk;                                                      \
                sb[k] += (double)lk * xt;                                               \
                sa[k] -= (double)lk * yt;                                               \
            }                                                                           \
            gxr[t] = acc;                                                               \
        }                                                                               \
        for (long i = 0; i < n; ++i) gzi[r * n + i] = lam[i];                           \
        for (long k = 0; k <= n; ++k) { gbf[k] = sb[k]; gaf[k] = sa[k]; }               \
    }                                                                                   \
}                                                                                       \
void linrec_adjoint_##SUF(const T* A, const T* s0, const T* s, const T* gs, T* lam,     \
                          double* gA, T* gs0, long R, long Tn, long n) {                \
    for (long i = 0; i < n * n; ++i) gA[i] = 0;                                         \
    for (long r = 0; r < R; ++r) {                                                      \
        const T* next = 0;                                                              \
        for (long t = Tn - 1; t >= 0; --t) {                                            \
            T* lt = lam + (r * Tn + t) * n;                                             \
            const T* gt = gs + (r * Tn + t) * n;                                        \
            const T* prev = t > 0 ? s + (r * Tn + t - 1) * n : s0 + r * n;              \
            for (long i = 0; i < n; ++i) {                                              \
                T acc = 0;                                                              \
                if (next) for (long j = 0; j < n; ++j) acc += A[j * n + i] * next[j];   \
                lt[i] = acc + gt[i];                                                    \
            }                                                                           \
            for (long i = 0; i < n; ++i)                                                \
                for (long j = 0; j < n; ++j) gA[i * n + j] += (double)lt[i] * (double)prev[j]; \
            next = lt;                                                                  \
        }                                                                               \
        for (long i = 0; i < n; ++i) {                                                  \
            T acc = 0;                                                                  \
            for (long j = 0; j < n; ++j) acc += A[j * n + i] * next[j];                 \
            gs0[r * n + i] = acc;                                                       \
        }                                                                               \
    }                                                                                   \
}
FILTER_DEFINE(float, f32)
FILTER_DEFINE(double, f64)
"""

@functools.lru_cache(maxsize=1)
def _load() -> tuple[ctypes.CDLL | None, str | None]:
    """The compiled library, or None and the reason it cannot be used."""
    p, lng = ctypes.c_void_p, ctypes.c_long
    return build("filter", _SOURCE, what="filter kernel", fallback="the pure-torch chunked scan",
                 argtypes={"df2t": [p] * 6 + [lng] * 4, "linrec": [p] * 4 + [lng] * 3,
                           "df2t_adjoint": [p] * 11 + [lng] * 4,
                           "linrec_adjoint": [p] * 7 + [lng] * 3})


def filter_kernel_unavailable_reason() -> str | None:
    """Why the compiled kernels cannot run on this machine, or None when they can."""
    return _load()[1]


def filter_kernel_available(*tensors: Tensor) -> bool:
    """Whether the compiled kernels can serve these tensors (CPU, float32 or float64)."""
    return _enabled and servable(*tensors) and _load()[0] is not None


def df2t_kernel(x: Tensor, b: Tensor, a: Tensor, zi: Tensor) -> tuple[Tensor, Tensor]:
    """x (R, T), b (n+1,), a (n,) = a[1:], zi (R, n) with n >= 1 -> y (R, T), zf (R, n).

    With F filters, b (F, n+1) and a (F, n): row r uses filter ``r % F`` (R a multiple of F).
    """
    x, b, a, zi = (t.detach().contiguous() for t in (x, b, a, zi))
    R, T = x.shape
    n = a.shape[-1]
    F = 1 if b.dim() == 1 else b.shape[0]
    y = torch.empty(R, T, dtype=x.dtype)
    zf = torch.empty(R, n, dtype=x.dtype)
    fn = getattr(_load()[0], f"df2t_{_SUFFIX[x.dtype]}")
    fn(x.data_ptr(), b.data_ptr(), a.data_ptr(), zi.data_ptr(), y.data_ptr(), zf.data_ptr(),
       R, T, n, F)
    return y, zf


def linrec_kernel(A: Tensor, w: Tensor, s0: Tensor) -> Tensor:
    """A (n, n), w (R, T, n), s0 (R, n) -> s (R, T, n) with s[t] = A s[t-1] + w[t]."""
    A, w, s0 = (t.detach().contiguous() for t in (A, w, s0))
    R, T, n = w.shape
    s = torch.empty(R, T, n, dtype=w.dtype)
    fn = getattr(_load()[0], f"linrec_{_SUFFIX[w.dtype]}")
    fn(A.data_ptr(), w.data_ptr(), s0.data_ptr(), s.data_ptr(), R, T, n)
    return s


def df2t_adjoint_kernel(gy: Tensor, gzf: Tensor, x: Tensor, b: Tensor, a: Tensor, y: Tensor
                        ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gradients of ``<gy, y> + <gzf, zf>`` for :func:`df2t_kernel`: (gx, gb, ga, gzi), with
    ``ga`` the gradient of ``a[1:]``; the sums over time accumulate in float64. With F filters
    (b (F, n+1), a (F, n)) the gradients are per filter, (F, n+1) and (F, n)."""
    gy, gzf, x, b, a, y = (t.detach().contiguous() for t in (gy, gzf, x, b, a, y))
    R, T = x.shape
    n = a.shape[-1]
    F = 1 if b.dim() == 1 else b.shape[0]
    gx = torch.empty(R, T, dtype=x.dtype)
    gb = torch.zeros(F, n + 1, dtype=torch.float64)
    ga = torch.zeros(F, n + 1, dtype=torch.float64)
    gzi = torch.empty(R, n, dtype=x.dtype)
    lam = torch.empty(T + n, dtype=x.dtype)
    fn = getattr(_load()[0], f"df2t_adjoint_{_SUFFIX[x.dtype]}")
    fn(x.data_ptr(), y.data_ptr(), gy.data_ptr(), gzf.data_ptr(), b.data_ptr(), a.data_ptr(),
       gx.data_ptr(), gb.data_ptr(), ga.data_ptr(), gzi.data_ptr(), lam.data_ptr(), R, T, n, F)
    return gx, gb.reshape(b.shape).to(x.dtype), ga[:, 1:].reshape(a.shape).to(x.dtype), gzi


def linrec_adjoint_kernel(gs: Tensor, A: Tensor, s0: Tensor, s: Tensor
                          ) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients of ``<gs, s>`` for :func:`linrec_kernel`: (gA, gw, gs0); ``gA`` accumulates
    in float64."""
    gs, A, s0, s = (t.detach().contiguous() for t in (gs, A, s0, s))
    R, T, n = s.shape
    lam = torch.empty(R, T, n, dtype=s.dtype)
    gA = torch.empty(n, n, dtype=torch.float64)
    gs0 = torch.empty(R, n, dtype=s.dtype)
    fn = getattr(_load()[0], f"linrec_adjoint_{_SUFFIX[s.dtype]}")
    fn(A.data_ptr(), s0.data_ptr(), s.data_ptr(), gs.data_ptr(), lam.data_ptr(), gA.data_ptr(),
       gs0.data_ptr(), R, T, n)
    return gA.to(s.dtype), lam, gs0


# --- custom ops ---------------------------------------------------------------------------------


def _kernel_runs(*tensors: Tensor) -> bool:
    """:func:`filter_kernel_available` for plain tensors (the implementations' inputs)."""
    return _enabled and cpu_float(*tensors) and _load()[0] is not None


def _df2t_impl(x: Tensor, b: Tensor, a: Tensor, zi: Tensor) -> tuple[Tensor, Tensor]:
    if _kernel_runs(x, b, a, zi):
        return df2t_kernel(x, b, a, zi)
    return _df2t_scan_filters(x, b, a, zi)


def _linrec_impl(A: Tensor, w: Tensor, s0: Tensor) -> Tensor:
    if _kernel_runs(A, w, s0):
        return linrec_kernel(A, w, s0)
    return recurrence_scan(A, w, s0)


def _df2t_adjoint_impl(gy: Tensor, gzf: Tensor, x: Tensor, b: Tensor, a: Tensor, y: Tensor
                       ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    if a.shape[-1] <= MAX_FUSED_ORDER and _kernel_runs(gy, gzf, x, b, a, y):
        return df2t_adjoint_kernel(gy, gzf, x, b, a, y)  # one fused pass
    return df2t_adjoint_torch(gy, gzf, x, b, a, y, _df2t_impl)


def _linrec_adjoint_impl(gs: Tensor, A: Tensor, s0: Tensor, s: Tensor
                         ) -> tuple[Tensor, Tensor, Tensor]:
    if _kernel_runs(gs, A, s0, s):
        return linrec_adjoint_kernel(gs, A, s0, s)
    return linrec_adjoint_torch(gs, A, s0, s, _linrec_impl)


def _fresh(*tensors: Tensor) -> tuple[Tensor, ...]:
    return tuple(t.contiguous() for t in tensors)


@torch.library.custom_op("torchhys::df2t", mutates_args=())
def df2t_op(x: Tensor, b: Tensor, a: Tensor, zi: Tensor) -> tuple[Tensor, Tensor]:
    """DF2T filters: x (R, T), b (F, n+1), a (F, n) = a[:, 1:], zi (R, n) -> y (R, T),
    zf (R, n); row r uses filter r % F."""
    return _fresh(*_df2t_impl(x, b, a, zi))  # type: ignore[return-value]


@df2t_op.register_fake
def _(x: Tensor, b: Tensor, a: Tensor, zi: Tensor) -> tuple[Tensor, Tensor]:
    return x.new_empty(x.shape), zi.new_empty(zi.shape)


@torch.library.custom_op("torchhys::linrec", mutates_args=())
def linrec_op(A: Tensor, w: Tensor, s0: Tensor) -> Tensor:
    """States of s[t] = A s[t-1] + w[t]: A (n, n), w (R, T, n), s0 (R, n) -> (R, T, n)."""
    return _fresh(_linrec_impl(A, w, s0))[0]


@linrec_op.register_fake
def _(A: Tensor, w: Tensor, s0: Tensor) -> Tensor:
    return w.new_empty(w.shape)


@torch.library.custom_op("torchhys::df2t_adjoint", mutates_args=())
def df2t_adjoint_op(gy: Tensor, gzf: Tensor, x: Tensor, b: Tensor, a: Tensor, y: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Gradients (gx, gb, ga, gzi) of ``<gy, y> + <gzf, zf>`` for ``torchhys::df2t``."""
    return _fresh(*_df2t_adjoint_impl(gy, gzf, x, b, a, y))  # type: ignore[return-value]


@df2t_adjoint_op.register_fake
def _(gy: Tensor, gzf: Tensor, x: Tensor, b: Tensor, a: Tensor, y: Tensor
      ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    return x.new_empty(x.shape), b.new_empty(b.shape), a.new_empty(a.shape), gzf.new_empty(
        gzf.shape)


@torch.library.custom_op("torchhys::linrec_adjoint", mutates_args=())
def linrec_adjoint_op(gs: Tensor, A: Tensor, s0: Tensor, s: Tensor
                      ) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients (gA, gw, gs0) of ``<gs, s>`` for ``torchhys::linrec``."""
    return _fresh(*_linrec_adjoint_impl(gs, A, s0, s))  # type: ignore[return-value]


@linrec_adjoint_op.register_fake
def _(gs: Tensor, A: Tensor, s0: Tensor, s: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    return A.new_empty(A.shape), s.new_empty(s.shape), s0.new_empty(s0.shape)


def _save_df2t(ctx, inputs, output) -> None:  # noqa: ANN001
    x, b, a, _ = inputs
    ctx.save_for_backward(x, b, a, output[0])


def _df2t_backward(ctx, gy: Tensor, gzf: Tensor):  # noqa: ANN001, ANN202
    x, b, a, y = ctx.saved_tensors
    if torch.is_grad_enabled():  # a graph of the gradient: the adjoint over the op itself
        return df2t_adjoint_torch(gy, gzf, x, b, a, y, df2t_op)
    return df2t_adjoint_op(gy, gzf, x, b, a, y)


def _save_linrec(ctx, inputs, output) -> None:  # noqa: ANN001
    A, _, s0 = inputs
    ctx.save_for_backward(A, s0, output)


def _linrec_backward(ctx, gs: Tensor):  # noqa: ANN001, ANN202
    A, s0, s = ctx.saved_tensors
    if torch.is_grad_enabled():
        return linrec_adjoint_torch(gs, A, s0, s, linrec_op)
    return linrec_adjoint_op(gs, A, s0, s)


def _first_order_only(name: str):  # noqa: ANN202
    def backward(ctx, *grads):  # noqa: ANN001, ANN002, ANN202
        raise RuntimeError(
            f"torchhys::{name} is a first-order gradient without a derivative of its own; "
            "differentiate torchhys::df2t or torchhys::linrec (or lfilter, linear_recurrence) "
            "with create_graph=True, whose backward then builds a differentiable graph")
    return backward


df2t_op.register_autograd(_df2t_backward, setup_context=_save_df2t)
linrec_op.register_autograd(_linrec_backward, setup_context=_save_linrec)
df2t_adjoint_op.register_autograd(_first_order_only("df2t_adjoint"),
                                  setup_context=lambda ctx, inputs, output: None)
linrec_adjoint_op.register_autograd(_first_order_only("linrec_adjoint"),
                                    setup_context=lambda ctx, inputs, output: None)
for _op in (df2t_op, linrec_op, df2t_adjoint_op, linrec_adjoint_op):
    loop_vmap(_op)


def df2t(x: Tensor, b: Tensor, a: Tensor, zi: Tensor) -> tuple[Tensor, Tensor]:
    """``torchhys::df2t`` (traced or transformed) or its implementation (plain eager)."""
    return df2t_op(x, b, a, zi) if dispatched(x, b, a, zi) else _df2t_impl(x, b, a, zi)


def linrec(A: Tensor, w: Tensor, s0: Tensor) -> Tensor:
    """``torchhys::linrec`` (traced or transformed) or its implementation (plain eager)."""
    return linrec_op(A, w, s0) if dispatched(A, w, s0) else _linrec_impl(A, w, s0)


def df2t_adjoint(gy: Tensor, gzf: Tensor, x: Tensor, b: Tensor, a: Tensor, y: Tensor
                 ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``torchhys::df2t_adjoint`` or its implementation, as :func:`df2t`; no graph."""
    if dispatched(gy, gzf, x, b, a, y):
        return df2t_adjoint_op(gy, gzf, x, b, a, y)
    return _df2t_adjoint_impl(gy, gzf, x, b, a, y)


def linrec_adjoint(gs: Tensor, A: Tensor, s0: Tensor, s: Tensor
                   ) -> tuple[Tensor, Tensor, Tensor]:
    """``torchhys::linrec_adjoint`` or its implementation, as :func:`df2t`; no graph."""
    if dispatched(gs, A, s0, s):
        return linrec_adjoint_op(gs, A, s0, s)
    return _linrec_adjoint_impl(gs, A, s0, s)
