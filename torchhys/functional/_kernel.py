"""A compiled CPU kernel for the play operator, with the pure-torch scan as the fallback.

The kernel is a few lines of C, compiled once with the system C compiler into a
user cache directory (``$TORCHHYS_CACHE``, default ``~/.cache/torchhys``) and loaded
with :mod:`ctypes`; no torch headers are needed, so compiling takes well under a
second. It runs the recurrence sample by sample (forward) and its adjoint in
reverse (backward) without temporaries. Where no compiler is found, on devices
other than the CPU, for dtypes other than float32/float64, or with the
environment variable ``TORCHHYS_DISABLE_KERNEL=1``, the pure-torch blocked scan of
:mod:`torchhys.functional._play_scan` is used instead; both give the same results.

The two directions are also the custom ops ``torch.ops.torchhys.play`` (x, r, y0 -> y) and
``torch.ops.torchhys.play_adjoint`` (g, x, r, y0, y -> gx, gr, gy0), each with a fake
implementation, an autograd formula and a ``vmap`` rule: :func:`play_forward` and
:func:`play_adjoint` call them where a call is traced or transformed
(:func:`~torchhys.functional._compile.dispatched`), and the implementation directly in plain
eager calls. Either way the kernel-or-scan choice is made when the op runs.
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
from torchhys.functional._play_scan import _scan_backward, _scan_forward, play_tangent

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


def _kernel_runs(*tensors: Tensor) -> bool:
    """:func:`kernel_available` for plain tensors (the implementations' inputs)."""
    return _enabled and cpu_float(*tensors) and _library() is not None


def _forward_impl(x: Tensor, r: Tensor, y0: Tensor) -> Tensor:
    if _kernel_runs(x, r, y0):
        return play_forward_kernel(x, r, y0)
    return _scan_forward(x, r, y0)[:, : x.shape[1]]


def _adjoint_impl(g: Tensor, x: Tensor, r: Tensor, y0: Tensor, y: Tensor
                  ) -> tuple[Tensor, Tensor, Tensor]:
    if _kernel_runs(g, x, r, y0, y):
        return play_backward_kernel(g, x, r, y0, y)
    return _scan_backward(g, x, r, y0, y)


@torch.library.custom_op("torchhys::play", mutates_args=())
def play_op(x: Tensor, r: Tensor, y0: Tensor) -> Tensor:
    """Play outputs y (B, T, N) of x (B, T), half-widths r (N,), initial outputs y0 (B, N):
    the compiled kernel where it can run, else the scan."""
    return _forward_impl(x, r, y0).contiguous()


@play_op.register_fake
def _(x: Tensor, r: Tensor, y0: Tensor) -> Tensor:
    return x.new_empty(x.shape[0], x.shape[1], r.shape[0])


@torch.library.custom_op("torchhys::play_adjoint", mutates_args=())
def play_adjoint_op(g: Tensor, x: Tensor, r: Tensor, y0: Tensor, y: Tensor
                    ) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients of ``sum(g * y)``, y = play(x, r, y0), with respect to x, r and y0."""
    gx, gr, gy0 = _adjoint_impl(g, x, r, y0, y)
    return gx.contiguous(), gr.contiguous(), gy0.contiguous()


@play_adjoint_op.register_fake
def _(g: Tensor, x: Tensor, r: Tensor, y0: Tensor, y: Tensor) -> tuple[Tensor, ...]:
    return x.new_empty(x.shape), r.new_empty(r.shape), y0.new_empty(y0.shape)


def _save_all(ctx, inputs, output) -> None:  # noqa: ANN001
    ctx.save_for_backward(*inputs, output)


def _play_op_backward(ctx, grad_y: Tensor) -> tuple[Tensor, Tensor, Tensor]:  # noqa: ANN001
    x, r, y0, y = ctx.saved_tensors
    return play_adjoint_op(grad_y, x, r, y0, y)


def _save_adjoint(ctx, inputs, output) -> None:  # noqa: ANN001
    ctx.save_for_backward(*inputs[1:])


def _play_adjoint_op_backward(ctx, ggx, ggr, ggy0):  # noqa: ANN001, ANN202
    x, r, y0, y = ctx.saved_tensors
    return play_tangent(x, r, y0, y, ggx, ggr, ggy0), None, None, None, None


play_op.register_autograd(_play_op_backward, setup_context=_save_all)
play_adjoint_op.register_autograd(_play_adjoint_op_backward, setup_context=_save_adjoint)
loop_vmap(play_op)
loop_vmap(play_adjoint_op)


def play_forward(x: Tensor, r: Tensor, y0: Tensor) -> Tensor:
    """Play outputs y (B, T, N) of x (B, T), r (N,), y0 (B, N): the op where the call is
    traced or transformed, else its implementation directly (kernel or scan)."""
    if dispatched(x, r, y0):
        return play_op(x, r, y0)
    return _forward_impl(x, r, y0)


def play_adjoint(g: Tensor, x: Tensor, r: Tensor, y0: Tensor, y: Tensor
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """Gradients of ``sum(g * y)`` with respect to x, r and y0 (:func:`play_forward`'s
    dispatch), without a graph."""
    if dispatched(g, x, r, y0, y):
        return play_adjoint_op(g, x, r, y0, y)
    return _adjoint_impl(g, x, r, y0, y)
