"""Pointwise C templates of :mod:`torchhys.deploy.c` (see
:mod:`torchhys.deploy.c._templates`).

Each reproduces torch's CPU kernel, NaN included: ``maximum``, ``minimum`` and ``clamp``
propagate NaN (unlike C's ``fmax``), ``sign(NaN)`` is 0, ``pow`` takes torch's special
exponents (2, 3, -2, 0.5, -0.5, -1), ``sigmoid`` is ``1 / (1 + exp(-x))``; ``exp``,
``sigmoid`` and ``tanh`` are the writer's vectorizable ones (within 1, 4 and 3 ulp of libm's
in float64; in float32 ``exp`` and ``tanh`` within 1 and 4, ``sigmoid`` computed with that
``exp``).
Operands are cast to the op's compute dtype first (torch's type promotion), as torch's
kernels do.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import torch

from torchhys.deploy.c._writer import CTensor, Writer, contiguous_strides

Emitter = Callable[..., Any]
Operand = CTensor | float | int | bool


def promoted(*xs: Operand) -> torch.dtype:
    """torch's result type of the operands (0-dim tensors and numbers rank lower)."""
    from torch._prims_common import ELEMENTWISE_TYPE_PROMOTION_KIND, elementwise_dtypes

    dummies = [torch.empty((1,) * len(x.shape), dtype=x.dtype) if isinstance(x, CTensor)
               else x for x in xs]
    return elementwise_dtypes(
        *dummies, type_promotion_kind=ELEMENTWISE_TYPE_PROMOTION_KIND.DEFAULT)[1]


def pointwise(w: Writer, spec: CTensor, fmt: str | dict[str, str], operands: Sequence[Operand],
              compute: torch.dtype | None = None, raw: Sequence[int] = ()) -> CTensor:
    """``spec``'s elements from ``fmt`` (``{0}``, ``{1}``: the operands, broadcast and cast
    to ``compute`` (default: the output dtype) except those in ``raw``; ``{T}``: the compute
    C type; ``{f}``: the math functions' suffix). A dict ``fmt`` is chosen by the compute
    dtype's kind: ``float``, ``int`` or ``bool`` (a missing ``bool`` falls back on ``int``)."""
    compute = compute or spec.dtype
    if isinstance(fmt, dict):
        kind = ("float" if compute.is_floating_point else
                "bool" if compute == torch.bool and "bool" in fmt else "int")
        if kind not in fmt:
            raise ValueError(f"no template for dtype {compute}")
        fmt = fmt[kind]
    t, f = w.ctype(compute), "f" if compute == torch.float32 else ""
    # an operand read more than once by the expression is computed once, into a local
    operands = [w.materialize(x) if isinstance(x, CTensor) and fmt.count(f"{{{i}}}") > 1
                else x for i, x in enumerate(operands)]

    def element(idx: list[str]) -> str:
        args = [w.read_broadcast(x, idx, x.dtype if (i in raw and isinstance(x, CTensor))
                                 else compute) for i, x in enumerate(operands)]
        expr = fmt.format(*args, T=t, f=f)
        return expr if spec.dtype == torch.bool else w.cast(expr, compute, spec.dtype)

    if w.defer and spec.numel > 0:
        return CTensor(spec.dtype, spec.shape, contiguous_strides(spec.shape),
                       element=element)
    out = w.local(spec.dtype, spec.shape)
    w.assign(out, element)
    return out


def _op(fmt: str | dict[str, str], n: int = 1, promote: bool = False) -> Emitter:
    """A template of the first ``n`` operands; ``promote``: computed in their result type
    (comparisons), else in the output's dtype."""
    def emit(w: Writer, spec: CTensor, *args: Operand) -> CTensor:
        ops = args[:n]
        return pointwise(w, spec, fmt, ops, promoted(*ops) if promote else None)
    return emit


def _helper(kind: str, n: int = 2) -> Emitter:
    def emit(w: Writer, spec: CTensor, *args: Operand) -> CTensor:
        name = w.helper(kind, spec.dtype)
        return pointwise(w, spec, f"{name}(" + ", ".join(f"{{{i}}}" for i in range(n)) + ")",
                         args[:n])
    return emit


def _alpha(sign: str, swap: bool = False) -> Emitter:
    """add / sub / rsub with torch's ``alpha``: ``a + alpha * b``."""
    def emit(w: Writer, spec: CTensor, a: Operand, b: Operand, alpha: float = 1) -> CTensor:
        if swap:
            a, b = b, a
        if alpha == 1:
            return pointwise(w, spec, f"({{0}} {sign} {{1}})", [a, b])
        return pointwise(w, spec, f"({{0}} {sign} {{2}} * {{1}})", [a, b, alpha])
    return emit


def _addc(sign: str) -> Emitter:
    """addcmul / addcdiv: ``self + value * t1 * t2`` (resp. ``/ t2``), torch's order."""
    def emit(w: Writer, spec: CTensor, x: Operand, t1: Operand, t2: Operand, *,
             value: float = 1) -> CTensor:
        if value == 1:
            return pointwise(w, spec, f"({{0}} + {{1}} {sign} {{2}})", [x, t1, t2])
        return pointwise(w, spec, f"({{0}} + {{3}} * {{1}} {sign} {{2}})", [x, t1, t2, value])
    return emit


def _pow_scalar(w: Writer, spec: CTensor, x: CTensor, exponent: float) -> CTensor:
    special = {0: "(({T})1)", 1: "{0}", 2: "({0} * {0})", 3: "({0} * {0} * {0})",
               -2: "(({T})1 / ({0} * {0}))", 0.5: "sqrt{f}({0})",
               -0.5: "(({T})1 / sqrt{f}({0}))", -1: "(({T})1 / {0})"}
    if not spec.dtype.is_floating_point:
        raise ValueError("pow of integers has no template")
    return pointwise(w, spec, special.get(exponent, "pow{f}({0}, {1})"), [x, exponent])


def _clamp(w: Writer, spec: CTensor, x: CTensor, min: Operand | None = None,
           max: Operand | None = None) -> CTensor:
    if min is not None and max is not None:
        return pointwise(w, spec, w.helper("clamp", spec.dtype) + "({0}, {1}, {2})",
                         [x, min, max])
    if min is None and max is None:
        return x
    # one bound: std::max(a, lo) = a < lo ? lo : a (NaN a stays), resp. std::min
    return pointwise(w, spec, "(({0} < {1}) ? {1} : {0})" if max is None
                     else "(({1} < {0}) ? {1} : {0})", [x, max if min is None else min])


def _div_mode(w: Writer, spec: CTensor, a: Operand, b: Operand, *,
              rounding_mode: str | None = None) -> CTensor:
    if rounding_mode is None:
        return pointwise(w, spec, "({0} / {1})", [a, b])
    if rounding_mode == "trunc":
        return pointwise(w, spec, {"float": "trunc{f}({0} / {1})", "int": "({0} / {1})"}, [a, b])
    return pointwise(w, spec, w.helper("floordiv", spec.dtype) + "({0}, {1})", [a, b])


def _where(w: Writer, spec: CTensor, cond: CTensor, a: Operand, b: Operand) -> CTensor:
    if not (isinstance(cond, CTensor) and cond.numel == 1 and spec.numel > 1):
        return pointwise(w, spec, "({0} ? {1} : {2})", [cond, a, b], raw=[0])
    # one condition for all: two copy loops (which vectorize) under an if; a deferred
    # operand is computed in its branch only. Read by the step's outputs only (the new
    # state: the old one, held, or the new one): a pointer to one of two whole arrays
    cond_c = w.read(cond, ['0'] * len(cond.shape))
    if w.alias and w._depth == 1 and all(_whole_array(w, x, spec) for x in (a, b)):
        return w.pointer(cond_c, a, b)
    out = w.local(spec.dtype, spec.shape)
    w.emit(f"if ({cond_c}) {{")
    for k, x in enumerate((a, b)):
        if k:
            w.emit("} else {")
        w._depth += 1
        w.assign(out, lambda idx, x=x: w.read_broadcast(x, idx, spec.dtype))
        w._depth -= 1
    w.emit("}")
    return out


def _whole_array(w: Writer, x: Operand, spec: CTensor) -> bool:
    """Whether ``x`` is a whole contiguous array (a local or the state's) of ``spec``'s shape
    and dtype."""
    return (isinstance(x, CTensor) and x.element is None and x.value is None
            and bool(x.base) and x.base not in w.scalars and x.offset == 0
            and x.shape == spec.shape and x.dtype == spec.dtype and x.is_contiguous())


def _masked_fill(w: Writer, spec: CTensor, x: CTensor, mask: CTensor, value: Operand
                 ) -> CTensor:
    return pointwise(w, spec, "({1} ? {2} : {0})", [x, mask, value], raw=[1])


def _to(w: Writer, spec: CTensor, x: CTensor, *args: Any, **kwargs: Any) -> CTensor:
    """A cast to the output's dtype (a float NaN or out-of-range cast to an integer is
    undefined in C, as it is in torch's kernel)."""
    return x if spec.dtype == x.dtype else pointwise(w, spec, "{0}", [x], x.dtype)


def _gelu(w: Writer, spec: CTensor, x: CTensor, *, approximate: str = "none") -> CTensor:
    if approximate != "none":
        raise ValueError(f"gelu(approximate={approximate!r}) has no template")
    return pointwise(w, spec, "({0} * ({T})0.5 * (({T})1 + erf{f}({0} * "
                     "({T})0.70710678118654757)))", [x])


def _exp(fmt: str, helper: str | None = None) -> Emitter:
    """``fmt`` with ``EXP`` the writer's vectorizable ``exp`` of a double or a float (within
    1 ulp of libm's; a loop of libm calls does not vectorize), or in float64 its ``helper``
    of the whole expression (``sigmoid``: one division, within 4 ulp)."""
    def emit(w: Writer, spec: CTensor, x: CTensor) -> CTensor:
        if helper is not None and spec.dtype == torch.float64:
            return pointwise(w, spec, w.helper(helper, spec.dtype) + "({0})", [x])
        return pointwise(w, spec, fmt.replace("EXP", w.helper("exp", spec.dtype)), [x])
    return emit


def _elu(w: Writer, spec: CTensor, x: CTensor, alpha: float = 1.0, scale: float = 1.0,
         input_scale: float = 1.0) -> CTensor:
    """torch's elu kernel: ``x <= 0 ? expm1(x input_scale) alpha scale : x scale``."""
    return pointwise(w, spec, "(({0} <= 0) ? expm1{f}({0} * {3}) * {1} : {0} * {2})",
                     [x, float(alpha) * float(scale), float(scale), float(input_scale)])


def _softplus(w: Writer, spec: CTensor, x: CTensor, beta: float = 1.0,
              threshold: float = 20.0) -> CTensor:
    """torch's softplus kernel: ``x beta > threshold ? x : log1p(exp(x beta)) / beta``."""
    return pointwise(w, spec, "(({0} * {1} > {2}) ? {0} : log1p{f}(exp{f}({0} * {1})) / {1})",
                     [x, beta, threshold])


def _hardtanh(w: Writer, spec: CTensor, x: CTensor, min_val: float = -1.0,
              max_val: float = 1.0) -> CTensor:
    return _clamp(w, spec, x, min_val, max_val)


def _hard(fmt: str) -> Emitter:
    """hardsigmoid / hardswish over ``R = min(max(x + 3, 0), 6)`` (NaN stays NaN)."""
    def emit(w: Writer, spec: CTensor, x: CTensor) -> CTensor:
        r = w.helper("clamp", spec.dtype) + "({0} + 3, ({T})0, ({T})6)"
        return pointwise(w, spec, fmt.replace("R", r), [x])
    return emit


def _tanh(w: Writer, spec: CTensor, x: CTensor) -> CTensor:
    """The writer's vectorizable ``tanh`` (within 3 ulp of libm's in float64, 4 in float32;
    an LSTM's or a GRU's gates)."""
    return pointwise(w, spec, w.helper("tanh", spec.dtype) + "({0})", [x])


def _unary_float(name: str) -> Emitter:
    return _op(name + "{f}({0})")


def _test(kind: str, integer: str) -> Emitter:
    """isnan / isinf / isfinite: a float's bits tested (the writer's helper ``kind``, right
    under -ffast-math too), a bool out (``integer``: the answer for an integer input)."""
    def emit(w: Writer, spec: CTensor, x: CTensor) -> CTensor:
        fmt = w.helper(kind, x.dtype) + "({0})" if x.dtype.is_floating_point else integer
        return pointwise(w, spec, fmt, [x], x.dtype)
    return emit


_COMPARE = {"eq": "==", "ne": "!=", "lt": "<", "le": "<=", "gt": ">", "ge": ">="}
_LOGICAL = {"logical_and": "({0} && {1})", "logical_or": "({0} || {1})",
            "logical_xor": "(!{0} != !{1})"}
_BITWISE = {"and": "&", "or": "|", "xor": "^"}

POINTWISE: dict[str, Emitter] = {
    **{f"{k}.{v}": _alpha("+") for k in ("add",) for v in ("Tensor", "Scalar")},
    **{f"sub.{v}": _alpha("-") for v in ("Tensor", "Scalar")},
    **{f"rsub.{v}": _alpha("-", swap=True) for v in ("Tensor", "Scalar")},
    "mul.Tensor": _op("({0} * {1})", 2), "mul.Scalar": _op("({0} * {1})", 2),
    "div.Tensor": _op("({0} / {1})", 2), "div.Scalar": _op("({0} / {1})", 2),
    "div.Tensor_mode": _div_mode, "div.Scalar_mode": _div_mode,
    "addcmul.default": _addc("*"), "addcdiv.default": _addc("/"),
    "neg.default": _op("(-{0})"), "square.default": _op("({0} * {0})"),
    "abs.default": _op({"float": "fabs{f}({0})", "int": "(({0} < 0) ? -{0} : {0})"}),
    "sign.default": _op({"float": "(({T})((0 < {0}) - ({0} < 0)))",
                         "int": "(({T})((0 < {0}) - ({0} < 0)))"}),
    "reciprocal.default": _op("(({T})1 / {0})"),
    "rsqrt.default": _op("(({T})1 / sqrt{f}({0}))"),
    "sigmoid.default": _exp("(({T})1 / (({T})1 + EXP(-{0})))", "sigmoid"),
    "exp.default": _exp("EXP({0})"), "tanh.default": _tanh,
    "relu.default": _op("(({0} < 0) ? ({T})0 : {0})"),
    "leaky_relu.default": lambda w, s, x, slope=0.01: pointwise(
        w, s, "(({0} > 0) ? {0} : {0} * {1})", [x, slope]),
    "silu.default": _op("({0} / (({T})1 + exp{f}(-{0})))"),
    "mish.default": _op("({0} * tanh{f}(log1p{f}(exp{f}({0}))))"),
    "log_sigmoid.default": _op("((({0} < 0) ? {0} : ({T})0) - log1p{f}(exp{f}(-fabs{f}({0}))))"),
    "elu.default": _elu,
    "selu.default": lambda w, s, x: _elu(w, s, x, 1.6732632423543772848170429916717,
                                         1.0507009873554804934193349852946),
    "celu.default": lambda w, s, x, alpha=1.0: _elu(w, s, x, alpha, 1.0, 1.0 / alpha),
    "softplus.default": _softplus, "hardtanh.default": _hardtanh,
    "relu6.default": lambda w, s, x: _clamp(w, s, x, 0.0, 6.0),
    "hardsigmoid.default": _hard("(R / ({T})6)"),
    "hardswish.default": _hard("({0} * R / ({T})6)"),
    "gelu.default": _gelu,
    **{f"{n}.default": _unary_float(n) for n in (
        "sqrt", "exp2", "expm1", "log", "log1p", "log2", "log10", "sin", "cos", "tan",
        "asin", "acos", "atan", "sinh", "cosh", "asinh", "acosh", "atanh", "erf",
        "erfc")},
    **{f"{n}.default": _op({"float": n + "{f}({0})", "int": "{0}"})
       for n in ("floor", "ceil", "trunc")},
    "round.default": _op({"float": "rint{f}({0})", "int": "{0}"}),
    "copysign.Tensor": _op("copysign{f}({0}, {1})", 2),
    "copysign.Scalar": _op("copysign{f}({0}, {1})", 2),
    "atan2.default": _op("atan2{f}({0}, {1})", 2),
    "pow.Tensor_Tensor": _op("pow{f}({0}, {1})", 2),
    "pow.Tensor_Scalar": _pow_scalar,
    "maximum.default": _helper("max"), "minimum.default": _helper("min"),
    "fmax.default": _helper("fmax"), "fmin.default": _helper("fmin"),
    "remainder.Tensor": _helper("remainder"), "remainder.Scalar": _helper("remainder"),
    "fmod.Tensor": _op({"float": "fmod{f}({0}, {1})", "int": "({0} % {1})"}, 2),
    "fmod.Scalar": _op({"float": "fmod{f}({0}, {1})", "int": "({0} % {1})"}, 2),
    "clamp.default": _clamp, "clamp.Tensor": _clamp,
    "clamp_min.default": lambda w, s, x, v: _clamp(w, s, x, min=v),
    "clamp_min.Tensor": lambda w, s, x, v: _clamp(w, s, x, min=v),
    "clamp_max.default": lambda w, s, x, v: _clamp(w, s, x, max=v),
    "clamp_max.Tensor": lambda w, s, x, v: _clamp(w, s, x, max=v),
    **{f"{k}.{v}": _op(f"({{0}} {c} {{1}})", 2, promote=True)
       for k, c in _COMPARE.items() for v in ("Tensor", "Scalar")},
    **{f"{k}.default": _op(f, 2, promote=True) for k, f in _LOGICAL.items()},
    "logical_not.default": _op("(!{0})", 1, promote=True),
    **{f"{p}.Tensor": _op(f"({{0}} {c} {{1}})", 2)
       for k, c in _BITWISE.items() for p in (f"bitwise_{k}", f"__{k}__")},
    "bitwise_not.default": _op({"bool": "(!{0})", "int": "(~{0})"}),
    "where.self": _where, "where.ScalarOther": _where, "where.ScalarSelf": _where,
    "where.Scalar": _where, "masked_fill.Scalar": _masked_fill,
    "masked_fill.Tensor": _masked_fill,
    "isnan.default": _test("isnan", "0"),
    "isinf.default": _test("isinf", "0"),
    "isfinite.default": _test("isfinite", "1"),
    "to.dtype": _to, "_to_copy.default": _to, "to.dtype_layout": _to,
}


