"""The stop-type Prandtl-Ishlinskii model with piecewise-linear characteristics, its
per-sample step (identification: :mod:`torchhys.identification.stop_pi`).

The maths is in :mod:`torchhys.functional.stop_pi`; the module holds the thresholds, the
segment slopes, the linear term, the offset and the input's center, and the step runs the
same :func:`~torchhys.functional.play_step` and
:func:`~torchhys.functional.stop_pi.stop_characteristic` as the sequence path.

A friction element (Coulomb slip) in series with a spring, or a family of them, is a
superposition of stop operators; a nonlinear spring (stiffening, a dead zone of backlash) is
the characteristic each stop's output goes through. Such elements dissipate energy: with
non-negative slopes the loops run clockwise in the (input, output) plane (the output leads),
the orientation of friction force against displacement and of a magnetic core's field
against its flux density.

**The exact inverse of a stop-type Prandtl-Ishlinskii model, as an operator.**

A :class:`~torchhys.StopPrandtlIshlinskii` model ``y = F[x]`` whose output is strictly
monotone in the current input (``linear_weight`` nonzero and every segment slope of its sign:
:func:`~torchhys.functional.stop_pi.check_invertible`, the case of a fit with non-negative
slopes and a positive linear weight) has an exact inverse: at each sample the output is a
piecewise-linear, strictly monotone function of the input given the stops' state, solved in
closed form on the segment that holds the target
(:func:`~torchhys.functional.stop_pi.stop_pi_inverse_step`), and the stops then move with the
solved input. Fitted in the direction where the stop-type model has the right shape (e.g. a
forward model, command -> response), it is the compensator (response -> command) of that
model: fed the model's output from the same state, it returns the model's input.

The sequence path loops over time (each sample's state depends on the inputs solved before
it), so it is much slower than the model's own (a scan); docs/models.md gives the costs of
both, measured by ``benchmarks/stop_pi.py``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_bool,
    check_int,
    check_real,
)
from torchhys.functional.backlash import check_play_state, play_step
from torchhys.functional.stop_pi import (
    check_invertible,
    check_stop_parameters,
    inverse_constants,
    stop_characteristic,
    stop_pi,
    stop_pi_inverse,
    stop_pi_inverse_step,
)
from torchhys.operator import HysteresisOperator
from torchhys.registry import register_operator
from torchhys.step import OperatorStep, StateBlock
from torchhys.testing import Example

__all__ = ["StopPIInverse", "StopPIInverseStep", "StopPIStep", "StopPrandtlIshlinskii"]


def _as_real_tensor(value: object, name: str) -> Tensor:
    """A tensor, or a (nested) sequence of real numbers as one; ``TypeError`` naming ``name``
    for anything else (strings, None entries, complex values)."""
    try:
        t = value if isinstance(value, Tensor) else torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name} must be a tensor or a sequence of real numbers, got "
                        f"{value!r}") from None
    if t.is_complex() or t.dtype == torch.bool:
        raise TypeError(f"{name} must hold real numbers, got dtype {t.dtype}")
    return t


class StopPIStep(OperatorStep):
    """A :class:`StopPrandtlIshlinskii` model, one sample at a time.

    State: ``plays`` (N columns, 0 at the first sample: the plays of ``x - center``).
    Feature: the model's output.
    """

    def __init__(self, thresholds: Tensor, weights: Tensor, center: Tensor,
                 linear_weight: Tensor, offset: Tensor) -> None:
        super().__init__()
        self.register_buffer("r", thresholds.detach().clone())
        self.register_buffer("weights", weights.detach().clone())
        self.register_buffer("center", center.detach().clone().reshape(()))
        self.register_buffer("linear_weight", linear_weight.detach().clone().reshape(()))
        self.register_buffer("offset", offset.detach().clone().reshape(()))
        self.n_outputs = 1
        self.state_spec = [StateBlock("plays", int(thresholds.shape[0]))]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        u = x - self.center  # (B, 1)
        p = play_step(u, self.r, state[0])  # (B, N)
        y = self.offset + self.linear_weight * u + stop_characteristic(
            (u - p).unsqueeze(1), self.r, self.weights)
        return y, [p]


class StopPrandtlIshlinskii(HysteresisOperator):
    """Stop-type Prandtl-Ishlinskii model with piecewise-linear characteristics:

        y = offset + w0 u + sum_i sum_k W[i, k] clamp(s_i, kappa[i, k], kappa[i, k + 1]),

    ``u = x - center``, ``s_i`` the stop operator of threshold ``r_i`` of u (in
    ``[-r_i, r_i]``), ``kappa[i, k] = r_i (2 k / K - 1)`` (K equal segments; ``W[i, k]`` the
    slope of stop i's characteristic on segment k). ``K = 1`` is the classical stop-type
    model. See :mod:`torchhys.functional.stop_pi`; identify it with :func:`fit_stop_pi`.

    Args:
        thresholds: stop thresholds r_i > 0, (N,).
        weights: segment slopes, (N, K) (a tensor or nested lists); zeros (one segment) if
            None.
        center: the input value at which the stops start (their plays at 0).
        linear_weight, offset: w0 and the offset.
        learnable: make the weights, linear weight and offset trainable (the thresholds and
            the center stay fixed).

    Shape:
        - x: (time,) or (batch, time)
        - state: the plays of ``x - center`` before the first sample, (N,) or (batch, N);
          zeros if None
        - returns ``(y, state)``: y the shape of x; state the plays at the last sample
          (chunked calls with it equal one call).
    """

    n_outputs: int = 1

    def __init__(
        self,
        thresholds: Tensor | Sequence[float],
        weights: Tensor | Sequence[Sequence[float]] | None = None,
        *,
        center: float = 0.0,
        linear_weight: float = 0.0,
        offset: float = 0.0,
        learnable: bool = False,
    ) -> None:
        super().__init__()
        r = _as_real_tensor(thresholds, "thresholds")
        if not r.is_floating_point():
            r = r.to(torch.get_default_dtype())
        w = (torch.zeros(r.shape[0] if r.dim() == 1 else 0, 1, dtype=r.dtype) if weights is None
             else _as_real_tensor(weights, "weights").to(r.dtype))
        check_stop_parameters(r, w)
        check_bool(learnable, "learnable")
        w = w.detach().clone()
        scalars = {name: torch.tensor(check_real(value, name), dtype=r.dtype) for name, value in
                   (("center", center), ("linear_weight", linear_weight), ("offset", offset))}
        self.register_buffer("thresholds", r.detach().clone())
        self.register_buffer("center", scalars["center"])
        if learnable:
            self.weights = nn.Parameter(w)
            self.linear_weight = nn.Parameter(scalars["linear_weight"])
            self.offset = nn.Parameter(scalars["offset"])
        else:
            self.register_buffer("weights", w)
            self.register_buffer("linear_weight", scalars["linear_weight"])
            self.register_buffer("offset", scalars["offset"])

    @property
    def segments(self) -> int:
        """K, the segments of each characteristic."""
        return int(self.weights.shape[1])

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        check_play_state(state, x, self.thresholds.shape[0], "state")
        return stop_pi(x, self.thresholds, self.weights, center=self.center,
                       linear_weight=self.linear_weight, offset=self.offset, state=state)

    @torch.no_grad()
    def project_(self) -> StopPrandtlIshlinskii:
        """Clamp the slopes at 0 in place (after an optimizer step of a ``learnable`` model
        fitted with ``nonnegative=True``: projected gradient keeps every characteristic
        rising, the loops clockwise); returns self."""
        self.weights.clamp_(min=0.0)
        return self

    def inverse(self) -> StopPIInverse:
        """The exact inverse ``x = F^-1[y]`` as an operator (:class:`~torchhys.StopPIInverse`,
        detached parameters; see :class:`StopPIInverse`): the compensator of this
        model. It shares the model's state (the plays of ``x - center``).

        Raises:
            ValueError: the output is not strictly monotone in the input (``linear_weight``
                zero, or a segment slope of the other sign).
        """

        return StopPIInverse.from_model(self)

    def streaming_step(self, dtype: torch.dtype) -> StopPIStep:
        """The per-sample step with the current parameters, in ``dtype``."""
        return StopPIStep(*(t.detach().to(dtype) for t in (
            self.thresholds, self.weights, self.center, self.linear_weight, self.offset)))

    constraints = {"thresholds": "positive", "weights": "finite", "center": "finite",
                   "linear_weight": "finite", "offset": "finite"}

    def extra_repr(self) -> str:
        return (f"thresholds={self.thresholds.numel()}, segments={self.segments}, "
                f"center={float(self.center):.4g}")


register_operator("stop_pi", StopPrandtlIshlinskii, example=Example(
    lambda: StopPrandtlIshlinskii(torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64),
                                  [[0.5, 0.2], [0.3, 0.4], [0.2, 0.1]], center=0.1,
                                  linear_weight=0.5, offset=-0.2),
    bad_values={"thresholds": 0.0, "weights": float("inf")}))


class StopPIInverseStep(OperatorStep):
    """Per-sample step of :class:`StopPIInverse`
    (:func:`~torchhys.functional.stop_pi.stop_pi_inverse_step`).

    State: ``plays`` (N columns, 0 at the first sample: the model's plays of ``x - center``).
    Feature: the solved input. Shapes: y (batch, 1) -> features (batch, 1).
    """

    def __init__(self, thresholds: Tensor, weights: Tensor, center: Tensor,
                 linear_weight: Tensor, offset: Tensor) -> None:
        super().__init__()
        sign, w, w0, knots, jumps, floor = inverse_constants(
            thresholds.detach(), weights.detach(), linear_weight.detach().reshape(()))
        for name, v in (("r", thresholds), ("sign", sign), ("w", w), ("w0", w0),
                        ("knots", knots), ("jumps", jumps), ("floor", floor),
                        ("center", center.reshape(())), ("offset", offset.reshape(()))):
            self.register_buffer(name, v.detach().clone())
        self.n_outputs = 1
        self.state_spec = [StateBlock("plays", int(thresholds.shape[0]))]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        u, p = stop_pi_inverse_step(x, state[0], self.r, self.sign, self.w, self.w0,
                                    self.knots, self.jumps, self.floor, self.center,
                                    self.offset)
        return u, [p]


class StopPIInverse(HysteresisOperator):
    """``x = F^-1[y]``, the exact inverse of a :class:`~torchhys.StopPrandtlIshlinskii`
    model F (module docstring). Fixed (buffers only): build it with :meth:`from_model` (or
    ``model.inverse()``); the plain constructor gives a placeholder of the right shape for
    ``load_state_dict``.

    Args:
        n_stops: number of stop operators N (>= 1).
        segments: segments K of each characteristic (>= 1).

    Shape:
        - y: (time,) or (batch, time)
        - state: the model's plays before the first sample, (N,) or (batch, N); zeros if
          None (the inverse of the model started from zero state)
        - returns ``(x, state)``: x the shape of y; state the model's plays at the last
          sample (chunked calls with it equal one call).
    """

    n_outputs: int = 1

    def __init__(self, n_stops: int = 1, segments: int = 1) -> None:
        super().__init__()
        check_int(n_stops, "n_stops", minimum=1)
        check_int(segments, "segments", minimum=1)
        dtype = torch.get_default_dtype()
        self.register_buffer("thresholds",
                             torch.arange(1, n_stops + 1, dtype=dtype) / n_stops)
        self.register_buffer("weights", torch.zeros(n_stops, segments, dtype=dtype))
        self.register_buffer("center", torch.zeros((), dtype=dtype))
        self.register_buffer("linear_weight", torch.ones((), dtype=dtype))
        self.register_buffer("offset", torch.zeros((), dtype=dtype))

    @classmethod
    @torch.no_grad()
    def from_model(cls, model: StopPrandtlIshlinskii) -> StopPIInverse:
        """The inverse of ``model`` (its current parameters, detached), in its dtype.

        Raises:
            TypeError: ``model`` is not a :class:`~torchhys.StopPrandtlIshlinskii`.
            ValueError: the model's output is not strictly monotone in its input (no
                inverse; :func:`~torchhys.functional.stop_pi.check_invertible`).
        """
        if not isinstance(model, StopPrandtlIshlinskii):
            raise TypeError(f"model must be a StopPrandtlIshlinskii, got "
                            f"{type(model).__name__}")
        check_stop_parameters(model.thresholds.detach(), model.weights.detach())
        check_invertible(model.weights.detach(), model.linear_weight.detach())
        n, k = model.weights.shape
        inverse = cls(int(n), int(k)).to(model.thresholds.dtype)
        for name in ("thresholds", "weights", "center", "linear_weight", "offset"):
            getattr(inverse, name).copy_(getattr(model, name).detach())
        return inverse.to(model.thresholds.device)

    @property
    def segments(self) -> int:
        """K, the segments of each characteristic."""
        return int(self.weights.shape[1])

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        as_batched_sequence(x, "x")  # the maths calls its input y: check x under its name
        check_play_state(state, x, self.thresholds.shape[0], "state")
        return stop_pi_inverse(x, self.thresholds, self.weights, center=self.center,
                               linear_weight=self.linear_weight, offset=self.offset, state=state)

    def streaming_step(self, dtype: torch.dtype) -> StopPIInverseStep:
        """The per-sample step with the current buffers, in ``dtype``."""
        return StopPIInverseStep(*(t.detach().to(dtype) for t in (
            self.thresholds, self.weights, self.center, self.linear_weight, self.offset)))

    constraints = {"thresholds": "positive", "weights": "finite", "center": "finite",
                   "linear_weight": "finite", "offset": "finite"}

    def check_loaded(self, values: Mapping[str, Tensor], prefix: str) -> None:
        """The model it would hold (also for a partial state dict, whose missing keys keep
        their current values): scalars, the shapes and values of
        :func:`~torchhys.functional.stop_pi.check_stop_parameters`, and an invertible model;
        each error names its key."""
        for name in ("center", "linear_weight", "offset"):
            if values[name].numel() != 1:
                raise ValueError(f"{prefix}{name} must be one finite number, got "
                                 f"{values[name].tolist()!r:.80}")
        try:
            check_stop_parameters(values["thresholds"], values["weights"])
            check_invertible(values["weights"], values["linear_weight"])
        except (TypeError, ValueError) as err:
            raise ValueError(f"{prefix}{err}") from None

    def extra_repr(self) -> str:
        return (f"n_stops={self.thresholds.numel()}, segments={self.segments}, "
                f"center={float(self.center):.4g}")


register_operator("stop_pi_inverse", StopPIInverse, example=Example(
    lambda: StopPrandtlIshlinskii(torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64),
                                  [[0.5, 0.2], [0.3, 0.4], [0.2, 0.1]], center=0.1,
                                  linear_weight=0.5, offset=-0.2).inverse(),
    bad_values={"thresholds": 0.0, "linear_weight": 0.0}))
