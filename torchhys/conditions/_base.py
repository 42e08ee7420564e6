"""What the conditioned operators share (:class:`ConditionedOperator`): the input layout
``[x, conditions]``, the conditions' calibrated range and its scaling to [-1, 1], and the
log-linear schedule ``theta . b(c~)`` in the Legendre basis without its constant."""

# no `from __future__ import annotations`: TorchScript reads the steps' class annotations
import torch
from torch import Tensor

from torchhys._checks import (
    as_batched_sequence,
    check_finite,
    check_floating,
    check_int,
    check_tensor,
    concrete,
)
from torchhys.conditions.basis import legendre_basis, total_degree, varying_range
from torchhys.operator import HysteresisOperator


def schedule(c: Tensor, theta: Tensor, scale: Tensor, shift: Tensor,
             exponents: list[list[int]], degree: int) -> Tensor:
    """``theta . b(c * scale + shift)``: (..., P) of conditions c (..., n), ``theta`` (P,
    len(exponents)), ``b`` the Legendre basis of ``exponents`` (without the constant), and
    ``scale``, ``shift`` (n,) mapping the calibrated range to [-1, 1]."""
    b = legendre_basis(c * scale + shift, exponents, degree)  # (..., K)
    return (b.unsqueeze(-2) * theta).sum(-1)


class ConditionedOperator(HysteresisOperator):
    """Base of the operators whose parameters move with measured conditions.

    A subclass calls :meth:`_init_conditions` at the end of ``__init__`` (after its own
    parameters and buffers: the state dict keeps their order). Its input is x (batch, time,
    1 + n_conditions) (column 0 the driving input), or x (batch, time) without conditions;
    :meth:`calibrate` records ``cond_min``, ``cond_max`` (NaN until then), which the
    compensator's condition clamp also reads. ``_scales`` names what the conditions scale
    (for the messages).
    """

    _scales = "the parameters"

    def _init_conditions(self, n_conditions: int, degree: int, dtype: torch.dtype) -> None:
        self.n_conditions = check_int(n_conditions, "n_conditions", minimum=0)
        self.degree = check_int(degree, "degree", minimum=1)
        self.exponents = total_degree(self.n_conditions, self.degree)[1:]  # no constant
        for name in ("cond_min", "cond_max"):
            self.register_buffer(name, torch.full((self.n_conditions,), float("nan"),
                                                  dtype=dtype))

    @property
    def n_inputs(self) -> int:
        """Input columns per sample: the driving input and the conditions."""
        return 1 + self.n_conditions

    @property
    def n_basis(self) -> int:
        """The basis' size K without its constant: ``C(n + degree, degree) - 1``."""
        return len(self.exponents)

    def _inputs(self, x: Tensor) -> tuple[Tensor, bool]:
        """x as (batch, time, 1 + n) (n >= 1) or (batch, time), checked; whether a batch
        dimension was added."""
        n = self.n_conditions
        if n == 0:
            return as_batched_sequence(x, "x")
        check_tensor(x, "x")
        check_floating(x, "x")
        if x.dim() not in (2, 3) or x.shape[-1] != 1 + n or x.shape[-2] == 0 or (
                x.dim() == 3 and x.shape[0] == 0):
            raise ValueError(f"x must have shape (time, {1 + n}) or (batch, time, {1 + n}) (the "
                             f"input, then {n} condition column(s)) with time >= 1, got shape "
                             f"{tuple(x.shape)}")
        check_finite(x, "x")
        return (x.unsqueeze(0), True) if x.dim() == 2 else (x, False)

    def _scaling(self, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """``(scale, shift)`` (n,) in ``dtype``: ``c * scale + shift`` maps [cond_min,
        cond_max] to [-1, 1] (computed in float64)."""
        lo, hi = self.cond_min.double(), self.cond_max.double()
        if self.n_conditions and concrete(lo, hi) and not bool(
                (torch.isfinite(lo) & torch.isfinite(hi)).all()):
            raise ValueError(f"{type(self).__name__} is not calibrated: call calibrate(x) with x "
                             f"(batch, time, {1 + self.n_conditions}) first (it records the "
                             "conditions' range cond_min, cond_max)")
        scale = 2.0 / (hi - lo)
        return scale.to(dtype), (-1.0 - lo * scale).to(dtype)

    @torch.no_grad()
    def calibrate(self, x: Tensor) -> None:
        """Record the conditions' range (``cond_min``, ``cond_max``) from the condition
        columns of x (batch, time, 1 + n_conditions); nothing without conditions.

        Raises:
            ValueError: x of another shape or not finite, a condition constant over x.
        """
        if self.n_conditions == 0:
            return
        xb, _ = self._inputs(x)
        c = xb[..., 1:].reshape(-1, self.n_conditions)
        lo, hi = varying_range(c, "x: condition column {i} is constant ({value}) over the "
                                  "calibration samples: it cannot scale " + self._scales)
        self.cond_min.copy_(lo)
        self.cond_max.copy_(hi)

    def check_loaded(self, values: dict, prefix: str) -> None:
        """A recorded range (finite ``cond_min`` or ``cond_max``) must have ``cond_max >
        cond_min``."""
        lo, hi = values.get("cond_min"), values.get("cond_max")
        if isinstance(lo, Tensor) and isinstance(hi, Tensor) and lo.shape == hi.shape:
            known = torch.isfinite(lo) | torch.isfinite(hi)
            if bool((known & ~(hi > lo)).any()):
                raise ValueError(f"{prefix}cond_max must be above {prefix}cond_min (a recorded "
                                 "range) or both NaN (not calibrated)")
