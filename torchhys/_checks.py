"""Input checks shared by the public entry points.

Every public function validates its arguments once, here, and raises a
``TypeError`` or ``ValueError`` that names the argument and what was received.

Checks of a tensor's type, dtype and shape run everywhere. Checks of its values (finite,
non-negative, ...) read the values on the host, so they run only where the values are there
to read (:func:`concrete`): in eager mode on real tensors, not while ``torch.compile``
or ``torch.export`` traces, under ``torch.func.vmap``, or on meta and fake tensors
(``docs/design.md``, "Which checks run where").
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Iterable
from typing import TypeVar

import numpy as np
import torch
from torch import Tensor
from torch._C._functorch import TransformType
from torch._functorch.pyfunctorch import retrieve_all_functorch_interpreters
from torch._subclasses.fake_tensor import is_fake

_T = TypeVar("_T")


def concrete(*tensors: object) -> bool:
    """Whether ``tensors`` hold concrete values that can be read on the host: False while
    ``torch.compile`` or ``torch.export`` traces, under ``torch.func.vmap``, and for a meta
    or fake tensor among them (the values are symbolic or absent there); True otherwise
    (eager mode, ``torch.func.grad`` and ``jvp`` included). Arguments that are not tensors
    are ignored. The value checks (finite, non-negative, ...) run only where it is True, and
    so do the compiled C kernels (they read the tensors' memory)."""
    if torch.compiler.is_compiling():
        return False
    if torch._C._functorch.peek_interpreter_stack() is not None and any(
            i.key() == TransformType.Vmap for i in retrieve_all_functorch_interpreters()):
        return False
    for t in tensors:  # a plain tensor is not fake: is_fake only for subclasses (a
        # parameter may hold a fake tensor)
        if isinstance(t, Tensor) and (t.is_meta or (type(t) is not Tensor and is_fake(t))):
            return False
    return True


def check_tensor(value: object, name: str) -> Tensor:
    """Raise ``TypeError`` unless ``value`` is a tensor."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    return value


def check_floating(value: Tensor, name: str) -> Tensor:
    """Raise ``TypeError`` unless ``value`` has a floating-point dtype."""
    if not value.is_floating_point():
        raise TypeError(
            f"{name} must have a floating-point dtype (e.g. torch.float32), got {value.dtype}; "
            f"convert it with {name}.float()"
        )
    return value


def check_dtype_of(value: Tensor, name: str, dtype: torch.dtype, owner: str) -> Tensor:
    """``value`` in the floating dtype ``dtype`` of ``owner``'s parameters: a narrower float
    (float32 into a float64 network) is widened, as torch's type promotion does; a wider one
    (float64 into a float32 network) raises ``TypeError`` naming both and the remedies (as
    ``nn.Linear`` refuses it, which would lose the input's precision). Other dtypes pass."""
    if value.dtype == dtype or not (value.is_floating_point() and dtype.is_floating_point):
        return value
    if torch.finfo(value.dtype).bits < torch.finfo(dtype).bits:
        return value.to(dtype)
    got, want = (str(d).replace("torch.", "") for d in (value.dtype, dtype))
    var = owner.split()[-1]
    raise TypeError(f"{name} is {got} but the {owner} is {want}: convert the input "
                    f"({name}.to(torch.{want})) or the {owner} ({var}.to(torch.{got}))")


def check_finite(value: Tensor, name: str) -> Tensor:
    """Raise ``ValueError`` if ``value`` holds a NaN or an infinity (where values are
    checked: :func:`concrete`)."""
    if value.numel() > 0 and concrete(value) and not bool(torch.isfinite(value).all()):
        bad = (~torch.isfinite(value)).nonzero()[0].tolist()
        raise ValueError(
            f"{name} must be finite, but it holds NaN or inf (first at index {tuple(bad)})"
        )
    return value


def check_int(value: object, name: str, *, minimum: int | None = None) -> int:
    """Raise ``ValueError`` unless ``value`` is an int (a bool is not), ``>= minimum`` if given.

    The message names the argument and the bound: ``"max_depth must be an int >= 3, got 2"``.
    """
    if (isinstance(value, bool) or not isinstance(value, int)
            or (minimum is not None and value < minimum)):
        bound = "" if minimum is None else f" >= {minimum}"
        raise ValueError(f"{name} must be an int{bound}, got {value!r}")
    return value


def check_warmup(warmup: object, T: int) -> int:
    """Raise ``ValueError`` unless ``warmup`` (leading samples left out of a fit of ``T``
    samples; their states still run) is an int in ``[0, T)``; return it."""
    check_int(warmup, "warmup", minimum=0)
    if warmup >= T:
        raise ValueError(f"warmup must leave samples to fit: warmup={warmup} of {T} samples")
    return warmup


def fitted_samples(mask: object, shape: tuple[int, int], warmup: int) -> Tensor:
    """The samples a fit uses, (rows, time) bool: those of ``mask`` (None: every sample)
    from sample ``warmup`` of each row on.

    ``mask`` is a bool tensor of the data's shape ``(rows, time)``, or ``(time,)`` for one
    row: the samples to fit (False: left out of the fit, e.g. a held-out block of a
    cross-validation or the padding of a shorter recording; the states still run through
    them). ``warmup`` must already be checked (:func:`check_warmup`).

    Raises:
        TypeError: ``mask`` not a bool tensor.
        ValueError: ``mask`` of another shape, or no sample left to fit.
    """
    rows, T = shape
    if mask is None:
        out = torch.zeros(rows, T, dtype=torch.bool)
        out[:, warmup:] = True
        return out
    check_tensor(mask, "mask")
    if mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor (True: fit the sample), got {mask.dtype}")
    m = mask.unsqueeze(0) if mask.dim() == 1 else mask
    if tuple(m.shape) != (rows, T):
        raise ValueError(f"mask must have the data's shape {(rows, T)} (rows, time), got "
                         f"{tuple(mask.shape)}")
    out = m.detach().cpu().clone()
    out[:, :warmup] = False
    if not bool(out.any()):
        raise ValueError(f"mask (with warmup={warmup}) leaves no sample to fit")
    return out


def check_bool(value: object, name: str) -> bool:
    """Raise ``TypeError`` unless ``value`` is a bool, a NumPy bool or a one-element bool
    tensor (a flag given as a string or a number would otherwise act by its truth value);
    return it as a bool."""
    if isinstance(value, Tensor) and value.dtype == torch.bool and value.numel() == 1:
        return bool(value)
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be True or False, got {type(value).__name__} {value!r}")
    return bool(value)


def check_real(value: object, name: str, *, allow_inf: bool = False) -> float:
    """A finite real number (a Python or NumPy number, not a bool, or a one-element tensor;
    with ``allow_inf`` also +-inf) as a float; ``ValueError`` otherwise (NaN never passes)."""
    if isinstance(value, Tensor) and value.numel() == 1 and not value.is_complex():
        value = value.item()
    ok = not isinstance(value, bool) and isinstance(value, numbers.Real) and (
        not math.isnan(value) if allow_inf else math.isfinite(value))
    if not ok:
        want = "a real number (or +-inf)" if allow_inf else "a finite real number"
        raise ValueError(f"{name} must be {want}, got {value!r}")
    return float(value)


def check_nonnegative(value: object, name: str, *, alternatives: str = "") -> float:
    """Raise ``ValueError`` unless ``value`` is a finite int or float ``>= 0`` (a bool is not),
    e.g. a penalty weight; return it as a float. ``alternatives`` names other accepted values
    in the message (e.g. ``"'auto' or "``)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            math.isfinite(value) and value >= 0):
        raise ValueError(f"{name} must be {alternatives}a finite number >= 0, got {value!r}")
    return float(value)


def check_positive(value: object, name: str) -> float:
    """Raise ``ValueError`` unless ``value`` is a finite int or float ``> 0`` (a bool is not);
    return it as a float."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


def check_choice(value: _T, name: str, choices: Iterable[object]) -> _T:
    """Raise ``ValueError`` unless ``value`` is one of ``choices``; the message lists them."""
    valid = list(choices)
    try:
        found = value in valid
    except (TypeError, ValueError, RuntimeError):  # an array compares element by element
        found = False
    if not found:
        raise ValueError(f"{name} must be one of {valid}, got {value!r}")
    return value


def check_same_shape(a: Tensor, b: Tensor, name_a: str, name_b: str) -> None:
    """Raise ``ValueError`` unless ``a`` has the shape of ``b``; the message gives both."""
    if a.shape != b.shape:
        raise ValueError(
            f"{name_a} must have the shape of {name_b} {tuple(b.shape)}, "
            f"got shape {tuple(a.shape)}"
        )


def check_widths(widths: Tensor, name: str = "widths") -> Tensor:
    """Validate dead-band widths: a finite, non-negative floating tensor of shape (N,) (the
    values where they are checked: :func:`concrete`)."""
    check_tensor(widths, name)
    check_floating(widths, name)
    if widths.dim() != 1:
        raise ValueError(f"{name} must have shape (N,), got shape {tuple(widths.shape)}")
    if widths.numel() == 0:
        raise ValueError(f"{name} must hold at least one width, got an empty tensor")
    check_finite(widths, name)
    if concrete(widths) and bool((widths < 0).any()):
        raise ValueError(
            f"{name} must be non-negative, got minimum {widths.min().item():.6g}"
        )
    return widths


def check_nonnegative_weights(w: Tensor, name: str, what: str) -> None:
    """Raise ``ValueError`` naming ``name`` unless the weights ``w`` of a constrained model
    (any shape; empty passes) are finite and non-negative; ``what`` completes "must be
    finite and ..." (``">= 0 (a nonnegative Prandtl-Ishlinskii model)"``); where values are
    checked (:func:`concrete`)."""
    if w.numel() and concrete(w) and not bool((w.isfinite() & (w >= 0)).all()):
        raise ValueError(f"{name} must be finite and {what}, got minimum "
                         f"{w.min().item():.6g}; call project_() before saving")


def sequence_batch(x: object) -> int | None:
    """The batch size of a sequence (time,) -> 1 or (batch, time) -> batch, read from its
    shape only (no pass over its values); None for anything else, which
    :func:`as_batched_sequence` names where the sequence is used."""
    if isinstance(x, Tensor) and x.dim() in (1, 2):
        return x.shape[0] if x.dim() == 2 else 1
    return None


def as_batched_sequence(x: Tensor, name: str = "x") -> tuple[Tensor, bool]:
    """Check a sequence of shape (T,) or (B, T) and return it as (B, T).

    Returns:
        The tensor as (B, T) and whether a batch dimension was added.
    """
    check_tensor(x, name)
    check_floating(x, name)
    if x.dim() not in (1, 2):
        raise ValueError(
            f"{name} must have shape (time,) or (batch, time), got shape {tuple(x.shape)}"
        )
    if x.shape[-1] == 0:
        raise ValueError(f"{name} must hold at least one sample, got shape {tuple(x.shape)}")
    if x.dim() == 2 and x.shape[0] == 0:
        raise ValueError(f"{name} must hold at least one row, got shape {tuple(x.shape)}")
    check_finite(x, name)
    if x.dim() == 1:
        return x.unsqueeze(0), True
    return x, False


def check_penalty(value: object, name: str) -> float:
    """A finite real number >= 0 (a Python or NumPy number, or a one-element tensor)."""
    if isinstance(value, Tensor) and value.numel() == 1:
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value}")
    if v < 0:
        raise ValueError(f"{name} must be >= 0, got {v}")
    return v


def check_state(state: object, batch: int, size: int, like: Tensor) -> Tensor:
    """A carried state, (size,) or (batch, size), as (batch, size) in ``like``'s dtype."""
    check_tensor(state, "state")
    check_floating(state, "state")
    if state.shape not in (torch.Size([size]), torch.Size([batch, size])):
        raise ValueError(f"state must have shape ({size},) or ({batch}, {size}) for batch "
                         f"{batch}, got shape {tuple(state.shape)}")
    check_finite(state, "state")
    return state.to(dtype=like.dtype, device=like.device).expand(batch, size)
