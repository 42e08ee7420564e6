"""The exact inverse of a generalized Prandtl-Ishlinskii model, as an operator.

The model is ``y = g(p[x])`` (:class:`~torchhys.GeneralizedPrandtlIshlinskii`): a
Prandtl-Ishlinskii model ``p`` with non-negative weights and a strictly increasing output
function ``g``. Its inverse is ``x = p^-1[g^-1(y)]``: the memoryless inverse of ``g``
(:func:`monotone_inverse`), then the analytic inverse of the PI part, itself a PI model of
``g^-1(y)`` (:func:`~torchhys.functional.prandtl_ishlinskii_inverse_parameters`). Fitted in
the direction where a generalized PI model has the right shape (e.g. H -> B of a magnetic
core, whose loops saturate), it models the other direction (B -> H) exactly.

``g^-1`` has no closed form. Because ``|sum_k c_k tanh(.)| <= sum_k c_k``, the root of
``g(v) = y`` lies in ``[(y - offset - C) / a, (y - offset + C) / a]`` (``C = sum_k c_k``);
:func:`monotone_inverse` halves that bracket 20 times, takes two Newton steps kept inside
the final bracket, and ends with one more Newton step from the (detached) result, so that
the result is differentiable with the implicit-function gradient ``1 / g'(v)``. The sequence
path and the per-sample step call the same function.

A fitted ``g`` that saturates has a tiny gain ``a``: its inverse is steep beyond the
saturation, and its bracket huge. ``lower``/``upper`` bound ``v`` (e.g. the range of the
PI part's output in the fit, with a margin): the bracket is cut to them and ``v`` clamped,
so that the inverse holds ``v`` at the bound for an input beyond ``g(upper)`` (or below
``g(lower)``). Unbounded (the exact inverse) by default.
"""

import torch
from torch import Tensor

from torchhys._checks import as_batched_sequence, check_int, check_real
from torchhys.functional.backlash import backlash, check_play_state, play_step
from torchhys.functional.prandtl_ishlinskii import (
    pi_output,
    prandtl_ishlinskii_inverse_parameters,
)
from torchhys.operator import Example, HysteresisOperator, register_operator
from torchhys.operators.generalized_pi import (
    GeneralizedPIStep,
    GeneralizedPrandtlIshlinskii,
    monotone_output,
)

__all__ = ["GeneralizedPIInverse", "GeneralizedPIInverseStep", "monotone_inverse",
           "monotone_slope"]

BISECTIONS = 20
"""Halvings of the bracket of ``g^-1`` (its width shrinks by 2^-20), before the Newton
steps."""
NEWTON = 2
"""Newton steps from the bisection's midpoint, each kept inside the final bracket
(quadratic convergence: from 2^-20 of the bracket to float64's resolution), before the last
one that carries the gradient."""


def monotone_slope(v: Tensor, gain: Tensor, unit_weights: Tensor, centers: Tensor,
                   slopes: Tensor) -> Tensor:
    """``g'(v)`` of :func:`monotone_output`'s ``g``: v (...) -> (...). Scriptable."""
    tanh = torch.tanh(slopes * (v.unsqueeze(-1) - centers))
    return gain + (unit_weights * slopes * (1.0 - tanh * tanh)).sum(-1)


def monotone_inverse(y: Tensor, gain: Tensor, unit_weights: Tensor, centers: Tensor,
                     slopes: Tensor, offset: Tensor, lower: Tensor, upper: Tensor,
                     bisections: int = BISECTIONS, newton: int = NEWTON) -> Tensor:
    """``v`` in ``[lower, upper]`` with ``g(v) = y`` for the increasing ``g`` of
    :func:`monotone_output` (the bound where there is none): y (...) -> (...). Scriptable.

    Bisection on ``[(y - offset - C) / gain, (y - offset + C) / gain]`` (``C`` the sum of
    ``unit_weights``) cut to ``[lower, upper]`` (0-dim, may be infinite), then ``newton``
    Newton steps kept inside the final bracket, all detached, then one more Newton step
    (the gradient with respect to y and the parameters is the implicit-function one),
    clamped to the bounds.
    """
    if unit_weights.numel() == 0:  # g is affine: its inverse in closed form
        return torch.minimum(torch.maximum((y - offset) / gain, lower), upper)
    spread = unit_weights.sum()
    base = (y - offset).detach()
    lo = torch.maximum((base - spread.detach()) / gain.detach(), lower)
    hi = torch.minimum((base + spread.detach()) / gain.detach(), upper)
    hi = torch.maximum(lo, hi)
    target = y.detach()
    a, c, b, s, off = (gain.detach(), unit_weights.detach(), centers.detach(), slopes.detach(),
                       offset.detach())
    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        below = monotone_output(mid, a, c, b, s, off) < target
        lo = torch.where(below, mid, lo)
        hi = torch.where(below, hi, mid)
    v = 0.5 * (lo + hi)
    for _ in range(newton):
        step = (monotone_output(v, a, c, b, s, off) - target) / monotone_slope(v, a, c, b, s)
        v = torch.minimum(torch.maximum(v - step, lo), hi)
    residual = monotone_output(v, gain, unit_weights, centers, slopes, offset) - y
    v = v - residual / monotone_slope(v, gain, unit_weights, centers, slopes)
    return torch.minimum(torch.maximum(v, lower), upper)


class GeneralizedPIInverseStep(GeneralizedPIStep):
    """Per-sample step of :class:`GeneralizedPIInverse`: :func:`monotone_inverse`, then N
    plays (:func:`~torchhys.functional.play_step`) and
    :func:`~torchhys.functional.pi_output`.

    State: ``plays`` (N columns, 0 at the first sample). Shapes: x (batch, 1) -> features
    (batch, 1). The buffers of :class:`~torchhys.operators.generalized_pi.GeneralizedPIStep` (the
    model's effective parameters), and the bounds ``lower``, ``upper`` of ``g^-1``.
    """

    def __init__(self, widths: Tensor, weights: Tensor, linear_weight: Tensor, gain: Tensor,
                 unit_weights: Tensor, centers: Tensor, slopes: Tensor, offset: Tensor,
                 lower: Tensor, upper: Tensor) -> None:
        super().__init__(widths, weights, linear_weight, gain, unit_weights, centers, slopes,
                         offset)
        self.register_buffer("lower", lower.detach().clone())
        self.register_buffer("upper", upper.detach().clone())

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        v = monotone_inverse(x, self.gain, self.unit_weights, self.centers, self.slopes,
                             self.offset, self.lower, self.upper)
        z = play_step(v, self.r, state[0])
        return pi_output(v, z.unsqueeze(1), self.weights, self.linear_weight), [z]


_LOADED = {
    "widths": ("finite and >= 0 (play widths)", lambda t: t.isfinite() & (t >= 0)),
    "weights": ("finite", torch.isfinite),
    "linear_weight": ("finite", torch.isfinite),
    "gain": ("finite and > 0 (g increasing)", lambda t: t.isfinite() & (t > 0)),
    "unit_weights": ("finite and >= 0 (g increasing)", lambda t: t.isfinite() & (t >= 0)),
    "centers": ("finite", torch.isfinite),
    "slopes": ("finite and >= 0 (g non-decreasing in each unit)",
               lambda t: t.isfinite() & (t >= 0)),
    "offset": ("finite", torch.isfinite),
    "lower": ("a number or -inf", lambda t: ~t.isnan() & (t < torch.inf)),
    "upper": ("a number or +inf", lambda t: ~t.isnan() & (t > -torch.inf)),
}
"""What :class:`GeneralizedPIInverse` asks of a loaded buffer: ``g^-1`` needs an increasing
``g`` (:func:`monotone_inverse`'s bracket and bisection): ``gain > 0``, each unit's weight
and slope ``>= 0`` (a slope that underflowed to 0 makes its unit constant)."""


def _check_loaded(state_dict: dict, prefix: str) -> None:
    """Raise ``ValueError`` naming the key of a buffer that breaks :data:`_LOADED`, or bounds
    with ``lower >= upper``."""
    for name, (what, ok) in _LOADED.items():
        t = state_dict.get(prefix + name)
        if isinstance(t, Tensor) and t.is_floating_point() and not bool(ok(t).all()):
            raise ValueError(f"{prefix}{name} must be {what}, got {t.tolist()!r:.80}")
    lower, upper = state_dict.get(prefix + "lower"), state_dict.get(prefix + "upper")
    if isinstance(lower, Tensor) and isinstance(upper, Tensor) and not bool(lower < upper):
        raise ValueError(f"{prefix}lower must be below {prefix}upper, got {float(lower)!r} "
                         f"and {float(upper)!r}")


class GeneralizedPIInverse(HysteresisOperator):
    """``x = p^-1[g^-1(y)]``, the inverse of a :class:`~torchhys.GeneralizedPrandtlIshlinskii`
    model (module docstring). Fixed (buffers only): build it with
    :meth:`from_model` (or ``model.inverse()``); the plain constructor gives a placeholder of
    the right shape for ``load_state_dict``.

    Args:
        n_plays: number of play operators N of the inverse PI part (>= 1).
        n_units: number of tanh units K of ``g`` (>= 0).

    Shape:
        - y: (time,) or (batch, time)
        - state: the inverse PI part's play outputs before the first sample, (N,) or
          (batch, N); zeros if None (the inverse of the model started from zero state)
        - returns ``(x, state)``: x the shape of y; chunked calls equal one call.
    """

    n_outputs: int = 1

    def __init__(self, n_plays: int = 1, n_units: int = 0) -> None:
        super().__init__()
        check_int(n_plays, "n_plays", minimum=1)
        check_int(n_units, "n_units", minimum=0)
        dtype = torch.get_default_dtype()
        self.register_buffer("widths", torch.arange(1, n_plays + 1, dtype=dtype) / n_plays)
        self.register_buffer("weights", torch.zeros(n_plays, dtype=dtype))
        self.register_buffer("linear_weight", torch.ones((), dtype=dtype))
        self.register_buffer("gain", torch.ones((), dtype=dtype))
        self.register_buffer("unit_weights", torch.zeros(n_units, dtype=dtype))
        self.register_buffer("centers", torch.zeros(n_units, dtype=dtype))
        self.register_buffer("slopes", torch.ones(n_units, dtype=dtype))
        self.register_buffer("offset", torch.zeros((), dtype=dtype))
        self.register_buffer("lower", torch.full((), -torch.inf, dtype=dtype))
        self.register_buffer("upper", torch.full((), torch.inf, dtype=dtype))

    @classmethod
    @torch.no_grad()
    def from_model(cls, model: GeneralizedPrandtlIshlinskii, *, lower: float = -float("inf"),
                   upper: float = float("inf")) -> "GeneralizedPIInverse":
        """The inverse of ``model`` (its current parameters, detached), in its dtype, with
        ``g^-1`` bounded to ``[lower, upper]`` (module docstring).

        Raises:
            ValueError: the PI part's loading curve is not strictly increasing (no inverse).
        """
        widths, w, w0, a, c, b, s, off = (t.detach() for t in model.parameters_effective())
        lower = check_real(lower, "lower", allow_inf=True)
        upper = check_real(upper, "upper", allow_inf=True)
        if not lower < upper:
            raise ValueError(f"lower must be below upper, got {lower!r} and {upper!r}")
        p = prandtl_ishlinskii_inverse_parameters(widths, w, w0)
        n = int(widths.shape[0])
        inverse = cls(n, int(c.shape[0])).to(widths.dtype)
        m = int(p.widths.shape[0])
        # operators of width 0 fold into the linear weight: pad with idle plays (weight 0)
        pad = float(p.widths.max()) if m else 1.0
        inverse.widths.fill_(pad)[:m] = p.widths
        inverse.weights.zero_()[:m] = p.weights
        inverse.linear_weight.copy_(p.linear_weight)
        for name, v in (("gain", a), ("unit_weights", c), ("centers", b), ("slopes", s),
                        ("offset", off)):
            getattr(inverse, name).copy_(v)
        inverse.lower.fill_(float(lower))  # fill_ with a Python float: no float32 rounding
        inverse.upper.fill_(float(upper))
        return inverse

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        as_batched_sequence(x, "x")  # g^-1 comes first: check x before it
        check_play_state(state, x, self.widths.shape[0], "state")
        v = monotone_inverse(x, *(t.to(x.dtype) for t in (
            self.gain, self.unit_weights, self.centers, self.slopes, self.offset, self.lower,
            self.upper)))
        z = backlash(v, self.widths.to(v.dtype), y0=state)
        out = pi_output(v, z, self.weights.to(z.dtype), self.linear_weight.to(z.dtype))
        return out, z[..., -1, :]

    def streaming_step(self, dtype: torch.dtype) -> GeneralizedPIInverseStep:
        """The per-sample step with the current buffers, in ``dtype``."""
        return GeneralizedPIInverseStep(*(t.to(dtype) for t in (
            self.widths, self.weights, self.linear_weight, self.gain, self.unit_weights,
            self.centers, self.slopes, self.offset, self.lower, self.upper)))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[override]
        _check_loaded(state_dict, prefix)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return (f"n_plays={self.widths.shape[0]}, n_units={self.centers.shape[0]}, "
                f"lower={float(self.lower):.6g}, upper={float(self.upper):.6g}")


register_operator("generalized_pi_inverse", GeneralizedPIInverse, example=Example(
    lambda: GeneralizedPrandtlIshlinskii(
        torch.tensor([0.0, 0.3, 0.8], dtype=torch.float64), [0.5, 0.3, 0.2],
        linear_weight=0.5, centers=[-0.5, 0.5], slopes=[2.0, 1.0], unit_weights=[0.2, 0.1],
    ).inverse(lower=-3.0, upper=3.0),
    bad_values={"gain": 0.0, "slopes": -1.0}))
