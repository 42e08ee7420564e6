"""``nn.Module`` wrappers of the branch operators: :class:`EIHO` and :class:`ZhaoTanOperator`."""

from __future__ import annotations

import math
import warnings

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence, check_choice
from torchhys.functional._branch import BranchState
from torchhys.functional.eiho import NonCausalWarning, eiho, segment_coefficients, zhao_tan
from torchhys.functional.turning_points import estimate_threshold
from torchhys.operator import Example, HysteresisOperator, OperatorStep, register_operator
from torchhys.operators.branch_steps import branch_step

__all__ = ["EIHO", "ZhaoTanOperator"]

_A_FORMULAS = ("sqrt", "paper")
_OUTPUTS = ("level", "branch")


def _threshold_buffer(threshold: float | str) -> Tensor:
    if threshold == "auto":
        return torch.tensor(float("nan"))
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)):
        raise TypeError(f"threshold must be a number or 'auto', got {threshold!r}")
    if not math.isfinite(threshold) or threshold < 0:
        raise ValueError(f"threshold must be a finite number >= 0 or 'auto', got {threshold!r}")
    return torch.tensor(float(threshold))


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
        if bool(torch.isnan(self.threshold)):
            raise ValueError(
                "threshold='auto' is not calibrated yet: call calibrate_threshold(x) on "
                "representative data first (a per-chunk estimate would break streaming)"
            )
        return self.threshold


class EIHO(_TurningPointOperator):
    """Elementary inverse hysteresis operator, Eq. (2), with streaming state.

    Modes of ``a``:
        * a positive number, or a pair ``(ascending, descending)``: fixed (causal);
        * ``"learnable"``: positive parameter(s) ``exp(log_a)`` (one, or one per direction
          with ``per_direction=True``), trained with the network (causal);
        * ``"anchored"``: a learned positive function of the branch's start point ``x_e``
          (causal): ``a_d(x_e) = exp(log_a_d + k_d (x_e - anchor_center) / anchor_scale)``,
          one ``(log_a_d, k_d)`` per direction, ``k`` starting at 0 (a constant ``a_init``);
          set ``anchor_center`` / ``anchor_scale`` near the input's mean and spread;
        * ``"segment"``: the paper's per-segment ``a_i`` from the training targets with
          ``a_formula`` (``"sqrt"``: ``|dy| / |dx|^(1/2)``, consistent with Eq. (2);
          ``"paper"``: Eq. (19) as printed, ``|dy| / dx^2``). **Not causal**: pass
          ``target=`` (whole record) or precomputed ``segment_a=`` to :meth:`forward`.

    Args:
        a: see above.
        rule: ``"recent"`` (Eq. (2) as printed) or ``"dominant"`` (return-point memory).
        a_formula: formula of the ``"segment"`` mode.
        threshold: reversal threshold of the turning-point detector, or ``"auto"`` (then
            call :meth:`calibrate_threshold` before :meth:`forward`).
        per_direction: with ``a="learnable"``, learn ascending and descending values.
        a_init: initial value of a learnable ``a``.
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
        self, *, a: float | tuple[float, float] | str = 1.0, rule: str = "recent",
        a_formula: str = "sqrt", threshold: float | str = 0.0, per_direction: bool = False,
        a_init: float = 1.0, max_depth: int = 32, eps: float = 1e-8,
        anchor_center: float = 0.0, anchor_scale: float = 1.0, output: str = "level",
    ) -> None:
        super().__init__(threshold, rule, max_depth, output)
        check_choice(a_formula, "a_formula", _A_FORMULAS)
        mode = a if isinstance(a, str) else "fixed"
        for name, value, default, modes in (
            ("per_direction", per_direction, False, ("learnable",)),
            ("a_init", a_init, 1.0, ("learnable", "anchored")),
            ("anchor_center", anchor_center, 0.0, ("anchored",)),
            ("anchor_scale", anchor_scale, 1.0, ("anchored",)),
            ("a_formula", a_formula, "sqrt", ("segment",)),
        ):
            if value != default and mode not in modes:
                raise ValueError(
                    f"{name}={value!r} applies only with a in {modes}, got a={a!r}"
                )
        if isinstance(eps, bool) or not isinstance(eps, (int, float)) or not (
                math.isfinite(eps) and eps >= 0):
            raise ValueError(f"eps must be a finite number >= 0, got {eps!r}")
        self.a_formula, self.eps = a_formula, float(eps)
        self.per_segment = a == "segment"
        self.causal = not self.per_segment
        if a in ("learnable", "anchored"):
            if not (math.isfinite(a_init) and a_init > 0):
                raise ValueError(f"a_init must be a positive number, got {a_init!r}")
            n_a = 2 if (per_direction or a == "anchored") else 1
            self.log_a = nn.Parameter(torch.full((n_a,), math.log(a_init)))
            if a == "anchored":
                ok = math.isfinite(anchor_center) and math.isfinite(anchor_scale)
                if not (ok and anchor_scale > 0):
                    raise ValueError(
                        "anchor_center must be finite and anchor_scale positive, got "
                        f"{anchor_center!r}, {anchor_scale!r}"
                    )
                self.anchor_slope = nn.Parameter(torch.zeros(2))
                self.register_buffer(
                    "anchor_norm", torch.tensor([float(anchor_center), float(anchor_scale)])
                )
        elif self.per_segment:
            warnings.warn(
                "EIHO(a='segment') uses the target's next extremum: not causal, for replaying "
                "recorded data only", NonCausalWarning, stacklevel=2,
            )
        elif isinstance(a, str):
            raise ValueError(
                "a must be a positive number, a pair, 'learnable', 'anchored' or 'segment', "
                f"got {a!r}"
            )
        else:
            pair = (a, a) if isinstance(a, (int, float)) else tuple(a)
            if len(pair) != 2 or not all(isinstance(v, (int, float)) and v > 0 for v in pair):
                raise ValueError(f"a must be positive (a number or a pair), got {a!r}")
            self.register_buffer("a_fixed", torch.tensor([float(v) for v in pair]))

    def coefficient(self) -> Tensor:
        """The causal coefficients ``(ascending, descending)``, shape (2,).

        With ``a="anchored"``: their values for a branch starting at ``anchor_center``.
        """
        if hasattr(self, "log_a"):
            return torch.exp(self.log_a).expand(2)
        if self.per_segment:
            raise ValueError("a='segment' has no fixed coefficient: it comes from targets")
        return self.a_fixed

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
        """Apply the operator to ``x`` (time,) or (batch, time), continuing from ``state``.

        ``target`` (same shape as ``x``, the whole record) or ``segment_a`` (from
        :meth:`segment_coefficients`, for chunked replay) are required with ``a="segment"``.
        """
        as_batched_sequence(x, "x")
        if self.per_segment:
            if segment_a is None:
                if target is None:
                    raise ValueError(
                        "EIHO(a='segment') needs target= (the recorded outputs) or segment_a=: "
                        "per-segment coefficients come from the target's extrema"
                    )
                segment_a = self.segment_coefficients(x, target)
            a = segment_a
        else:
            a = self.coefficient()
        slope = None
        if hasattr(self, "anchor_slope"):
            a, slope = self._anchored()
            slope = slope.to(x.dtype) if x.is_floating_point() else slope
        return eiho(
            x, a.to(x.dtype) if x.is_floating_point() else a, rule=self.rule,
            threshold=self._threshold(), state=state, per_segment=self.per_segment,
            eps=self.eps, max_depth=self.max_depth, anchor_slope=slope, output=self.output,
        )

    def _anchored(self) -> tuple[Tensor, Tensor]:
        """``a="anchored"`` as coefficients of ``exp(slope x_e)``: ``(a (2,), slope (2,))``.

        ``a_d exp(k_d (x_e - c) / s) = [a_d exp(-k_d c / s)] exp((k_d / s) x_e)``.
        """
        slope = self.anchor_slope / self.anchor_norm[1]
        return self.coefficient() * torch.exp(-slope * self.anchor_norm[0]), slope

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        """The per-sample step (see :mod:`torchhys.operators.branch_steps`).

        Raises:
            ValueError: ``a="segment"`` (not causal) or an uncalibrated ``"auto"`` threshold.
        """
        if self.per_segment:
            raise ValueError(
                "EIHO(a='segment') cannot be deployed: its per-segment coefficients come from "
                "the target's next extremum (not causal). Train with a fixed or learnable a."
            )
        with torch.no_grad():
            a, slope = self._anchored() if hasattr(self, "anchor_slope") else (
                self.coefficient(), None)
            return branch_step(
                "eiho", self.rule, a, slope, self._threshold(), eps=self.eps, scale=1.0,
                output=self.output, max_depth=self.max_depth, dtype=dtype,
            )

    def extra_repr(self) -> str:
        mode = "segment" if self.per_segment else ("learnable" if hasattr(self, "log_a") else "")
        mode = "anchored" if hasattr(self, "anchor_slope") else mode
        out = "" if self.output == "level" else f", output={self.output!r}"
        return f"rule={self.rule!r}, a={mode or self.a_fixed.tolist()}{out}"


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
            "zhao_tan", self.rule, torch.ones(2), None, self._threshold(), eps=0.0,
            scale=self.scale, output=self.output, max_depth=self.max_depth, dtype=dtype,
        )


register_operator("eiho", EIHO, example=Example(
    lambda: EIHO(a=(1.5, 0.8), rule="dominant", threshold=0.1, max_depth=6),
    bad_values={"threshold": -1.0}))
register_operator("zhao_tan", ZhaoTanOperator, example=Example(
    # chunked calls round the level f(x_p) differently (to about 1e-16)
    lambda: ZhaoTanOperator(threshold=0.05, scale=0.5), atol=1e-12,
    bad_values={"threshold": -1.0}))
