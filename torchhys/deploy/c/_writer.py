"""The C99 primitives of :mod:`torchhys.deploy.c`: static-shape tensors as arrays, loops,
literals, constants and the small helper functions the op templates share.

Every tensor of the step has a static shape. A :class:`CTensor` is either a constant (its
value is known when the C is written: a parameter, a buffer, or a folded node) or a view of a
C array (``base``) read at ``offset`` with ``strides``: a view (``narrow``, ``select``,
``unsqueeze`` ...) costs no code, and a broadcast is a stride of 0. Arrays written by the step
are contiguous locals. Loops have constant bounds and are written so that the compiler
vectorizes them at ``-O2`` (GCC 12: no libm call, no mixed element widths, no comparison
that would need speculating inside a loop): a pointwise result with one pointwise reader of
as many elements is not stored but written into its reader's loop (``CTensor.element``), and
the exp of a double is a branch-free inline function within 1 ulp of libm's.
"""

from __future__ import annotations

import contextlib
import math
import re
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from torchhys.deploy.c._libm import LIBM_FREE

#: C type of each tensor dtype (a bool is a uint8_t holding 0 or 1)
CTYPES = {torch.float64: "double", torch.float32: "float", torch.int64: "int64_t",
          torch.int32: "int32_t", torch.bool: "uint8_t"}


def contiguous_strides(shape: Sequence[int]) -> tuple[int, ...]:
    """Row-major strides of ``shape``."""
    strides, step = [], 1
    for d in reversed(shape):
        strides.append(step)
        step *= max(int(d), 1)
    return tuple(reversed(strides))


@dataclass(frozen=True)
class CTensor:
    """A tensor of the generated step: a constant (``value``) or a view of the C array
    ``base``: element ``idx`` is ``base[offset + sum(idx[d] * strides[d])]``."""

    dtype: torch.dtype
    shape: tuple[int, ...]
    strides: tuple[int, ...] = ()
    base: str = ""
    offset: int = 0
    value: Tensor | None = None
    #: a deferred pointwise result: the C expression of its element at an index (one C
    #: index expression a dim), written into the one loop that reads it (fused)
    element: Callable[[list[str]], str] | None = field(default=None, compare=False)

    @property
    def numel(self) -> int:
        return math.prod(self.shape)

    def is_contiguous(self) -> bool:
        """Whether the elements are consecutive in the array from ``offset``, row-major
        (size-1 dims ignored)."""
        kept = [(n, s) for n, s in zip(self.shape, self.strides, strict=True) if n != 1]
        return all(s == c for (_, s), c in zip(kept, contiguous_strides([n for n, _ in kept]),
                                                strict=True))

    def view(self, shape: Sequence[int], strides: Sequence[int], offset: int) -> CTensor:
        return CTensor(self.dtype, tuple(shape), tuple(strides), self.base, offset)


def constant(value: Tensor) -> CTensor:
    value = value.detach().cpu().contiguous()
    return CTensor(value.dtype, tuple(value.shape), contiguous_strides(value.shape),
                   value=value)


def _index(offset: int, idx: Sequence[str], strides: Sequence[int]) -> str:
    """``offset + sum(idx * strides)`` as C, constants folded."""
    const, terms = offset, []
    for i, s in zip(idx, strides, strict=True):
        if s == 0 or i == "0":
            continue
        if i.isdigit():
            const += int(i) * s
            continue
        if not i.isidentifier():
            i = f"({i})"
        terms.append(i if s == 1 else f"{i} * {s}")
    if const or not terms:
        terms.append(str(const))
    return " + ".join(terms)


_FLOAT_HELPERS = {
    # torch.maximum / minimum: NaN propagates; otherwise std::max(a, b) = a < b ? b : a. The
    # comparisons quiet (isless, !=: no exception on NaN), so that GCC if-converts a loop of
    # them and vectorizes it (an ordered < under -ftrapping-math it would not speculate)
    "max": "return isless(a, b) ? b : ((b != b) ? b : a);",
    "min": "return isless(b, a) ? b : ((b != b) ? b : a);",
    # torch.clamp with tensor bounds: a NaN bound gives NaN, else min(max(a, lo), hi)
    "clamp": "T m = isless(a, lo) ? lo : a;\n    m = isless(hi, m) ? hi : m;\n"
             "    return (lo != lo) ? lo : ((hi != hi) ? hi : m);",
    # torch.fmax / fmin: a NaN operand is ignored (C99 fmax)
    "fmax": "return isless(a, b) ? b : ((a != a) ? b : a);",
    "fmin": "return isless(b, a) ? b : ((a != a) ? b : a);",
    # torch's floor division of floats (div_floor_floating)
    "floordiv": "T mod, div, fl;\n    if (b == 0) return a / b;\n    mod = FMOD(a, b);\n"
                "    div = (a - mod) / b;\n    if (mod != 0 && (b < 0) != (mod < 0)) div -= 1;\n"
                "    if (div == 0) return COPYSIGN((T)0, a / b);\n    fl = FLOOR(div);\n"
                "    return (div - fl > (T)0.5) ? fl + 1 : fl;",
    # torch.remainder of floats: the sign of the divisor
    "remainder": "T mod = FMOD(a, b);\n    if (mod != 0 && (b < 0) != (mod < 0)) mod += b;\n"
                 "    return mod;",
}
_INT_HELPERS = {
    "max": "return (a < b) ? b : a;",
    "min": "return (b < a) ? b : a;",
    "clamp": "T m = (a < lo) ? lo : a;\n    return (hi < m) ? hi : m;",
    "floordiv": "T q = a / b;\n    if (a % b != 0 && ((a < 0) != (b < 0))) q -= 1;\n    return q;",
    "remainder": "T m = a % b;\n    if (m != 0 && ((b < 0) != (m < 0))) m += b;\n    return m;",
}
_ARGS = {"clamp": "T a, T lo, T hi"}

# isfinite / isnan / isinf of a float told from its bits (the magnitude's bits against
# those of inf), not by arithmetic: -ffinite-math-only (in -ffast-math) folds x != x and
# x - x == 0 to constants
_BIT_TESTS = {"isfinite": "<", "isnan": ">", "isinf": "=="}
_BITS = {"double": ("uint64_t", "UINT64_C(0x7FFFFFFFFFFFFFFF)", "UINT64_C(0x7FF0000000000000)"),
         "float": ("uint32_t", "UINT32_C(0x7FFFFFFF)", "UINT32_C(0x7F800000)")}


class Writer:
    """Collects the C of one step function: locals, constants, helpers and statements.

    Args:
        prefix: the C prefix of every global name.
    """

    def __init__(self, prefix: str) -> None:
        self.prefix = prefix
        self.lines: list[str] = []
        self.locals: list[tuple[str, str, int]] = []  # (name, C type, elements)
        self.constants: list[str] = []  # definitions, in order of first use
        self.helpers: dict[str, str] = {}
        self._const_names: dict[int, str] = {}
        self._pinned: list[Tensor] = []  # the constants seen (their ids stay theirs)
        self._uniform: dict[int, bool] = {}
        # liveness of the locals, in node numbers (``node`` is set by the caller), for
        # sharing arrays between locals whose lifetimes do not overlap
        self.node = 0
        self._born: dict[str, int] = {}
        self._last: dict[str, float] = {}
        self.scalars = {"x"}  # the step's argument: a one-element tensor that is a C scalar
        # set by the caller for each node: its pointwise result may be deferred into its one
        # reader's loop (it has one user, a pointwise op of as many elements)
        self.defer = False
        # set by the caller for each node: its result is read by the step's outputs only (a
        # one-condition where of two whole arrays may then be a pointer to one of them)
        self.alias = False
        self.pointers: dict[str, tuple[str, str]] = {}  # pointer -> the arrays it may point to
        self._depth = 1
        self._loops = 0

    # --- types and values ---------------------------------------------------------------
    @staticmethod
    def ctype(dtype: torch.dtype) -> str:
        if dtype not in CTYPES:
            raise ValueError(f"dtype {dtype} has no C type here (supported: "
                             f"{', '.join(str(d) for d in CTYPES)})")
        return CTYPES[dtype]

    def literal(self, value: float | int | bool, dtype: torch.dtype) -> str:
        """``value`` as a C constant of ``dtype``: the shortest decimal that reads back as
        that value (``f`` suffix in float32), in parentheses when negative."""
        t = self.ctype(dtype)
        if dtype.is_floating_point:
            v = float(value)
            if not math.isfinite(v):
                text = "NAN" if math.isnan(v) else "INFINITY" if v > 0 else "-INFINITY"
                return f"(({t}){text})"
            text = repr(v) if dtype == torch.float64 else str(np.float32(v)) + "f"
            return text if math.copysign(1.0, v) > 0 else f"({text})"
        if dtype == torch.bool:
            return "1" if bool(value) else "0"
        if isinstance(value, float) and not value.is_integer():
            raise ValueError(f"{value!r} is not an integer of {dtype}")
        v = int(value)
        return f"INT64_C({v})" if dtype == torch.int64 else f"(({t}){v})"

    def local(self, dtype: torch.dtype, shape: Sequence[int]) -> CTensor:
        """A new contiguous local array (none is declared for a tensor without elements)."""
        shape = tuple(int(d) for d in shape)
        name = f"t{len(self.locals)}"
        self.locals.append((name, self.ctype(dtype), math.prod(shape)))
        self._born[name] = self._last[name] = self.node
        return CTensor(dtype, shape, contiguous_strides(shape), name)

    def array(self, t: CTensor) -> str:
        """The C array of ``t``; a constant is defined at its first use."""
        if t.value is None:
            if t.base in self._last:
                self._last[t.base] = max(self._last[t.base], self.node)
            return t.base
        key = id(t.value)
        if key not in self._const_names:
            name = f"{self.prefix}_k{len(self._const_names)}"
            self._const_names[key] = name
            self._pinned.append(t.value)
            values = [self.literal(v, t.dtype) for v in t.value.reshape(-1).tolist()]
            rows = [", ".join(values[i:i + 4]) for i in range(0, len(values), 4)]
            body = ",\n    ".join(rows)
            self.constants.append(
                f"static const {self.ctype(t.dtype)} {name}[{len(values)}] = {{\n    {body}\n}};")
        return self._const_names[key]

    def uniform(self, t: CTensor) -> bool:
        """Whether the constant ``t`` holds one value (bit for bit) in every element: it is
        read as a literal, not from an array."""
        key = id(t.value)
        if key not in self._uniform:
            v = t.value.reshape(-1)
            if v.is_floating_point():
                v = v.view({8: torch.int64, 4: torch.int32, 2: torch.int16}[v.element_size()])
            self._uniform[key] = bool(v.numel() > 0 and (v == v[0]).all())
            self._pinned.append(t.value)
        return self._uniform[key]

    def read(self, t: CTensor, idx: Sequence[str]) -> str:
        """The C expression of ``t``'s element at ``idx`` (one C index expression a dim)."""
        if t.element is not None:
            return f"({t.element(list(idx))})"
        if t.value is not None and (t.numel == 1 or self.uniform(t)):
            return self.literal(t.value.reshape(-1)[0].item(), t.dtype)
        if t.base in self.scalars:
            return t.base
        return f"{self.array(t)}[{_index(t.offset, idx, t.strides)}]"

    def read_broadcast(self, t: CTensor | float | int | bool, idx: Sequence[str],
                       dtype: torch.dtype) -> str:
        """``t`` (or a Python number) broadcast to an output indexed by ``idx``, as C of
        ``dtype`` (cast where the types differ)."""
        if not isinstance(t, CTensor):
            return self.literal(t, dtype)
        lead = len(idx) - len(t.shape)
        own = ["0" if n == 1 else idx[lead + d] for d, n in enumerate(t.shape)]
        return self.cast(self.read(t, own), t.dtype, dtype)

    def cast(self, expr: str, src: torch.dtype, dst: torch.dtype) -> str:
        if src == dst:
            return expr
        if dst == torch.bool:
            return f"(({expr}) != 0)"
        return f"(({self.ctype(dst)})({expr}))"

    def keep(self, base: str) -> None:
        """Keep the local ``base`` to the end of the step (it is read after the last node)."""
        self._last[base] = math.inf

    def shared_locals(self) -> tuple[list[str], list[str]]:
        """The locals' declarations and the statements, with one array shared by locals of
        the same C type whose lifetimes do not overlap (a greedy interval allocation)."""
        slots: list[list] = []  # [C type, elements, busy until]
        where: dict[str, str] = {}
        for name, ctype, n in sorted(self.locals, key=lambda r: self._born[r[0]]):
            born = self._born[name]
            free = [i for i, (c, _, until) in enumerate(slots) if c == ctype and until < born]
            fit = [i for i in free if slots[i][1] >= n]
            if fit or free:
                i = min(fit, key=lambda i: slots[i][1]) if fit else max(
                    free, key=lambda i: slots[i][1])
                slots[i][1], slots[i][2] = max(slots[i][1], n), self._last[name]
            else:
                i = len(slots)
                slots.append([ctype, n, self._last[name]])
            where[name] = f"a{i}"
        decls = [f"{c} a{i}[{max(n, 1)}];" for i, (c, n, _) in enumerate(slots)]
        pattern = re.compile(r"\bt(\d+)\b")
        lines = [pattern.sub(lambda m: where.get(m.group(0), m.group(0)), line)
                 for line in self.lines]
        return decls, lines

    # --- statements ---------------------------------------------------------------------
    def emit(self, line: str) -> None:
        self.lines.append("    " * self._depth + line)

    @contextlib.contextmanager
    def loop(self, shape: Sequence[int]) -> Iterator[list[str]]:
        """Nested loops over ``shape``: yields one C index expression a dim (``"0"`` for a
        dim of size 1, which gets no loop)."""
        idx, opened = [], 0
        for n in shape:
            if n == 1:
                idx.append("0")
                continue
            var = f"i{self._loops}"
            self._loops += 1
            self.emit(f"for (int {var} = 0; {var} < {n}; ++{var}) {{")
            self._depth += 1
            idx.append(var)
            opened += 1
        try:
            yield idx
        finally:
            for _ in range(opened):
                self._depth -= 1
                self.emit("}")
            self._loops -= opened

    def pointer(self, cond: str, a: CTensor, b: CTensor) -> CTensor:
        """``cond ? a : b`` for two whole contiguous arrays of one shape and dtype, without a
        copy: a const pointer to one of them, read as a tensor of their shape (both arrays
        kept to the end of the step)."""
        name = f"p{len(self.pointers)}"
        arrays = (self.array(a), self.array(b))
        for base in arrays:
            if base in self._last:
                self.keep(base)
        self.pointers[name] = arrays
        self.emit(f"const {self.ctype(a.dtype)} *{name} = {cond} ? {arrays[0]} : {arrays[1]};")
        return CTensor(a.dtype, a.shape, a.strides, name)

    def materialize(self, t: CTensor) -> CTensor:
        """A deferred pointwise result (``t.element``) written into a local; else ``t``."""
        if t.element is None:
            return t
        out = self.local(t.dtype, t.shape)
        self.assign(out, t.element)
        return out

    def assign(self, dst: CTensor, element: Callable[[list[str]], str]) -> None:
        """``dst[idx] = element(idx)`` for every index of ``dst`` (nothing when empty)."""
        if dst.numel == 0:
            return
        with self.loop(dst.shape) as idx:
            self.emit(f"{self.read(dst, idx)} = {element(idx)};")

    def helper(self, kind: str, dtype: torch.dtype) -> str:
        """The name of a shared helper function (``max``, ``min``, ``clamp``, ``fmax``,
        ``fmin``, ``floordiv``, ``remainder``; ``exp``, ``tanh`` (and ``sigmoid``, double
        only): vectorizable ones of a double or a float (:mod:`torchhys.deploy.c._libm`);
        ``isfinite``, ``isnan``, ``isinf``: tests of a float's bits) for ``dtype``, defined
        on first use."""
        t = self.ctype(dtype)
        if kind in _BIT_TESTS:
            if not dtype.is_floating_point:
                raise ValueError(f"no {kind} for {dtype}")
            name = f"{self.prefix}_{kind}_{t}"
            unsigned, magnitude, inf = _BITS[t]
            self.helpers.setdefault(name, (
                f"static int {name}({t} a)\n{{\n    {unsigned} b;\n    memcpy(&b, &a, sizeof b);"
                f"\n    return (b & {magnitude}) {_BIT_TESTS[kind]} {inf};\n}}"))
            return name
        if kind in LIBM_FREE["double"] and kind not in LIBM_FREE.get(t, {}):
            raise ValueError(f"no {kind} helper for {dtype}")
        name = f"{self.prefix}_{kind}_{t.split('_')[0]}"
        if kind in LIBM_FREE["double"] and name not in self.helpers:
            body = LIBM_FREE[t][kind]
            self.helpers[name] = f"static inline {t} {name}({t} x)\n{{\n    {body}\n}}"
        if name not in self.helpers:
            table = _FLOAT_HELPERS if dtype.is_floating_point else _INT_HELPERS
            if kind not in table:
                raise ValueError(f"no {kind} for {dtype}")
            suffix = "f" if dtype == torch.float32 else ""
            body = (table[kind].replace("T ", f"{t} ").replace("(T)", f"({t})")
                    .replace("FMOD", f"fmod{suffix}").replace("FLOOR", f"floor{suffix}")
                    .replace("COPYSIGN", f"copysign{suffix}"))
            args = _ARGS.get(kind, "T a, T b").replace("T ", f"{t} ")
            self.helpers[name] = f"static {t} {name}({args})\n{{\n    {body}\n}}"
        return name
