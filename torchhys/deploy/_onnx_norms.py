"""ONNX translations of the normalisation layers for :func:`torchhys.deploy.export_onnx.to_onnx`
(merged into its ``_translations``): layer norm and eval-mode batch norm in primitive ops.

The exporter's own write ONNX's ``LayerNormalization`` and ``BatchNormalization``, whose
``epsilon`` is a float32 attribute: a float64 step's ``eps`` is rounded to float32, which
moved a composed model's float64 commands by 2.1e-11 of their scale (a layer norm of
``eps=1e-5``), 3.2e-9 (``eps=1e-3``) and 4.4e-11 (a batch norm of ``eps=1e-3``), against 6e-16
for an ``eps`` that float32 holds exactly. Here ``eps`` is a float64 constant:

* ``layer_norm`` (and ``native_layer_norm``): the mean, then the mean of the squared
  deviations from it (two passes), ``(x - mean) * (1 / sqrt(var + eps))``, times the
  weight, plus the bias (torch's order).
* ``_native_batch_norm_legit_no_training`` (eval mode): ``x * scale + shift`` over the
  channel dim 1, ``scale = weight / sqrt(running_var + eps)``, ``shift = bias -
  running_mean * scale`` (constants the exporter's optimizer folds).

RMS norm decomposes into elementwise ops and ``ReduceMean`` (its ``eps`` a Python number,
kept in float64 by the ``scalar_tensor`` translation); softmax and log-softmax are ONNX's
own ``Softmax`` and ``LogSoftmax``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch


def norm_translations(const: Callable[[float, Any], Any]) -> dict[Any, Any]:
    """The translations (module docstring); ``const(value, like)``: ``value`` as a float64
    constant cast to the dtype of ``like``."""
    import numpy as np
    from onnxscript import ir
    from onnxscript import opset18 as op

    def native_layer_norm(x, normalized_shape: Sequence[int], weight=None, bias=None,
                          eps: float = 1e-5):
        axes = op.Constant(value_ints=[-k for k in range(len(normalized_shape), 0, -1)])
        mean = op.ReduceMean(x, axes, keepdims=1)
        d = op.Sub(x, mean)
        var = op.ReduceMean(op.Mul(d, d), axes, keepdims=1)
        rstd = op.Reciprocal(op.Sqrt(op.Add(var, const(eps, x))))
        y = op.Mul(d, rstd)
        if weight is not None:
            y = op.Mul(y, weight)
        if bias is not None:
            y = op.Add(y, bias)
        return y, mean, rstd

    def layer_norm(x, normalized_shape: Sequence[int], weight=None, bias=None,
                   eps: float = 1e-5, cudnn_enable: bool = True):
        return native_layer_norm(x, normalized_shape, weight, bias, eps)[0]

    def batch_norm_no_training(x, weight, bias, running_mean, running_var,
                               momentum: float = 0.1, eps: float = 1e-5):
        scale = op.Reciprocal(op.Sqrt(op.Add(running_var, const(eps, running_var))))
        if weight is not None:
            scale = op.Mul(scale, weight)
        shift = op.Neg(op.Mul(running_mean, scale))
        if bias is not None:
            shift = op.Add(bias, shift)
        # (C,) -> (C, 1, ..., 1) against x (N, C, ...)
        shape = op.Constant(value_ints=[-1] + [1] * (len(x.shape) - 2))
        y = op.Add(op.Mul(x, op.Reshape(op.CastLike(scale, x), shape)),
                   op.Reshape(op.CastLike(shift, x), shape))
        empty = op.CastLike(op.Constant(value=ir.tensor(np.zeros(0, dtype=np.float64))), x)
        return y, empty, empty

    return {torch.ops.aten.layer_norm.default: layer_norm,
            torch.ops.aten.native_layer_norm.default: native_layer_norm,
            torch.ops.aten._native_batch_norm_legit_no_training.default:
                batch_norm_no_training}
