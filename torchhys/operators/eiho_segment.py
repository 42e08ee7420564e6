"""The paper's per-segment EIHO: coefficients from the recorded targets, not causal.

The paper identifies one ``a_i`` per monotone segment of the training record from the
target's next extremum (Eq. (19)): ``a_i = |dy| / |dx|^(1/2)`` (``"sqrt"``, consistent with
Eq. (2)) or ``|dy| / dx^2`` (``"paper"``, Eq. (19) as printed). A segment's coefficient is
known only once its end is, so this operator needs the whole target: it trains and replays
recorded data (``forward(x, target=...)``), and has no per-sample step (``causal = False``:
networks pass it the target; the streaming compensator and the exporters refuse it).
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

from torchhys._checks import as_batched_sequence, check_choice
from torchhys.functional._branch import BranchState
from torchhys.functional.eiho import NonCausalWarning, eiho, segment_coefficients
from torchhys.operators.eiho import _TurningPointOperator, check_eps
from torchhys.registry import register_operator
from torchhys.step import OperatorStep
from torchhys.testing import Example

__all__ = ["SegmentEIHO"]

A_FORMULAS = ("sqrt", "paper")


class SegmentEIHO(_TurningPointOperator):
    """The EIHO of Eq. (2) with the paper's per-segment coefficients (module docstring).

    Args:
        rule: ``"recent"`` or ``"dominant"``.
        a_formula: ``"sqrt"`` or ``"paper"`` (module docstring).
        threshold: reversal threshold of the turning-point detector, or ``"auto"``.
        max_depth: stack size of the ``"dominant"`` rule.
        eps: linear zone of the square root (see :func:`torchhys.functional.eiho`).
        output: ``"level"`` or ``"branch"`` (as for :class:`~torchhys.EIHO`).

    Shapes:
        ``forward(x, target=y)``: x, y (time,) or (batch, time) -> f of x's shape, and a
        :class:`~torchhys.functional.BranchState`.
    """

    causal = False

    def __init__(self, *, rule: str = "recent", a_formula: str = "sqrt",
                 threshold: float | str = 0.0, max_depth: int = 32, eps: float = 1e-8,
                 output: str = "level") -> None:
        super().__init__(threshold, rule, max_depth, output)
        self.a_formula = check_choice(a_formula, "a_formula", A_FORMULAS)
        self.eps = check_eps(eps)
        warnings.warn("SegmentEIHO uses the target's next extremum: not causal, for "
                      "replaying recorded data only", NonCausalWarning, stacklevel=2)

    def segment_coefficients(self, x: Tensor, target: Tensor) -> Tensor:
        """Per-segment ``a_i`` of a whole record (x, target) with this operator's settings."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NonCausalWarning)
            return segment_coefficients(
                x, target, threshold=self._threshold(), formula=self.a_formula
            )

    def forward(
        self, x: Tensor, state: BranchState | None = None, *,
        target: Tensor | None = None, segment_a: Tensor | None = None,
    ) -> tuple[Tensor, BranchState]:
        """Apply the operator to ``x`` (time,) or (batch, time), continuing from ``state``,
        with the coefficients of ``target`` (the whole record) or precomputed ``segment_a``
        (from :meth:`segment_coefficients`, for chunked replay)."""
        as_batched_sequence(x, "x")
        if segment_a is None:
            if target is None:
                raise ValueError(
                    "SegmentEIHO needs target= (the recorded outputs) or segment_a=: "
                    "per-segment coefficients come from the target's extrema")
            segment_a = self.segment_coefficients(x, target)
        return eiho(
            x, segment_a.to(x.dtype), rule=self.rule, threshold=self._threshold(),
            state=state, per_segment=True, eps=self.eps, max_depth=self.max_depth,
            output=self.output,
        )

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        """Raises ``ValueError``: the coefficients come from the target's next extremum."""
        raise ValueError(
            "SegmentEIHO cannot be deployed: its per-segment coefficients come from the "
            "target's next extremum (not causal). Train an EIHO with a fixed or learnable a.")

    def extra_repr(self) -> str:
        return f"rule={self.rule!r}, a_formula={self.a_formula!r}"


def _example() -> SegmentEIHO:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", NonCausalWarning)
        return SegmentEIHO(rule="dominant", threshold=0.1, max_depth=6)


register_operator("eiho_segment", SegmentEIHO, example=Example(
    _example, bad_values={"threshold": -1.0}))
