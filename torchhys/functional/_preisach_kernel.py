"""A compiled CPU kernel for the exact inverse of the hard-relay Preisach model over a
sequence, without gradients (:func:`~torchhys.functional.preisach_inverse.preisach_inverse`
calls it when nothing needs a gradient).

One loop of plain C over the samples, compiled once with the system C compiler and loaded with
:mod:`ctypes` as the play-operator kernel is (:mod:`torchhys.functional._compile`). Each sample
is :func:`~torchhys.functional.preisach_inverse.inverse_on_relays` (the levels' output
``offs0 + r @ doffs``, the segment by binary search, the solution in closed form) and
:func:`~torchhys.functional.preisach.relay_update`. ``offs`` is updated by the rows of the
relays that switch and summed afresh every :data:`REFRESH` samples with a switch, so that it
stays within a few units in the last place of the sum the torch path forms; the cost follows
the switches (K (L + 1) per refresh, L + 1 per switched relay), where the windowed torch path
pays a few tensor operations for every switch. Results equal the torch path up to that
rounding (a target within it of a jump may land on the other side of the jump).

Where no compiler is found, on devices other than the CPU, for dtypes other than
float32/float64, or with ``TORCHHYS_DISABLE_KERNEL=1``, the torch path runs.

The kernel is also the custom op ``torch.ops.torchhys.preisach_inverse`` (a fake
implementation, a ``vmap`` rule; no gradient: differentiating it raises, the gradient is the
torch path's).
"""

from __future__ import annotations

import ctypes
import functools
from typing import Optional

import torch
from torch import Tensor

from torchhys.functional._compile import SUFFIX as _SUFFIX
from torchhys.functional._compile import build, dispatched, loop_vmap, servable

REFRESH = 32
"""Samples with a switch between two sums of ``offs`` afresh."""

_SOURCE = r"""
#include <math.h>
#include <stddef.h>
#define PREISACH_INVERSE_DEFINE(T, SUF, SINH)                                            \
static void offs_sum_##SUF(const T* offs0, const T* doffs, const T* r, T* offs,          \
                           long K, long L1) {                                            \
    for (long j = 0; j < L1; ++j) offs[j] = 0;                                           \
    for (long k = 0; k < K; ++k) {                                                       \
        const T rk = r[k];                                                               \
        const T* row = doffs + k * L1;                                                   \
        for (long j = 0; j < L1; ++j) offs[j] += rk * row[j];                            \
    }                                                                                    \
    for (long j = 0; j < L1; ++j) offs[j] = offs0[j] + offs[j];                          \
}                                                                                        \
void preisach_inverse_##SUF(                                                             \
        const T* y, T* r, const T* alpha, const T* beta, const T* offs0, const T* doffs, \
        const T* lin_g, const T* cap, const T* level, const T* lower, const T* upper,    \
        T linear, T center, T scale, int graded, T* x, T* offs, T* edge,                 \
        long B, long Tn, long K, long L, long refresh) {                                 \
    const long L1 = L + 1;                                                               \
    for (long b = 0; b < B; ++b) {                                                       \
        T* rb = r + b * K;                                                               \
        offs_sum_##SUF(offs0, doffs, rb, offs, K, L1);                                   \
        for (long j = 0; j < L; ++j) edge[j] = lin_g[j] + offs[j + 1];                   \
        long since = 0;                                                                  \
        for (long t = 0; t < Tn; ++t) {                                                  \
            const T yt = y[b * Tn + t];                                                  \
            long lo = 0, hi = L;               /* first j with edge[j] >= yt */          \
            while (lo < hi) {                                                            \
                const long mid = lo + (hi - lo) / 2;                                     \
                if (edge[mid] < yt) lo = mid + 1; else hi = mid;                         \
            }                                                                            \
            const long m = lo;                                                           \
            const T g = (yt - offs[m]) / linear;                                         \
            const T c = cap[m];                                                          \
            T v = g < c ? g : c;                                                         \
            if (graded) v = center + scale * SINH((v - center) / scale);                 \
            v = v < upper[m] ? v : upper[m];                                             \
            v = v > lower[m] ? v : lower[m];                                             \
            const T xt = g >= c ? level[m] : v;                                          \
            x[b * Tn + t] = xt;                                                          \
            long switched = 0;                                                           \
            for (long k = 0; k < K; ++k) {                                               \
                const T nr = xt >= alpha[k] ? (T)1 : (xt <= beta[k] ? (T)-1 : rb[k]);    \
                if (nr != rb[k]) {                                                       \
                    const T d = nr - rb[k];                                              \
                    const T* row = doffs + k * L1;                                       \
                    for (long j = 0; j < L1; ++j) offs[j] += d * row[j];                 \
                    rb[k] = nr;                                                          \
                    switched = 1;                                                        \
                }                                                                        \
            }                                                                            \
            if (switched) {                                                              \
                if (++since >= refresh) {                                                \
                    offs_sum_##SUF(offs0, doffs, rb, offs, K, L1);                       \
                    since = 0;                                                           \
                }                                                                        \
                for (long j = 0; j < L; ++j) edge[j] = lin_g[j] + offs[j + 1];           \
            }                                                                            \
        }                                                                                \
    }                                                                                    \
}
PREISACH_INVERSE_DEFINE(float, f32, sinhf)
PREISACH_INVERSE_DEFINE(double, f64, sinh)
"""


@functools.lru_cache(maxsize=1)
def _load() -> ctypes.CDLL | None:
    p, lng, i = ctypes.c_void_p, ctypes.c_long, ctypes.c_int
    lib, _ = build("preisach_inverse", _SOURCE, what="Preisach-inverse kernel",
                   fallback="the windowed torch path", argtypes=None)
    if lib is not None:
        for suffix, real in (("f32", ctypes.c_float), ("f64", ctypes.c_double)):
            getattr(lib, f"preisach_inverse_{suffix}").argtypes = (
                [p] * 11 + [real, real, real, i] + [p] * 3 + [lng] * 5)
    return lib


def inverse_kernel_available(*tensors: Tensor) -> bool:
    """Whether the kernel can serve these tensors (CPU, float32 or float64, none needing a
    gradient while gradients are on) and is built."""
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    return not needs_grad and servable(*tensors) and _load() is not None


def inverse_kernel(y: Tensor, r: Tensor, alpha: Tensor, beta: Tensor,
                   tables: tuple[Tensor, ...], linear: Tensor, center: float,
                   scale: float | None) -> tuple[Tensor, Tensor]:
    """What :func:`~torchhys.functional.preisach_inverse._inverse_windows` returns, for y
    (B, T) from relays r (B, K) with the tables of
    :func:`~torchhys.functional.preisach_inverse.preisach_inverse_constants`: ``(x, r)``,
    x (B, T) and the relays at the last sample. The op ``torchhys::preisach_inverse`` where
    the call is traced or transformed, else its implementation directly."""
    args = (y, r, alpha, beta, *tables)
    if dispatched(*args):
        return inverse_op(*args, float(linear), float(center), scale)
    return _inverse_impl(*args, float(linear), float(center), scale)


def _inverse_impl(y: Tensor, r: Tensor, alpha: Tensor, beta: Tensor, *rest: object
                  ) -> tuple[Tensor, Tensor]:
    *tables, linear, center, scale = rest
    dtype = y.dtype
    offs0, doffs, lin_g, cap, level, bounds = (t.detach().to(dtype).contiguous()  # type: ignore[union-attr]
                                               for t in tables)
    y = y.detach().contiguous()
    r = r.detach().to(dtype).clone().contiguous()
    alpha, beta = alpha.detach().to(dtype).contiguous(), beta.detach().to(dtype).contiguous()
    B, T = y.shape
    K, L = alpha.shape[0], lin_g.shape[0]
    lower, upper = bounds[0].contiguous(), bounds[1].contiguous()
    x = torch.empty_like(y)
    offs, edge = torch.empty(L + 1, dtype=dtype), torch.empty(max(L, 1), dtype=dtype)
    fn = getattr(_load(), f"preisach_inverse_{_SUFFIX[dtype]}")
    fn(y.data_ptr(), r.data_ptr(), alpha.data_ptr(), beta.data_ptr(), offs0.data_ptr(),
       doffs.data_ptr(), lin_g.data_ptr(), cap.data_ptr(), level.data_ptr(), lower.data_ptr(),
       upper.data_ptr(), float(linear), float(center), 1.0 if scale is None else float(scale),
       0 if scale is None else 1, x.data_ptr(), offs.data_ptr(), edge.data_ptr(), B, T, K, L,
       REFRESH)
    return x, r


@torch.library.custom_op("torchhys::preisach_inverse", mutates_args=())
def inverse_op(y: Tensor, r: Tensor, alpha: Tensor, beta: Tensor, offs0: Tensor,
               doffs: Tensor, lin_g: Tensor, cap: Tensor, level: Tensor, bounds: Tensor,
               linear: float, center: float, scale: Optional[float]  # noqa: UP045
               ) -> tuple[Tensor, Tensor]:
    """:func:`inverse_kernel` with the tables spelled out and ``linear`` a number."""
    if _load() is None:
        raise RuntimeError("torchhys::preisach_inverse needs the compiled Preisach-inverse "
                           "kernel, which is not built here (inverse_kernel_available is "
                           "False); use torchhys.functional.preisach_inverse")
    return _inverse_impl(y, r, alpha, beta, offs0, doffs, lin_g, cap, level, bounds, linear,
                         center, scale)


@inverse_op.register_fake
def _(y: Tensor, r: Tensor, *_: object) -> tuple[Tensor, Tensor]:
    return y.new_empty(y.shape), y.new_empty(r.shape)


def _no_gradient(ctx, *grads):  # noqa: ANN001, ANN002, ANN202
    raise RuntimeError("torchhys::preisach_inverse has no gradient (it runs where nothing "
                       "needs one); torchhys.functional.preisach_inverse takes its torch path "
                       "when a gradient is asked for")


inverse_op.register_autograd(_no_gradient, setup_context=lambda ctx, inputs, output: None)
loop_vmap(inverse_op)
