"""A compiled CPU kernel for the play operator, with the pure-torch scan as the fallback.

The kernel is a few lines of C, compiled once with the system C compiler into a
user cache directory (``$TORCHHYS_CACHE``, default ``~/.cache/torchhys``) and loaded
with :mod:`ctypes`; no torch headers are needed, so compiling takes well under a
second. It runs the recurrence sample by sample (forward) and its adjoint in
reverse (backward) without temporaries. Where no compiler is found, on devices
other than the CPU, for dtypes other than float32/float64, or with the
environment variable ``TORCHHYS_DISABLE_KERNEL=1``, the pure-torch blocked scan in
:mod:`torchhys.functional.backlash` is used instead; both give the same results.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
from collections.abc import Iterator

import torch
from torch import Tensor

from torchhys.functional._compile import SUFFIX as _SUFFIX
from torchhys.functional._compile import build, servable

_enabled = True


@contextlib.contextmanager
def kernel_enabled(enabled: bool) -> Iterator[None]:
    """Context manager that switches the compiled kernel on or off (for tests, benchmarks)."""
    global _enabled
    previous, _enabled = _enabled, bool(enabled)
    try:
        yield
    finally:
        _enabled = previous

_SOURCE = r"""
#include <stddef.h>
#define PLAY_DEFINE(T, SUF)                                                              \
void play_forward_##SUF(const T* x, const T* r, const T* y0, T* y,                       \
                        long B, long Tn, long N) {                                       \
    for (long b = 0; b < B; ++b) {                                                       \
        const T* xb = x + b * Tn;                                                        \
        T* yb = y + b * Tn * N;                                                          \
        const T* prev = y0 + b * N;                                                      \
        for (long t = 0; t < Tn; ++t) {                                                  \
            const T xt = xb[t];                                                          \
            T* yt = yb + t * N;                                                          \
            for (long n = 0; n < N; ++n) {                                               \
                const T lo = xt - r[n], hi = xt + r[n];                                  \
                T s = prev[n];                                                           \
                s = s < lo ? lo : s;                                                     \
                s = s > hi ? hi : s;                                                     \
                yt[n] = s;                                                               \
            }                                                                            \
            prev = yt;                                                                   \
        }                                                                                \
    }                                                                                    \
}                                                                                        \
void play_backward_##SUF(const T* x, const T* r, const T* y0, const T* y, const T* g,   \
                         T* gx, double* gr, T* gy0, T* lam, unsigned char* pass,         \
                         long B, long Tn, long N) {                                      \
    for (long n = 0; n < N; ++n) gr[n] = 0.0;                                            \
    for (long b = 0; b < B; ++b) {                                                       \
        for (long n = 0; n < N; ++n) { lam[n] = 0; pass[n] = 0; }                        \
        for (long t = Tn - 1; t >= 0; --t) {                                             \
            const T* prev = t > 0 ? y + (b * Tn + t - 1) * N : y0 + b * N;              \
            const T* gt = g + (b * Tn + t) * N;                                          \
            const T xt = x[b * Tn + t];                                                  \
            T acc = 0;                                                                   \
            for (long n = 0; n < N; ++n) {                                               \
                const T l = gt[n] + (pass[n] ? lam[n] : (T)0);                           \
                const T lo = xt - r[n], hi = xt + r[n];                                  \
                const T p = prev[n];                                                     \
                if (p < lo) { acc += l; gr[n] -= l; pass[n] = 0; }                       \
                else if (p > hi) { acc += l; gr[n] += l; pass[n] = 0; }                  \
                else { pass[n] = 1; }                                                    \
                lam[n] = l;                                                              \
            }                                                                            \
            gx[b * Tn + t] = acc;                                                        \
        }                                                                                \
        for (long n = 0; n < N; ++n) gy0[b * N + n] = pass[n] ? lam[n] : (T)0;          \
    }                                                                                    \
}
PLAY_DEFINE(float, f32)
PLAY_DEFINE(double, f64)
"""

@functools.lru_cache(maxsize=1)
def _load() -> tuple[ctypes.CDLL | None, str | None]:
    """The compiled library, or None and the reason it cannot be used."""
    p, lng = ctypes.c_void_p, ctypes.c_long
    return build("play", _SOURCE, what="play-operator kernel", fallback="the pure-torch scan",
                 argtypes={"play_forward": [p, p, p, p, lng, lng, lng],
                           "play_backward": [p] * 10 + [lng, lng, lng]})


def _library() -> ctypes.CDLL | None:
    return _load()[0]


def kernel_unavailable_reason() -> str | None:
    """Why the compiled kernel cannot run on this machine, or None when it can.

    Reasons: ``TORCHHYS_DISABLE_KERNEL`` is set, no C compiler is found, or the build
    failed. (Per call, the kernel also needs CPU float32/float64 tensors and
    :func:`kernel_enabled` not switched off: see :func:`kernel_available`.)
    """
    return _load()[1]


def kernel_available(*tensors: Tensor) -> bool:
    """Whether the compiled kernel can serve these tensors (CPU, float32 or float64)."""
    return _enabled and servable(*tensors) and _library() is not None


def _ptr(t: Tensor) -> int:
    return t.data_ptr()


def play_forward_kernel(x: Tensor, r: Tensor, y0: Tensor) -> Tensor:
    """x (B, T), r (N,), y0 (B, N) -> y (B, T, N), with the compiled kernel."""
    x, r, y0 = x.contiguous(), r.contiguous(), y0.contiguous()
    B, T = x.shape
    N = r.shape[0]
    y = torch.empty(B, T, N, dtype=x.dtype)
    fn = getattr(_library(), f"play_forward_{_SUFFIX[x.dtype]}")
    fn(_ptr(x), _ptr(r), _ptr(y0), _ptr(y), B, T, N)
    return y


def play_backward_kernel(
    g: Tensor, x: Tensor, r: Tensor, y0: Tensor, y: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients of sum(g * y) with respect to x (B, T), r (N,) and y0 (B, N)."""
    g, x, r, y0, y = (t.contiguous() for t in (g, x, r, y0, y))
    B, T = x.shape
    N = r.shape[0]
    gx = torch.empty(B, T, dtype=x.dtype)
    gr = torch.empty(N, dtype=torch.float64)
    gy0 = torch.empty(B, N, dtype=x.dtype)
    lam = torch.empty(N, dtype=x.dtype)
    passing = torch.empty(N, dtype=torch.uint8)
    fn = getattr(_library(), f"play_backward_{_SUFFIX[x.dtype]}")
    fn(
        _ptr(x), _ptr(r), _ptr(y0), _ptr(y), _ptr(g),
        _ptr(gx), _ptr(gr), _ptr(gy0), _ptr(lam), _ptr(passing), B, T, N,
    )
    return gx, gr.to(x.dtype), gy0
