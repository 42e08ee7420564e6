"""Compile a small C library once, cache it by the hash of its source, and load it.

Shared by the compiled kernels (:mod:`torchhys.functional._kernel` for the play operator,
:mod:`torchhys.functional._filter_kernel` for linear filters): the system C compiler builds
the source with IEEE-exact flags into ``$TORCHHYS_CACHE/kernels`` (default
``~/.cache/torchhys``), and every caller falls back to its pure-torch path, with the reason,
when the kernel is disabled (``TORCHHYS_DISABLE_KERNEL=1``), no compiler is found or the build
fails. A missing compiler or a failed build is said once per process, in one line (a
:class:`RuntimeWarning`, :func:`warn_fallback`): the slower path runs; the environment variable
chooses it silently.

Each kernel is also a torch custom op (``torch.ops.torchhys.*``, defined beside its kernel)
whose implementation makes the same choice, at run time: tracing (``torch.compile``,
``torch.export``), functorch transforms and fake or meta tensors see one opaque op with a
fake implementation, never the file-system checks, the build or :mod:`ctypes`. Plain eager
calls skip the dispatcher and call the implementation directly (:func:`dispatched`).
"""

from __future__ import annotations

import ctypes
import hashlib
import inspect
import os
import shutil
import subprocess
import tempfile
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TypeVar

import torch
from torch import Tensor

_F = TypeVar("_F", bound=type)

FLAGS = ["-O2", "-shared", "-fPIC", "-fno-fast-math", "-ffp-contract=off"]
"""Compiler flags: no fast math, no fused multiply-add contraction (results bit-equal to the
step-by-step tensor arithmetic)."""
SUFFIX = {torch.float32: "f32", torch.float64: "f64"}
"""The function-name suffix of each dtype the kernels are built for."""


def _cache_dir() -> Path:
    root = os.environ.get("TORCHHYS_CACHE") or Path.home() / ".cache" / "torchhys"
    return Path(root) / "kernels"


def _compile(compiler: str, name: str, source: str, lib_path: Path) -> None:
    lib_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        src, out = Path(tmp) / f"{name}.c", Path(tmp) / f"{name}.so"
        src.write_text(source)
        subprocess.run([compiler, *FLAGS, str(src), "-o", str(out)],
                       check=True, capture_output=True, timeout=120)
        staged = lib_path.with_suffix(f".{os.getpid()}.tmp")
        shutil.copyfile(out, staged)
        os.replace(staged, lib_path)  # atomic: concurrent builders never see a partial file


def servable(*tensors: Tensor) -> bool:
    """Whether a kernel is built for these tensors: all on the CPU, in a dtype of
    :data:`SUFFIX` (float32 or float64), plain tensors with concrete values (not traced,
    batched by vmap, meta, fake or another subclass: what :func:`dispatched` sends to the
    custom ops; a cheaper test than :func:`torchhys._checks.concrete`, which it implies).
    Whether it is switched on and built is the caller's check."""
    return cpu_float(*tensors) and not dispatched(*tensors)


def cpu_float(*tensors: Tensor) -> bool:
    """Whether the tensors are all on the CPU in a dtype of :data:`SUFFIX`: :func:`servable`
    for tensors known to be plain (an op's implementation, or after :func:`dispatched`)."""
    return all(t.device.type == "cpu" and t.dtype in SUFFIX for t in tensors)


def build(name: str, source: str, *, what: str, fallback: str,
          argtypes: Mapping[str, Sequence[type]] | None = None
          ) -> tuple[ctypes.CDLL | None, str | None]:
    """The library built from ``source`` (cached as ``{name}_{hash}.so``), or None and why.

    Args:
        name: file name stem.
        source: C source.
        what: what the kernel is, for the warning (``"play-operator kernel"``).
        fallback: what is used instead, for the warning (``"the pure-torch scan"``).
        argtypes: the :mod:`ctypes` argument types of each exported function, by its name
            without the dtype suffix (``{"play_forward": [c_void_p, ..., c_long]}``); set on
            the function of every suffix of :data:`SUFFIX`.
    """
    if os.environ.get("TORCHHYS_DISABLE_KERNEL", "") not in ("", "0"):
        return None, "disabled by the environment variable TORCHHYS_DISABLE_KERNEL"
    cc = os.environ.get("CC", "cc")
    compiler = shutil.which(cc) or shutil.which("gcc")
    if compiler is None:
        reason = f"no C compiler found (neither {cc!r} nor 'gcc' is on the PATH)"
        warn_fallback("compiler", f"{reason}: the compiled {what} and the other kernels are "
                      "off, the slower pure-torch paths run (set CC to a C compiler, or "
                      "TORCHHYS_DISABLE_KERNEL=1 to choose them without this warning)")
        return None, reason
    digest = hashlib.sha256((source + " ".join(FLAGS)).encode()).hexdigest()[:16]
    lib_path = _cache_dir() / f"{name}_{digest}.so"
    try:
        if not lib_path.exists():
            _compile(compiler, name, source, lib_path)
        lib = ctypes.CDLL(str(lib_path))
    except (OSError, subprocess.SubprocessError) as err:
        warn_fallback(what, f"could not build the compiled {what} ({err}); {fallback} runs "
                      "instead (slower; TORCHHYS_DISABLE_KERNEL=1 chooses it without this "
                      "warning)")
        return None, f"the kernel could not be built with {compiler} ({err})"
    for stem, types in (argtypes or {}).items():
        for suffix in SUFFIX.values():
            getattr(lib, f"{stem}_{suffix}").argtypes = list(types)
    return lib, None


_warned: set[str] = set()
"""The keys :func:`warn_fallback` has warned about in this process."""


def warn_fallback(key: str, message: str) -> None:
    """Warn once per process and ``key`` (``"compiler"``: every kernel at once; a kernel's
    name: its failed build) that a slower path runs: one line, ``torchhys:0: RuntimeWarning:
    <message>``, without the source line a warning from a file would echo (filters match the
    module ``torchhys``). The message is made one line (a compiler's error may hold several)."""
    if key in _warned:
        return
    _warned.add(key)
    text = " ".join(message.split())
    warnings.warn_explicit(text, RuntimeWarning, filename="torchhys", lineno=0,
                           module="torchhys")


def dispatched(*tensors: Tensor) -> bool:
    """Whether a kernel call must go through its custom op (``torch.ops.torchhys.*``) rather
    than call the implementation directly: while Dynamo or export traces, under a functorch
    transform (``vmap``, ``grad``), and for fake, meta or subclassed tensors. Plain eager
    tensors take the direct call (no dispatcher overhead)."""
    if torch.compiler.is_compiling():
        return True
    wrapped = torch._C._functorch.is_functorch_wrapped_tensor
    return any(type(t) not in (Tensor, torch.nn.Parameter) or t.is_meta or wrapped(t)
               for t in tensors)


def loop_vmap(op: Callable[..., object]) -> None:
    """Register a ``vmap`` rule on a custom op that calls it once per batch entry and stacks
    the results along dim 0 (its tensor arguments are batched any way: inputs, parameters or
    both)."""
    def rule(info, in_dims, *args):  # noqa: ANN001, ANN002, ANN202
        outs = [op(*(a if d is None else a.select(d, v)
                     for a, d in zip(args, in_dims, strict=True)))
                for v in range(info.batch_size)]
        if isinstance(outs[0], tuple):
            return tuple(torch.stack(o) for o in zip(*outs, strict=True)), (0,) * len(outs[0])
        return torch.stack(outs), 0
    op.register_vmap(rule)  # type: ignore[attr-defined]


def signature_once(cls: _F) -> _F:
    """Class decorator for an ``autograd.Function`` in ``setup_context`` form (the form
    ``torch.func`` needs): stores ``forward``'s signature once (torch binds each call's
    arguments with ``inspect.signature(forward)``, which computes it afresh every call) and
    builds ``cls.eager``, its twin in the ``forward(ctx, ...)`` form: the same forward,
    setup, backward and jvp, without torch's per-call binding and functorch bookkeeping of
    the ``setup_context`` form. :func:`call_function` chooses between them."""
    cls.forward.__signature__ = inspect.signature(cls.forward)  # type: ignore[attr-defined]

    def forward(ctx, *args):  # noqa: ANN001, ANN002, ANN202
        output = cls.forward(*args)  # type: ignore[attr-defined]
        cls.setup_context(ctx, args, output)  # type: ignore[attr-defined]
        return output

    body = {"forward": staticmethod(forward), "backward": staticmethod(cls.backward),  # type: ignore[attr-defined]
            "__doc__": f"{cls.__name__} in the forward(ctx, ...) form, for plain eager calls."}
    if "jvp" in cls.__dict__:
        body["jvp"] = staticmethod(cls.jvp)  # type: ignore[attr-defined]
    cls.eager = type(f"{cls.__name__}Eager", (torch.autograd.Function,), body)  # type: ignore[attr-defined]
    return cls


def call_function(cls: type, *args: object) -> object:
    """``cls.apply(*args)`` for a :func:`signature_once` function where ``torch.func``
    transforms or Dynamo see the call, else ``cls.eager.apply(*args)`` (the same results,
    without the ``setup_context`` form's per-call overhead)."""
    if torch.compiler.is_compiling() or torch._C._are_functorch_transforms_active():
        return cls.apply(*args)  # type: ignore[attr-defined]
    return cls.eager.apply(*args)  # type: ignore[attr-defined]
