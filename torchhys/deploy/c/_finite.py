"""The step's tests of non-finite samples, written in C from the bits of the numbers.

The compensator (:mod:`torchhys.deploy.streaming`) tests a tensor ``t`` for NaN and inf as
``t - t`` (0 exactly where ``t`` is finite, NaN where it is not): ``(x - x) + (u - u) != 0``
holds the step, ``x - x == 0`` counts a clamped finite sample. As C arithmetic these tests
are folded to constants under ``-ffinite-math-only`` (part of ``-ffast-math``), which would
let a NaN sample through. :func:`finite_test` finds such a comparison in the exported graph
(a sum of ``t - t`` terms against a zero, ``!=`` or ``==``) and :func:`emit` writes it as the
writer's ``isfinite`` test of each ``t``'s bits: the same answer for every input, and no
floating-point arithmetic for a compiler to fold.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, fx

from torchhys.deploy.c._pointwise import pointwise
from torchhys.deploy.c._writer import CTensor, Writer

_SUB = torch.ops.aten.sub.Tensor
_ADD = torch.ops.aten.add.Tensor
_NE = (torch.ops.aten.ne.Tensor, torch.ops.aten.ne.Scalar)
_EQ = (torch.ops.aten.eq.Tensor, torch.ops.aten.eq.Scalar)


def _floating(node: fx.Node) -> bool:
    val = node.meta.get("val")
    return isinstance(val, Tensor) and val.is_floating_point()


def _terms(node: object) -> list[fx.Node] | None:
    """The ``t`` of each ``t - t`` of ``node``, a sum of such differences; else None."""
    if not (isinstance(node, fx.Node) and node.op == "call_function" and len(node.args) == 2
            and not node.kwargs and _floating(node)):
        return None
    a, b = node.args
    if node.target == _SUB:
        return [a] if a is b and isinstance(a, fx.Node) and _floating(a) else None
    if node.target == _ADD:
        left, right = _terms(a), _terms(b)
        return None if left is None or right is None else left + right
    return None


def _is_zero(value: object) -> bool:
    if isinstance(value, Tensor):
        return value.numel() > 0 and bool((value == 0).all())
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value == 0


def finite_test(node: fx.Node, value: Callable[[fx.Node], Tensor | None]
                ) -> tuple[list[fx.Node], bool] | None:
    """For ``node`` a comparison ``(t1 - t1) + ... != 0`` (resp. ``== 0``) of floats: the
    ``t``'s (each once) and whether it is ``!=`` (some ``t`` not finite); else None.
    ``value(n)``: the known tensor of the node ``n`` (a buffer), or None."""
    if not (node.op == "call_function" and node.target in (*_NE, *_EQ)
            and len(node.args) == 2 and not node.kwargs):
        return None
    terms = _terms(node.args[0])
    zero = node.args[1]
    if isinstance(zero, fx.Node):
        zero = value(zero)
    if terms is None or not _is_zero(zero):
        return None
    return list(dict.fromkeys(terms)), node.target in _NE


def emit(w: Writer, spec: CTensor, operands: list[CTensor], ne: bool) -> CTensor:
    """``spec``'s bools: some operand not finite (``ne``), resp. all finite, broadcast."""
    tests = [f"{w.helper('isfinite', t.dtype)}({{{i}}})" for i, t in enumerate(operands)]
    fmt = " || ".join(f"!{t}" for t in tests) if ne else " && ".join(tests)
    return pointwise(w, spec, f"({fmt})", operands, raw=range(len(operands)))


def fold(values: list[Tensor], ne: bool, shape: tuple[int, ...]) -> Tensor:
    """The test of known ``values`` (of shape ``shape``), as :func:`emit` writes it."""
    finite = torch.ones(shape, dtype=torch.bool)
    for v in values:
        finite = finite & torch.isfinite(v)
    return ~finite if ne else finite
