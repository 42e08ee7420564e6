"""The branch operators: :class:`EIHO` with its coefficient kinds (:class:`Coefficients`) and
:class:`ZhaoTanOperator`; their steps are in :mod:`torchhys.operators.branch_steps`, the
non-causal per-segment EIHO in :mod:`torchhys.operators.eiho_segment`."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence, check_choice, concrete
from torchhys.functional._branch import BranchState, SquareRoot, ZhaoTanShape
from torchhys.functional.eiho import eiho, zhao_tan
from torchhys.functional.turning_points import estimate_threshold
from torchhys.operator import HysteresisOperator
from torchhys.operators.branch_steps import branch_step
from torchhys.registry import register_operator
from torchhys.step import OperatorStep
from torchhys.testing import Example

__all__ = ["EIHO", "AnchoredCoefficients", "Coefficients", "FixedCoefficients",
           "LearnableCoefficients", "ZhaoTanOperator", "coefficients"]

_OUTPUTS = ("level", "branch")


def _threshold_buffer(threshold: float | str) -> Tensor:
    if threshold == "auto":
        return torch.tensor(float("nan"))
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)):
        raise TypeError(f"threshold must be a number or 'auto', got {threshold!r}")
    if not math.isfinite(threshold) or threshold < 0:
        raise ValueError(f"threshold must be a finite number >= 0 or 'auto', got {threshold!r}")
    return torch.tensor(float(threshold))


class Coefficients(nn.Module):
    """An EIHO's coefficients ``a`` (ascending, descending): one kind of object per way they
    are set. :meth:`forward` returns ``(a (2,), slope)``, the coefficient of a branch that
    starts at ``x_e`` being ``a_d exp(slope_d x_e)`` (``slope`` None: constant)."""

    def forward(self) -> tuple[Tensor, Tensor | None]:  # pragma: no cover (abstract)
        raise NotImplementedError

    def at_center(self) -> Tensor:
        """The coefficients (2,) of a branch that starts at the reference level (for
        constant coefficients: the coefficients)."""
        return self()[0]


def _check_a_init(a_init: object) -> None:
    """The initial value of trained coefficients: a positive finite number."""
    if not (isinstance(a_init, (int, float)) and math.isfinite(a_init) and a_init > 0):
        raise ValueError(f"a_init must be a positive number, got {a_init!r}")


class FixedCoefficients(Coefficients):
    """Constant coefficients (a buffer ``a``): a positive number or a pair."""

    def __init__(self, a: float | Sequence[float]) -> None:
        super().__init__()
        pair = (a, a) if isinstance(a, (int, float)) and not isinstance(a, bool) else a
        try:
            values = [float(v) for v in pair]  # type: ignore[union-attr]
        except (TypeError, ValueError):
            values = []
        if len(values) != 2 or not all(math.isfinite(v) and v > 0 for v in values):
            raise ValueError(f"a must be positive (a number or a pair), got {a!r}")
        self.register_buffer("a", torch.tensor(values))

    def forward(self) -> tuple[Tensor, Tensor | None]:
        return self.a, None

    def extra_repr(self) -> str:
        return f"a={self.a.tolist()}"


class LearnableCoefficients(Coefficients):
    """Trained coefficients ``exp(log_a)``: one, or one per direction."""

    def __init__(self, a_init: float = 1.0, per_direction: bool = False) -> None:
        super().__init__()
        _check_a_init(a_init)
        self.log_a = nn.Parameter(torch.full((2 if per_direction else 1,), math.log(a_init)))

    def forward(self) -> tuple[Tensor, Tensor | None]:
        return torch.exp(self.log_a).expand(2), None


class AnchoredCoefficients(Coefficients):
    """Trained coefficients that depend on the branch's start point ``x_e``:
    ``a_d(x_e) = exp(log_a_d + k_d (x_e - center) / scale)``, ``k`` starting at 0."""

    def __init__(self, a_init: float = 1.0, center: float = 0.0, scale: float = 1.0) -> None:
        super().__init__()
        _check_a_init(a_init)
        if not (math.isfinite(center) and math.isfinite(scale) and scale > 0):
            raise ValueError("anchor_center must be finite and anchor_scale positive, got "
                             f"{center!r}, {scale!r}")
        self.log_a = nn.Parameter(torch.full((2,), math.log(a_init)))
        self.slope = nn.Parameter(torch.zeros(2))
        self.register_buffer("norm", torch.tensor([float(center), float(scale)]))

    def forward(self) -> tuple[Tensor, Tensor | None]:
        # a_d exp(k_d (x_e - c) / s) = [a_d exp(-k_d c / s)] exp((k_d / s) x_e)
        slope = self.slope / self.norm[1]
        return torch.exp(self.log_a) * torch.exp(-slope * self.norm[0]), slope

    def at_center(self) -> Tensor:
        return torch.exp(self.log_a)


class _TurningPointOperator(HysteresisOperator):
    """Holds the detector threshold (a buffer; NaN until an ``"auto"`` one is calibrated)."""

    n_outputs: int = 1

    constraints = {"threshold": "nonnegative_or_nan"}

    def __init__(
        self, threshold: float | str, rule: str, max_depth: int, output: str = "level"
    ) -> None:
        super().__init__()
        check_choice(rule, "rule", ("recent", "dominant"))
        check_choice(output, "output", _OUTPUTS)
        self.rule, self.output = rule, output
        self.max_depth = max_depth
        self.register_buffer("threshold", _threshold_buffer(threshold))

    def calibrate(self, x: Tensor) -> None:
        """Calibrate an ``"auto"`` threshold that is not calibrated yet on x (batch, time)."""
        if bool(torch.isnan(self.threshold)):
            self.calibrate_threshold(x)

    def calibrate_threshold(self, x: Tensor) -> Tensor:
        """Set the threshold from data: the median of :func:`estimate_threshold` over rows."""
        th = estimate_threshold(x).reshape(-1).median().detach()
        self.threshold.copy_(th)
        return th

    def _threshold(self) -> Tensor:
        if concrete(self.threshold) and bool(torch.isnan(self.threshold)):
            raise ValueError(
                "threshold='auto' is not calibrated yet: call calibrate_threshold(x) on "
                "representative data first (a per-chunk estimate would break streaming)"
            )
        return self.threshold


class EIHO(_TurningPointOperator):
    """Elementary inverse hysteresis operator, Eq. (2), with streaming state.

    Its coefficients ``a`` (ascending, descending) are one of the :class:`Coefficients`
    objects, or given by the shorthand of ``a``:
        * a positive number, or a pair ``(ascending, descending)``:
          :class:`FixedCoefficients`;
        * ``"learnable"``: :class:`LearnableCoefficients`, ``exp(log_a)`` (one, or one per
          direction with ``per_direction=True``), trained with the network;
        * ``"anchored"``: :class:`AnchoredCoefficients`, a learned positive function of the
          branch's start point ``x_e``:
          ``a_d(x_e) = exp(log_a_d + k_d (x_e - anchor_center) / anchor_scale)``, ``k``
          starting at 0 (a constant ``a_init``); set ``anchor_center`` / ``anchor_scale``
          near the input's mean and spread.
    The paper's per-segment ``a_i`` from the training targets is not causal: it is a
    separate operator, :class:`~torchhys.operators.eiho_segment.SegmentEIHO`
    (``"eiho_segment"``).

    Args:
        a: see above.
        rule: ``"recent"`` (Eq. (2) as printed) or ``"dominant"`` (return-point memory).
        threshold: reversal threshold of the turning-point detector, or ``"auto"`` (then
            call :meth:`calibrate_threshold` before :meth:`forward`).
        per_direction: with ``a="learnable"``, learn ascending and descending values.
        a_init: initial value of a learnable or anchored ``a``.
        max_depth: stack size of the ``"dominant"`` rule.
        eps: linear zone of the square root (see :func:`torchhys.functional.eiho`).
        anchor_center: with ``a="anchored"``, the input level where ``a_d = exp(log_a_d)``.
        anchor_scale: with ``a="anchored"``, the input scale of ``k`` (> 0).
        output: ``"level"`` (default): ``f`` (Eq. (2)); ``"branch"``: the branch-local value
            ``f - f(x_e)`` (``+/- a |x - x_e|^(1/2)`` from the committed anchor ``x_e``),
            bounded and free of the level that ``f`` accumulates along the history (a
            network feature that generalizes to new signals); see
            :func:`torchhys.functional.eiho`.

    Shapes:
        ``forward(x)``: x (time,) or (batch, time) -> f of the same shape, and a
        :class:`~torchhys.functional.BranchState` (tensors (batch, ...)).
    """

    def __init__(
        self, *, a: float | tuple[float, float] | str | Coefficients = 1.0,
        rule: str = "recent", threshold: float | str = 0.0, per_direction: bool = False,
        a_init: float = 1.0, max_depth: int = 32, eps: float = 1e-8,
        anchor_center: float = 0.0, anchor_scale: float = 1.0, output: str = "level",
    ) -> None:
        super().__init__(threshold, rule, max_depth, output)
        self.eps = check_eps(eps)
        self.coef = coefficients(a, per_direction=per_direction, a_init=a_init,
                                 anchor_center=anchor_center, anchor_scale=anchor_scale)

    def coefficient(self) -> Tensor:
        """The coefficients ``(ascending, descending)``, shape (2,); anchored ones: their
        values for a branch starting at ``anchor_center``."""
        return self.coef.at_center()

    def forward(self, x: Tensor, state: BranchState | None = None
                ) -> tuple[Tensor, BranchState]:
        """Apply the operator to ``x`` (time,) or (batch, time), continuing from ``state``."""
        as_batched_sequence(x, "x")
        a, slope = self.coef()
        return eiho(
            x, a.to(x.dtype), rule=self.rule, threshold=self._threshold(), state=state,
            eps=self.eps, max_depth=self.max_depth,
            anchor_slope=None if slope is None else slope.to(x.dtype), output=self.output,
        )

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        """The per-sample step (see :mod:`torchhys.operators.branch_steps`).

        Raises:
            ValueError: an uncalibrated ``"auto"`` threshold.
        """
        with torch.no_grad():
            a, slope = self.coef()
            return branch_step(
                SquareRoot(self.eps), self.rule, a, slope, self._threshold(),
                output=self.output, max_depth=self.max_depth, dtype=dtype,
            )

    def extra_repr(self) -> str:
        out = "" if self.output == "level" else f", output={self.output!r}"
        return f"rule={self.rule!r}{out}"


def check_eps(eps: object) -> float:
    """The square root's linear zone: a finite number >= 0."""
    if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not (
            math.isfinite(eps) and eps >= 0):
        raise ValueError(f"eps must be a finite number >= 0, got {eps!r}")
    return float(eps)


def coefficients(a: object, *, per_direction: bool = False, a_init: float = 1.0,
                 anchor_center: float = 0.0, anchor_scale: float = 1.0) -> Coefficients:
    """The :class:`Coefficients` of :class:`EIHO`'s ``a`` shorthand (see there); options
    that do not apply to the kind are an error."""
    if isinstance(a, Coefficients):
        kind = "object"
    elif a == "segment":
        raise ValueError("a='segment' (the paper's per-segment a from the targets) is not "
                         "causal: use the operator 'eiho_segment' (SegmentEIHO)")
    elif isinstance(a, str) and a not in ("learnable", "anchored"):
        raise ValueError(f"a must be a positive number, a pair, 'learnable' or 'anchored', "
                         f"got {a!r}")
    else:
        kind = a if isinstance(a, str) else "fixed"
    for name, value, default, kinds in (
        ("per_direction", per_direction, False, ("learnable",)),
        ("a_init", a_init, 1.0, ("learnable", "anchored")),
        ("anchor_center", anchor_center, 0.0, ("anchored",)),
        ("anchor_scale", anchor_scale, 1.0, ("anchored",)),
    ):
        if value != default and kind not in kinds:
            raise ValueError(f"{name}={value!r} applies only with a in {kinds}, got a={a!r}")
    if kind == "object":
        return a  # type: ignore[return-value]
    if kind == "learnable":
        return LearnableCoefficients(a_init, per_direction)
    if kind == "anchored":
        return AnchoredCoefficients(a_init, anchor_center, anchor_scale)
    return FixedCoefficients(a)  # type: ignore[arg-type]


class ZhaoTanOperator(_TurningPointOperator):
    """Zhao-Tan's operator ``f = (1 - exp(-|x - x_p|)) (x - x_p) + f(x_p)`` (Ref. [8]).

    Same turning-point machinery, rules, threshold and streaming state as :class:`EIHO`.

    Args:
        rule: ``"recent"`` or ``"dominant"``.
        threshold: reversal threshold or ``"auto"`` (then call :meth:`calibrate_threshold`).
        max_depth: stack size of the ``"dominant"`` rule.
        scale: input scale ``s`` (> 0):
            ``f = (1 - exp(-|x - x_p| / s)) (x - x_p) + f(x_p)``. With ``s = 1`` (the published
            form) an input of large range makes ``f`` almost ``x`` plus a constant; set ``s``
            near the input's spread.
        output: ``"level"`` (default) or ``"branch"`` (``f - f(x_p)``, as for :class:`EIHO`).
    """

    def __init__(
        self, *, rule: str = "recent", threshold: float | str = 0.0, max_depth: int = 32,
        scale: float = 1.0, output: str = "level",
    ) -> None:
        super().__init__(threshold, rule, max_depth, output)
        if not (isinstance(scale, (int, float)) and math.isfinite(scale) and scale > 0):
            raise ValueError(f"scale must be a positive number, got {scale!r}")
        self.scale = float(scale)

    def forward(
        self, x: Tensor, state: BranchState | None = None
    ) -> tuple[Tensor, BranchState]:
        """Apply the operator to ``x`` (time,) or (batch, time), continuing from ``state``."""
        return zhao_tan(
            x, rule=self.rule, threshold=self._threshold(), state=state,
            max_depth=self.max_depth, output=self.output, scale=self.scale,
        )

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        """The per-sample step (see :mod:`torchhys.operators.branch_steps`).

        Raises:
            ValueError: an uncalibrated ``"auto"`` threshold.
        """
        return branch_step(
            ZhaoTanShape(self.scale), self.rule, torch.ones(2), None, self._threshold(),
            output=self.output, max_depth=self.max_depth, dtype=dtype,
        )


register_operator("eiho", EIHO, example=Example(
    lambda: EIHO(a=(1.5, 0.8), rule="dominant", threshold=0.1, max_depth=6),
    bad_values={"threshold": -1.0}))
register_operator("zhao_tan", ZhaoTanOperator, example=Example(
    # chunked calls round the level f(x_p) differently (to about 1e-16)
    lambda: ZhaoTanOperator(threshold=0.05, scale=0.5), atol=1e-12,
    bad_values={"threshold": -1.0}))
