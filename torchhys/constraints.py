"""Constraints on the values an operator loads: declared once per class
(:attr:`torchhys.operator.HysteresisOperator.constraints`), checked by the base class before
``load_state_dict`` copies anything.

Each kind is a name with what it asks of every element of the tensor:

========================  ===============================================================
``"finite"``              finite
``"nonnegative"``         finite and ``>= 0``
``"positive"``            finite and ``> 0``
``"positive_integer"``    an integer ``>= 1`` (a count stored in a tensor)
``"relay"``               ``+1`` or ``-1``
``"not_nan"``             not NaN (``+-inf`` allowed: a bound that may be open)
``"nonnegative_or_nan"``  finite and ``>= 0``, or NaN (a setting not calibrated yet)
========================  ===============================================================
"""

from collections.abc import Callable

import torch
from torch import Tensor

__all__ = ["CONSTRAINTS", "check_constraint"]

CONSTRAINTS: dict[str, tuple[str, Callable[[Tensor], Tensor]]] = {
    "finite": ("finite", torch.isfinite),
    "nonnegative": ("finite and >= 0", lambda t: t.isfinite() & (t >= 0)),
    "positive": ("finite and > 0", lambda t: t.isfinite() & (t > 0)),
    "positive_integer": ("an integer >= 1",
                         lambda t: t.isfinite() & (t >= 1) & (t == torch.round(t))),
    "relay": ("+1 or -1 (relay values)", lambda t: (t == 1) | (t == -1)),
    "not_nan": ("a number or +-inf (not NaN)", lambda t: ~t.isnan()),
    "nonnegative_or_nan": ("finite and >= 0, or NaN (not calibrated)",
                           lambda t: t.isnan() | (t.isfinite() & (t >= 0))),
}
"""Constraint kinds: name -> (what it asks, elementwise test)."""


def check_constraint(value: Tensor, kind: str, name: str) -> None:
    """Raise ``ValueError`` naming ``name`` unless every element of ``value`` meets ``kind``
    (a key of :data:`CONSTRAINTS`); empty tensors pass.

    Raises:
        KeyError: an unknown kind (a declaration error in the operator class).
        ValueError: a value that breaks the constraint.
    """
    if kind not in CONSTRAINTS:
        raise KeyError(f"unknown constraint {kind!r} for {name}; kinds: {sorted(CONSTRAINTS)}")
    what, test = CONSTRAINTS[kind]
    t = value.detach()
    if not t.is_floating_point():
        t = t.to(torch.float64)
    if t.numel() and not bool(test(t).all()):
        bad = t[~test(t)].flatten()[:3].tolist()
        raise ValueError(f"{name} must be {what}, got {bad!r:.80} among its values")
