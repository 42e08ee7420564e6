"""C templates of :mod:`torchhys.deploy.c` that normalise: ``layer_norm``, ``rms_norm``,
``batch_norm`` (eval mode, folded), ``softmax`` and ``log_softmax``. Registered in
:mod:`torchhys.deploy.c._templates`.

* ``layer_norm`` over the last dims: the mean, then the (biased) variance of the deviations
  from it (two passes, in the step's dtype), ``(x - mean) * rstd`` with ``rstd = 1 /
  sqrt(var + eps)``, times the weight, plus the bias, where the layer has them.
* ``rms_norm``: ``x * (1 / sqrt(mean(x^2) + eps))`` times the weight (torch's order);
  ``eps=None`` is the dtype's machine epsilon, as torch's.
* ``batch_norm`` in eval mode with running statistics: folded when the C is written into a
  per-channel scale ``weight / sqrt(running_var + eps)`` and shift ``bias - running_mean *
  scale``, computed in float64 and cast to the step's dtype; the C is one multiply and one
  add an element. In training mode, or without running statistics
  (``track_running_stats=False``), it normalises by the batch's own statistics: refused
  (:class:`Refused`).
* ``softmax`` / ``log_softmax`` over one dim: the slice's maximum subtracted first (NaN
  propagates through it), the writer's ``exp``; ``exp(x - max) * (1 / sum)``, resp. ``x -
  max - log(sum)``, as torch's CPU kernels.
NaN in a slice gives NaN over the slice, as torch's kernels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from torchhys.deploy.c._pointwise import pointwise
from torchhys.deploy.c._products import _block
from torchhys.deploy.c._views import Emitter, _dim
from torchhys.deploy.c._writer import CTensor, Writer, constant


class Refused(ValueError):
    """A node the C does not write as it stands, with what to do instead: :func:`to_c`
    raises it at once, naming the node (not as a missing template)."""


def _constant(t: CTensor | None, what: str) -> torch.Tensor | None:
    if t is None:
        return None
    if t.value is None:
        raise ValueError(f"{what} must be a constant (a parameter or a buffer)")
    return t.value


def _norm(w: Writer, spec: CTensor, x: CTensor, k: int, weight: CTensor | None,
          bias: CTensor | None, eps: float, rms: bool) -> CTensor:
    """``x`` normalised over its last ``k`` dims (layer norm, or ``rms``), see the module
    docstring."""
    n = len(x.shape)
    if not 0 < k <= n:
        raise ValueError(f"normalized_shape of {k} dims over a tensor of {n}")
    lead, inner = list(x.shape[:n - k]), list(x.shape[n - k:])
    dtype, count = spec.dtype, math.prod(inner)
    if not dtype.is_floating_point:
        raise ValueError(f"no normalisation of {dtype}")
    out = w.local(dtype, spec.shape)
    if out.numel == 0:
        return out
    t, f = w.ctype(dtype), "f" if dtype == torch.float32 else ""
    zero, size = w.literal(0, dtype), w.literal(count, dtype)
    one, epsilon = w.literal(1, dtype), w.literal(eps, dtype)

    def at(x: CTensor, lidx: list[str], ridx: list[str]) -> str:
        return w.cast(w.read(x, [*lidx, *ridx]), x.dtype, dtype)

    def param(p: CTensor, ridx: list[str]) -> str:
        return w.cast(w.read(p, ridx), p.dtype, dtype)

    with w.loop(lead) as lidx:
        def body() -> None:
            if rms:
                w.emit(f"{t} ms = {zero};")
                with w.loop(inner) as ridx:
                    w.emit(f"{t} v = {at(x, lidx, ridx)};")
                    w.emit("ms += v * v;")
                w.emit(f"{t} r = {one} / sqrt{f}(ms / {size} + {epsilon});")
                value = "({x} * r)"
            else:
                w.emit(f"{t} mean = {zero};")
                w.emit(f"{t} var = {zero};")
                with w.loop(inner) as ridx:
                    w.emit(f"mean += {at(x, lidx, ridx)};")
                w.emit(f"mean = mean / {size};")
                with w.loop(inner) as ridx:
                    w.emit(f"{t} d = {at(x, lidx, ridx)} - mean;")
                    w.emit("var += d * d;")
                w.emit(f"{t} r = {one} / sqrt{f}(var / {size} + {epsilon});")
                value = "(({x} - mean) * r)"
            with w.loop(inner) as ridx:
                v = value.format(x=at(x, lidx, ridx))
                if weight is not None:
                    v = f"{v} * {param(weight, ridx)}"
                if bias is not None:
                    v = f"{v} + {param(bias, ridx)}"
                w.emit(f"{w.read(out, [*lidx, *ridx])} = {v};")
        _block(w, body)
    return out


def _layer_norm(w: Writer, spec: CTensor, x: CTensor, normalized_shape: Sequence[int],
                weight: CTensor | None = None, bias: CTensor | None = None,
                eps: float = 1e-5, cudnn_enable: bool = True) -> CTensor:
    return _norm(w, spec, x, len(normalized_shape), weight, bias, eps, rms=False)


def _rms_norm(w: Writer, spec: CTensor, x: CTensor, normalized_shape: Sequence[int],
              weight: CTensor | None = None, eps: float | None = None) -> CTensor:
    if eps is None:  # torch's default: the machine epsilon of the compute dtype
        eps = torch.finfo(spec.dtype).eps
    return _norm(w, spec, x, len(normalized_shape), weight, None, eps, rms=True)


#: what to do about a batch norm that normalises by its batch
TRAINING = ("a batch norm in training mode normalises by the batch's own statistics: call "
            ".eval() on the model before exporting (the C uses the running statistics)")
NO_RUNNING_STATS = ("a batch norm without running statistics (track_running_stats=False) "
                    "normalises by the batch's own statistics, so its output depends on the "
                    "batch: give it running statistics (track_running_stats=True), train, "
                    "and call .eval()")


def folded(weight: torch.Tensor | None, bias: torch.Tensor | None, mean: torch.Tensor,
           var: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch norm in eval mode as a per-channel ``(scale, shift)`` in float64:
    ``scale = weight / sqrt(var + eps)``, ``shift = bias - mean * scale``."""
    var64, mean64 = var.detach().double(), mean.detach().double()
    scale = 1.0 / torch.sqrt(var64 + float(eps))
    if weight is not None:
        scale = scale * weight.detach().double()
    shift = -mean64 * scale
    if bias is not None:
        shift = bias.detach().double() + shift
    return scale, shift


def _batch_norm(w: Writer, spec: CTensor, x: CTensor, weight: CTensor | None,
                bias: CTensor | None, running_mean: CTensor | None,
                running_var: CTensor | None, training: bool, momentum: float, eps: float,
                cudnn_enabled: bool = True) -> CTensor:
    """torch's eval-mode batch norm, folded (module docstring): ``x * scale[c] + shift[c]``
    over the channel dim 1."""
    if running_mean is None or running_var is None:
        raise Refused(NO_RUNNING_STATS)
    if training:
        raise Refused(TRAINING)
    if len(x.shape) < 2 or not spec.dtype.is_floating_point:
        raise ValueError(f"batch_norm of a {len(x.shape)}-dim {x.dtype} input")
    values = [_constant(t, name) for t, name in ((weight, "the weight"), (bias, "the bias"),
                                                 (running_mean, "running_mean"),
                                                 (running_var, "running_var"))]
    scale, shift = folded(*values, eps)
    shape = (x.shape[1],) + (1,) * (len(x.shape) - 2)
    scale = constant(scale.to(spec.dtype).reshape(shape))
    shift = constant(shift.to(spec.dtype).reshape(shape))
    return pointwise(w, spec, "({0} * {1} + {2})", [x, scale, shift])


def _softmax(log: bool) -> Emitter:
    """softmax / log_softmax over ``dim`` (module docstring), in the output's dtype."""
    def emit(w: Writer, spec: CTensor, x: CTensor, dim: int, *rest: object,
             **kwargs: object) -> CTensor:
        dtype, n = spec.dtype, len(x.shape)
        if not dtype.is_floating_point:
            raise ValueError(f"no softmax of {dtype}")
        out = w.local(dtype, spec.shape)
        if out.numel == 0:
            return out
        d = _dim(dim, n)
        t, f = w.ctype(dtype), "f" if dtype == torch.float32 else ""
        big, exp = w.helper("max", dtype), w.helper("exp", dtype)
        others = [m if i != d else 1 for i, m in enumerate(x.shape)] if n else []
        with w.loop(others) as idx:
            def body() -> None:
                def at(k: str) -> list[str]:
                    return [*idx[:d], k, *idx[d + 1:]] if n else []

                def xs(k: str) -> str:
                    return w.cast(w.read(x, at(k)), x.dtype, dtype)

                w.emit(f"{t} m = {xs('0')};")
                w.emit(f"{t} s = {w.literal(0, dtype)};")
                size = x.shape[d] if n else 1
                with w.loop([size]) as (k,):
                    w.emit(f"m = {big}(m, {xs(k)});")
                with w.loop([size]) as (k,):
                    if log:
                        w.emit(f"s += {exp}({xs(k)} - m);")
                    else:
                        w.emit(f"{w.read(out, at(k))} = {exp}({xs(k)} - m);")
                        w.emit(f"s += {w.read(out, at(k))};")
                if log:
                    w.emit(f"s = log{f}(s);")
                else:
                    w.emit(f"s = {w.literal(1, dtype)} / s;")
                with w.loop([size]) as (k,):
                    value = f"{xs(k)} - m - s" if log else f"{w.read(out, at(k))} * s"
                    w.emit(f"{w.read(out, at(k))} = {value};")
            _block(w, body)
        return out
    return emit


NORMS: dict[str, Emitter] = {
    "layer_norm.default": _layer_norm, "rms_norm.default": _rms_norm,
    "batch_norm.default": _batch_norm,
    "softmax.int": _softmax(False), "_softmax.default": _softmax(False),
    "log_softmax.int": _softmax(True), "_log_softmax.default": _softmax(True),
}
