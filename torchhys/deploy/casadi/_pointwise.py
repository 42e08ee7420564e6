"""Pointwise translations of :mod:`torchhys.deploy.casadi` (see
:mod:`torchhys.deploy.casadi._ops`): each maps the elements of its operands, broadcast, to
CasADi ``SX`` expressions. The non-smooth ones are CasADi's ``fmin``, ``fmax``, ``fabs``,
``sign``, ``floor``, ``ceil`` and ``if_else``: their derivatives are one side's at a kink
(``fmax(a, b)``'s is ``a``'s where ``a > b``). Differences from torch's kernels, where a
NaN is an operand: ``maximum``, ``minimum``, ``clamp`` and ``relu`` are ``fmax``/``fmin``
(C's: a NaN operand gives the other one, where torch gives NaN) and ``sign(NaN)`` is NaN
(torch: 0); the compensator's step tests its sample for NaN and inf before these, and holds
it (:mod:`torchhys.deploy.casadi._walk`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch

from torchhys.deploy.casadi._values import (
    Sym,
    Unsupported,
    casadi,
    cast,
    dtype_of,
    elementwise,
    finite,
    select,
    trunc,
)

Translation = Callable[..., Any]


def _map(fn: Callable[..., Any], n: int = 1) -> Translation:
    """The translation of an op whose first ``n`` arguments are mapped by ``fn``."""
    def translate(spec: Any, *args: Any) -> Sym:
        return elementwise(fn, spec, *args[:n])
    return translate


def _unary(name: str) -> Translation:
    return _map(lambda e: getattr(casadi(), name)(e))


def _alpha(sign: int, swap: bool = False) -> Translation:
    """add / sub / rsub with torch's ``alpha``: ``a + alpha * b``."""
    def translate(spec: Any, a: Any, b: Any, alpha: float = 1) -> Sym:
        if swap:
            a, b = b, a
        if alpha == 1:
            return elementwise((lambda p, q: p + q) if sign > 0 else (lambda p, q: p - q),
                               spec, a, b)
        return elementwise(lambda p, q: p + sign * alpha * q, spec, a, b)
    return translate


def _div(spec: Any, a: Any, b: Any, *, rounding_mode: str | None = None) -> Sym:
    ca = casadi()
    if rounding_mode is None:
        return elementwise(lambda p, q: p / q, spec, a, b)
    if rounding_mode == "trunc":
        return elementwise(lambda p, q: trunc(p / q), spec, a, b)
    return elementwise(lambda p, q: ca.floor(p / q), spec, a, b)


def _addc(kind: str) -> Translation:
    def translate(spec: Any, x: Any, t1: Any, t2: Any, *, value: float = 1) -> Sym:
        if kind == "mul":
            return elementwise(lambda s, p, q: s + value * p * q if value != 1 else s + p * q,
                               spec, x, t1, t2)
        return elementwise(lambda s, p, q: s + value * p / q if value != 1 else s + p / q,
                           spec, x, t1, t2)
    return translate


def _pow_scalar(spec: Any, x: Any, exponent: float) -> Sym:
    ca = casadi()
    special = {0: lambda e: 1 + 0 * e, 1: lambda e: e, 2: lambda e: e * e,
               3: lambda e: e * e * e, -2: lambda e: 1 / (e * e), 0.5: ca.sqrt,
               -0.5: lambda e: 1 / ca.sqrt(e), -1: lambda e: 1 / e}
    return elementwise(special.get(exponent, lambda e: e ** exponent), spec, x)


def _clamp(spec: Any, x: Any, min: Any = None, max: Any = None) -> Sym:
    ca = casadi()
    if min is None and max is None:
        return elementwise(lambda e: e, spec, x)
    if max is None:
        return elementwise(ca.fmax, spec, x, min)
    if min is None:
        return elementwise(ca.fmin, spec, x, max)
    return elementwise(lambda e, lo, hi: ca.fmin(ca.fmax(e, lo), hi), spec, x, min, max)


def _where(spec: Any, c: Any, a: Any, b: Any) -> Sym:
    return elementwise(select, spec, c, a, b)


def _masked_fill(spec: Any, x: Any, mask: Any, value: Any) -> Sym:
    return elementwise(lambda e, m, v: select(m, v, e), spec, x, mask, value)


def _to(spec: Any, x: Any, *args: Any, **kwargs: Any) -> Sym:
    return cast(x, spec.dtype)


def _remainder(p: Any, q: Any) -> Any:
    """torch's remainder: the sign of the divisor."""
    return p - casadi().floor(p / q) * q


def _sigmoid(e: Any) -> Any:
    return 1 / (1 + casadi().exp(-e))


def _softplus(spec: Any, x: Any, beta: float = 1.0, threshold: float = 20.0) -> Sym:
    ca = casadi()
    return elementwise(lambda e: select(e * beta > threshold, e,
                                        ca.log1p(ca.exp(e * beta)) / beta), spec, x)


def _elu(alpha: float = 1.0, scale: float = 1.0, input_scale: float = 1.0) -> Callable:
    ca = casadi()
    return lambda e: select(e <= 0, ca.expm1(e * input_scale) * alpha * scale, e * scale)


def _gelu(spec: Any, x: Any, *, approximate: str = "none") -> Sym:
    ca = casadi()
    if approximate == "tanh":
        c = math.sqrt(2 / math.pi)
        return elementwise(lambda e: 0.5 * e * (1 + ca.tanh(c * (e + 0.044715 * e * e * e))),
                           spec, x)
    return elementwise(lambda e: e * 0.5 * (1 + ca.erf(e * 0.70710678118654757)), spec, x)


def _compare(name: str) -> Translation:
    return _map(lambda p, q: getattr(casadi(), name)(p, q), 2)


def _integral_or(fn: Callable[[Any], Any]) -> Translation:
    """floor / ceil / trunc: an integer tensor is its own."""
    def translate(spec: Any, x: Any) -> Sym:
        if not dtype_of(x).is_floating_point:
            return elementwise(lambda e: e, spec, x)
        return elementwise(fn, spec, x)
    return translate


def _test(kind: str) -> Translation:
    """isnan / isinf / isfinite of a float (an integer's answer is a constant)."""
    ca = casadi()
    fns = {"isfinite": finite, "isinf": lambda e: ca.fabs(e) == ca.inf,
           "isnan": lambda e: ca.logic_not(ca.logic_or(finite(e), ca.fabs(e) == ca.inf))}

    def translate(spec: Any, x: Any) -> Sym:
        if not dtype_of(x).is_floating_point:
            return elementwise(lambda e: 0 * e + (kind == "isfinite"), spec, x)
        return elementwise(fns[kind], spec, x)
    return translate


def _not_supported(what: str) -> Translation:
    def translate(spec: Any, *args: Any, **kwargs: Any) -> Sym:
        raise Unsupported(what)
    return translate


def _table() -> dict[str, Translation]:
    ca = casadi()
    logical = {"logical_and": ca.logic_and, "logical_or": ca.logic_or,
               "logical_xor": lambda p, q: ca.ne(ca.logic_not(p), ca.logic_not(q))}
    unary = ("sqrt", "exp", "expm1", "log", "log1p", "log2", "log10", "sin", "cos", "tan",
             "asin", "acos", "atan", "sinh", "cosh", "asinh", "acosh", "atanh", "erf", "tanh")
    return {
        **{f"add.{v}": _alpha(1) for v in ("Tensor", "Scalar")},
        **{f"sub.{v}": _alpha(-1) for v in ("Tensor", "Scalar")},
        **{f"rsub.{v}": _alpha(-1, swap=True) for v in ("Tensor", "Scalar")},
        "mul.Tensor": _map(lambda p, q: p * q, 2), "mul.Scalar": _map(lambda p, q: p * q, 2),
        "div.Tensor": _div, "div.Scalar": _div, "div.Tensor_mode": _div,
        "div.Scalar_mode": _div,
        "addcmul.default": _addc("mul"), "addcdiv.default": _addc("div"),
        "neg.default": _map(lambda e: -e), "square.default": _map(lambda e: e * e),
        "abs.default": _map(ca.fabs), "sign.default": _map(ca.sign),
        "reciprocal.default": _map(lambda e: 1 / e),
        "rsqrt.default": _map(lambda e: 1 / ca.sqrt(e)),
        "sigmoid.default": _map(_sigmoid),
        **{f"{n}.default": _unary(n) for n in unary},
        "exp2.default": _map(lambda e: 2 ** e), "erfc.default": _map(lambda e: 1 - ca.erf(e)),
        "relu.default": _map(lambda e: ca.fmax(e, 0)),
        "relu6.default": _map(lambda e: ca.fmin(ca.fmax(e, 0), 6)),
        "leaky_relu.default": lambda s, x, slope=0.01: elementwise(
            lambda e: select(e > 0, e, e * slope), s, x),
        "silu.default": _map(lambda e: e / (1 + ca.exp(-e))),
        "mish.default": _map(lambda e: e * ca.tanh(ca.log1p(ca.exp(e)))),
        "elu.default": lambda s, x, alpha=1.0, scale=1.0, input_scale=1.0: elementwise(
            _elu(alpha, scale, input_scale), s, x),
        "selu.default": _map(_elu(1.6732632423543772848170429916717,
                                  1.0507009873554804934193349852946)),
        "celu.default": lambda s, x, alpha=1.0: elementwise(_elu(alpha, 1.0, 1.0 / alpha), s, x),
        "softplus.default": _softplus,
        "hardtanh.default": lambda s, x, min_val=-1.0, max_val=1.0: _clamp(s, x, min_val,
                                                                           max_val),
        "hardsigmoid.default": _map(lambda e: ca.fmin(ca.fmax(e + 3, 0), 6) / 6),
        "hardswish.default": _map(lambda e: e * ca.fmin(ca.fmax(e + 3, 0), 6) / 6),
        "gelu.default": _gelu,
        "floor.default": _integral_or(ca.floor), "ceil.default": _integral_or(ca.ceil),
        "trunc.default": _integral_or(trunc),
        "round.default": _not_supported("round (half to even) has no CasADi translation"),
        "copysign.Tensor": _map(ca.copysign, 2), "copysign.Scalar": _map(ca.copysign, 2),
        "atan2.default": _map(ca.atan2, 2),
        "pow.Tensor_Tensor": _map(ca.power, 2), "pow.Tensor_Scalar": _pow_scalar,
        "maximum.default": _map(ca.fmax, 2), "minimum.default": _map(ca.fmin, 2),
        "fmax.default": _map(ca.fmax, 2), "fmin.default": _map(ca.fmin, 2),
        "remainder.Tensor": _map(_remainder, 2), "remainder.Scalar": _map(_remainder, 2),
        "fmod.Tensor": _map(ca.fmod, 2), "fmod.Scalar": _map(ca.fmod, 2),
        "clamp.default": _clamp, "clamp.Tensor": _clamp,
        "clamp_min.default": lambda s, x, v: _clamp(s, x, min=v),
        "clamp_min.Tensor": lambda s, x, v: _clamp(s, x, min=v),
        "clamp_max.default": lambda s, x, v: _clamp(s, x, max=v),
        "clamp_max.Tensor": lambda s, x, v: _clamp(s, x, max=v),
        **{f"{k}.{v}": _compare(k) for k in ("eq", "ne", "lt", "le", "gt", "ge")
           for v in ("Tensor", "Scalar")},
        **{f"{k}.default": _map(f, 2) for k, f in logical.items()},
        "logical_not.default": _map(ca.logic_not),
        # bitwise ops of bools (the step's masks): an integer's bits have no translation
        **{f"{p}.Tensor": _bitwise(f) for k, f in (("and", ca.logic_and),
                                                    ("or", ca.logic_or),
                                                    ("xor", logical["logical_xor"]))
           for p in (f"bitwise_{k}", f"__{k}__")},
        "bitwise_not.default": _bitwise(ca.logic_not, 1),
        "where.self": _where, "where.ScalarOther": _where, "where.ScalarSelf": _where,
        "where.Scalar": _where, "masked_fill.Scalar": _masked_fill,
        "masked_fill.Tensor": _masked_fill,
        "isnan.default": _test("isnan"), "isinf.default": _test("isinf"),
        "isfinite.default": _test("isfinite"),
        "to.dtype": _to, "_to_copy.default": _to, "to.dtype_layout": _to,
    }


def _bitwise(fn: Callable[..., Any], n: int = 2) -> Translation:
    def translate(spec: Any, *args: Any) -> Sym:
        if any(dtype_of(a) != torch.bool for a in args[:n]):
            raise Unsupported("a bitwise op of integers has no CasADi translation")
        return elementwise(fn, spec, *args[:n])
    return translate


POINTWISE = _table
