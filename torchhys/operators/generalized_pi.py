"""Generalized Prandtl-Ishlinskii model: asymmetric, saturating hysteresis loops.

A Prandtl-Ishlinskii (PI) model with non-negative play weights, whose output passes through
a learned, strictly increasing, memoryless function ``g``::

    y = g(p),    p = w0 x + sum_i w_i play_{d_i}[x],            w0 > 0,  w_i >= 0,
    g(v) = a v + sum_k c_k tanh(s_k (v - b_k)) + offset,         a > 0,  c_k >= 0,  s_k > 0.

The PI part gives symmetric, congruent loops; ``g`` bends them (saturation, a steeper rise
than fall, an offset), which a plain PI model cannot. Every branch of ``p`` rises with slope
``>= w0`` and ``g' >= a``, so the model is strictly increasing along every branch: invertible.
With ``a = 1``, no ``c_k`` and no offset it is the PI model exactly.

This is the output-nonlinearity form of the generalized (modified) PI model: Kuhnen's
modified PI model composes a PI model with a memoryless, monotone superposition operator
(one-sided dead zones there, smooth tanh units here). The per-direction form of Al Janaideh
et al. (generalized plays with rising and falling envelope functions) is another way to make
the loops asymmetric; it is not implemented here.

Positivity: ``w0, a, s_k`` are stored as logarithms, ``w_i, c_k`` behind a softplus (a
weight given as 0 is stored as about 2e-9, as :class:`~torchhys.Backlash` stores a zero
width). Every parameter value is thus a valid, invertible model: unconstrained optimizers
(Adam, L-BFGS) train it, and a weight near 0 can grow back (a weight clamped at 0 would stay
there under L-BFGS).

References:
    K. Kuhnen, "Modeling, identification and compensation of complex hysteretic
    nonlinearities: a modified Prandtl-Ishlinskii approach", European Journal of Control
    9(4), 2003; M. Al Janaideh, S. Rakheja and C.-Y. Su, "An analytical generalized
    Prandtl-Ishlinskii model inversion for hysteresis compensation in micropositioning
    control", IEEE/ASME Transactions on Mechatronics 16(4), 2011.

**The exact inverse of a generalized Prandtl-Ishlinskii model, as an operator.**

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

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_bool,
    check_finite,
    check_int,
    check_penalty,
    check_real,
    check_same_shape,
    check_tensor,
)
from torchhys.functional.backlash import backlash, check_play_state, play_step
from torchhys.functional.generalized_pi import monotone_inverse, monotone_mse, monotone_output
from torchhys.functional.prandtl_ishlinskii import (
    pi_output,
    prandtl_ishlinskii_inverse_parameters,
)
from torchhys.operator import HysteresisOperator
from torchhys.operators.backlash import _inverse_softplus, _Widths
from torchhys.operators.prandtl_ishlinskii import PrandtlIshlinskii
from torchhys.registry import register_operator
from torchhys.step import OperatorStep, StateBlock
from torchhys.testing import Example

__all__ = ["ANALYTIC_ROWS", "GeneralizedPIInverse", "GeneralizedPIInverseStep",
           "GeneralizedPIStep", "GeneralizedPrandtlIshlinskii"]


class GeneralizedPIStep(OperatorStep):
    """Per-sample step of :class:`GeneralizedPrandtlIshlinskii`: N plays
    (:func:`~torchhys.functional.play_step`), :func:`~torchhys.functional.pi_output` and
    :func:`monotone_output`.

    State: ``plays`` (N columns, 0 at the first sample). Shapes: x (batch, 1) -> features
    (batch, 1). Args: the effective parameters (see
    :meth:`GeneralizedPrandtlIshlinskii.parameters_effective`), in the step's dtype.
    """

    def __init__(self, widths: Tensor, weights: Tensor, linear_weight: Tensor, gain: Tensor,
                 unit_weights: Tensor, centers: Tensor, slopes: Tensor, offset: Tensor) -> None:
        super().__init__()
        for name, v in (("r", 0.5 * widths), ("weights", weights),
                        ("linear_weight", linear_weight), ("gain", gain),
                        ("unit_weights", unit_weights), ("centers", centers),
                        ("slopes", slopes), ("offset", offset)):
            self.register_buffer(name, v.detach().clone())
        self.n_outputs = 1
        self.state_spec = [StateBlock("plays", int(widths.shape[0]))]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        y = play_step(x, self.r, state[0])
        p = pi_output(x, y.unsqueeze(1), self.weights, self.linear_weight)
        out = monotone_output(p, self.gain, self.unit_weights, self.centers, self.slopes,
                              self.offset)
        return out, [y]


ANALYTIC_ROWS = 10_000
"""Scored samples from which :meth:`GeneralizedPrandtlIshlinskii.mse_closure` takes the
analytic gradient."""


def _vector(value: Tensor | Sequence[float], n: int | None, name: str, dtype: torch.dtype,
            *, minimum: float | None = None, strict: bool = False) -> Tensor:
    """A finite (n,) tensor (any length if n is None), ``>= minimum`` (``>`` if strict)."""
    t = torch.as_tensor(value, dtype=dtype).detach().clone()
    if t.dim() != 1 or (n is not None and t.shape[0] != n):
        want = "(K,)" if n is None else f"({n},)"
        raise ValueError(f"{name} must have shape {want}, got shape {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} must be finite, got {t.tolist()}")
    if minimum is not None and t.numel() and bool((t <= minimum if strict else t < minimum).any()):
        raise ValueError(f"{name} must be {'>' if strict else '>='} {minimum}, got minimum "
                         f"{float(t.min()):.6g}")
    return t


def _scalar(value: float, name: str, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number, got {value!r}")
    if positive and value <= 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return float(value)


class GeneralizedPrandtlIshlinskii(_Widths, HysteresisOperator):
    """Generalized Prandtl-Ishlinskii model ``g(w0 x + sum_i w_i play_{d_i}[x])`` with a
    learned strictly increasing ``g`` (see the module docstring). All parameters but the
    widths are trainable (the widths too with ``learnable_widths``).

    Args:
        widths: full dead-band widths d_i >= 0, shape (N,).
        weights: play weights w_i >= 0, shape (N,); ones if None.
        linear_weight: w0 > 0.
        centers: centers b_k of the tanh units of g, shape (K,) (K >= 0); default
            ``linspace(-1, 1, 5)``.
        slopes: their slopes s_k > 0, shape (K,); ones if None.
        unit_weights: their weights c_k >= 0, shape (K,); 0.1 each if None.
        gain: a > 0; offset: the output offset.
        learnable_widths: make the widths trainable (kept positive by softplus).

    Shape:
        - x: (time,) or (batch, time)
        - state: play outputs before the first sample, (N,) or (batch, N); zeros if None
        - returns ``(y, state)``: y the shape of x, state the plays at the last sample;
          chunked calls equal one call.

    Raises:
        ValueError: a parameter of the wrong shape, not finite or out of range (named).
    """

    n_outputs: int = 1

    constraints = {"fixed_widths": "nonnegative", "raw_widths": "finite"}

    def __init__(
        self, widths: Tensor | Sequence[float], weights: Tensor | Sequence[float] | None = None,
        *, linear_weight: float = 1.0, centers: Tensor | Sequence[float] | None = None,
        slopes: Tensor | Sequence[float] | None = None,
        unit_weights: Tensor | Sequence[float] | None = None, gain: float = 1.0,
        offset: float = 0.0, learnable_widths: bool = False,
    ) -> None:
        super().__init__(widths, learnable=check_bool(learnable_widths, "learnable_widths"))
        n, dtype = self.n_operators, self.get_widths().dtype
        w = torch.ones(n, dtype=dtype) if weights is None else weights
        b = torch.linspace(-1.0, 1.0, 5, dtype=dtype) if centers is None else centers
        b = _vector(b, None, "centers", dtype)
        k = b.shape[0]
        s = torch.ones(k, dtype=dtype) if slopes is None else slopes
        c = torch.full((k,), 0.1, dtype=dtype) if unit_weights is None else unit_weights
        self.raw_weights = nn.Parameter(
            _inverse_softplus(_vector(w, n, "weights", dtype, minimum=0.0)))
        self.log_linear_weight = nn.Parameter(torch.tensor(
            math.log(_scalar(linear_weight, "linear_weight", positive=True)), dtype=dtype))
        self.log_gain = nn.Parameter(torch.tensor(
            math.log(_scalar(gain, "gain", positive=True)), dtype=dtype))
        self.raw_unit_weights = nn.Parameter(
            _inverse_softplus(_vector(c, k, "unit_weights", dtype, minimum=0.0)))
        self.centers = nn.Parameter(b)
        self.log_slopes = nn.Parameter(
            _vector(s, k, "slopes", dtype, minimum=0.0, strict=True).log())
        self.offset = nn.Parameter(torch.tensor(_scalar(offset, "offset"), dtype=dtype))

    def parameters_effective(self) -> tuple[Tensor, ...]:
        """``(widths, weights, linear_weight, gain, unit_weights, centers, slopes, offset)``
        as the model uses them: (N,), (N,), 0-dim, 0-dim, (K,), (K,), (K,), 0-dim."""
        return (self.get_widths(), F.softplus(self.raw_weights), self.log_linear_weight.exp(),
                self.log_gain.exp(), F.softplus(self.raw_unit_weights), self.centers,
                self.log_slopes.exp(), self.offset)

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        widths, *rest = self.parameters_effective()
        check_play_state(state, x, widths.shape[0], "state")
        y = backlash(x, widths, state=state)
        w, w0, a, c, b, s, off = (t.to(y.dtype) for t in rest)
        return monotone_output(pi_output(x, y, w, w0), a, c, b, s, off), y[..., -1, :]

    def predictor(self, x: Tensor) -> Callable[[], Tensor]:
        """The output on a fixed input x (batch, time), zero initial state, as a closure of the
        parameters, for fitting (:func:`~torchhys.identification.fitting.fit_full_batch` calls it at
        every step). With fixed widths the plays are computed once and ``p`` and ``g`` are matrix
        products: about half the time of :meth:`forward` per call on 1e5 samples, equal to it up to
        rounding (forward sums in a fixed order, so that chunked calls equal one call; this closure
        does not need that)."""
        if self.learnable:
            return lambda: self(x)[0]
        widths = self.get_widths()
        with torch.no_grad():
            z = backlash(x, widths)
        design = torch.cat([x.unsqueeze(-1), z], -1).reshape(-1, widths.shape[0] + 1)

        def predict() -> Tensor:
            w, w0, a, c, b, s, off = (t.to(design.dtype) for t in self.parameters_effective()[1:])
            p = design @ torch.cat([w0.reshape(1), w])
            units = torch.tanh(s * (p.unsqueeze(-1) - b))
            return (a * p + units @ c + off).reshape(x.shape)

        return predict

    def mse_closure(self, x: Tensor, y: Tensor, samples: Tensor) -> Callable[[], Tensor]:
        """The mean squared error against y over ``samples`` as a closure of the parameters
        (:meth:`~torchhys.HysteresisOperator.mse_closure`). From :data:`ANALYTIC_ROWS` scored
        samples on, with fixed widths, the plays are computed once and only the rows of the
        samples are kept; the loss and its gradient are
        :func:`~torchhys.functional.generalized_pi.monotone_mse` (about half the time of
        autograd through :meth:`predictor`, equal to it up to rounding). Below, autograd
        through :meth:`predictor`: the fit is non-convex, and a gradient that differs in its
        last bits can end it in another local optimum; short records keep the fits they had
        (the analytic gradient saves well under a second there)."""
        if self.learnable or int(samples.sum()) < ANALYTIC_ROWS:
            return super().mse_closure(x, y, samples)
        widths = self.get_widths()
        with torch.no_grad():
            z = backlash(x, widths)
            design = torch.cat([x.unsqueeze(-1), z], -1)[samples].contiguous()
            target = y[samples].to(design.dtype).contiguous()

        def mse() -> Tensor:
            w, w0, a, c, b, s, off = (t.to(design.dtype) for t in self.parameters_effective()[1:])
            return monotone_mse(design, target, torch.cat([w0.reshape(1), w]), a, c, b, s, off)

        return mse

    def streaming_step(self, dtype: torch.dtype) -> GeneralizedPIStep:
        """The per-sample step with the current parameters (detached), in ``dtype``."""
        return GeneralizedPIStep(*(t.detach().to(dtype) for t in self.parameters_effective()))

    def prandtl_ishlinskii(self) -> PrandtlIshlinskii:
        """Its PI part ``p`` (g left out) as a :class:`~torchhys.PrandtlIshlinskii`
        (detached parameters)."""
        widths, w, w0 = (t.detach() for t in self.parameters_effective()[:3])
        return PrandtlIshlinskii(widths.clone(), w.clone(), linear_weight=float(w0))

    def inverse(self, *, lower: float = -math.inf,
                upper: float = math.inf) -> GeneralizedPIInverse:
        """The exact inverse ``x = p^-1[g^-1(y)]`` as an operator
        (:class:`~torchhys.GeneralizedPIInverse`, detached parameters), ``g^-1`` bounded to
        ``[lower, upper]`` (see :class:`GeneralizedPIInverse`).

        Raises:
            ValueError: the PI part's loading curve is not strictly increasing.
        """

        return GeneralizedPIInverse.from_model(self, lower=lower, upper=upper)

    def bounded_inverse(self, x: Tensor, *, margin: float = 0.5,
                        pi_output: Tensor | None = None) -> GeneralizedPIInverse:
        """:meth:`inverse` with ``g^-1`` bounded to the range of the PI part's output on x
        (the training input), widened by ``margin`` times its span on each side.

        Args:
            x: the input the model was fitted on, (time,) or (batch, time).
            margin: the widening, a share of the span, >= 0.
            pi_output: the PI part's output on x (``self.prandtl_ishlinskii()(x)[0]``), when
                the caller has it already; computed if None.

        Raises:
            ValueError: a negative or non-finite margin, a ``pi_output`` not the shape of x,
                a PI part that is constant on x, or no inverse (see :meth:`inverse`).
        """
        margin = check_penalty(margin, "margin")
        if pi_output is None:
            with torch.no_grad():
                p = self.prandtl_ishlinskii()(x)[0]  # checks x
        else:
            as_batched_sequence(x, "x")
            check_tensor(pi_output, "pi_output")
            check_same_shape(pi_output, x, "pi_output", "x")
            p = check_finite(pi_output.detach(), "pi_output")
        lo, hi = float(p.min()), float(p.max())
        if not hi > lo:
            raise ValueError(f"the PI part is constant ({lo:.6g}) on x: its range gives no "
                             "bounds for g^-1")
        return self.inverse(lower=lo - margin * (hi - lo), upper=hi + margin * (hi - lo))

    def extra_repr(self) -> str:
        return f"n_plays={self.n_operators}, n_units={self.centers.shape[0]}"


register_operator("generalized_pi", GeneralizedPrandtlIshlinskii, example=Example(
    # every value of the parameters is a valid model (logarithms and softplus); fixed widths
    # must be >= 0
    lambda: GeneralizedPrandtlIshlinskii(
        torch.tensor([0.0, 0.3, 0.8], dtype=torch.float64), [0.5, 0.3, 0.2],
        linear_weight=0.5, centers=[-0.5, 0.5], slopes=[2.0, 1.0], unit_weights=[0.2, 0.1]),
    bad_values={"fixed_widths": -1.0}))


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
                   upper: float = float("inf")) -> GeneralizedPIInverse:
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
        z = backlash(v, self.widths.to(v.dtype), state=state)
        out = pi_output(v, z, self.weights.to(z.dtype), self.linear_weight.to(z.dtype))
        return out, z[..., -1, :]

    def streaming_step(self, dtype: torch.dtype) -> GeneralizedPIInverseStep:
        """The per-sample step with the current buffers, in ``dtype``."""
        return GeneralizedPIInverseStep(*(t.to(dtype) for t in (
            self.widths, self.weights, self.linear_weight, self.gain, self.unit_weights,
            self.centers, self.slopes, self.offset, self.lower, self.upper)))

    # g^-1 needs an increasing g (monotone_inverse's bracket and bisection): gain > 0, each
    # unit's weight and slope >= 0 (a slope that underflowed to 0 makes its unit constant)
    constraints = {"widths": "nonnegative", "weights": "finite", "linear_weight": "finite",
                   "gain": "positive", "unit_weights": "nonnegative", "centers": "finite",
                   "slopes": "nonnegative", "offset": "finite", "lower": "not_nan",
                   "upper": "not_nan"}

    def check_loaded(self, values: Mapping[str, Tensor], prefix: str) -> None:
        """Bounds ``lower < upper`` (``lower`` below +inf, ``upper`` above -inf)."""
        lower, upper = values["lower"], values["upper"]
        if lower.numel() == 1 and upper.numel() == 1 and not bool(lower < upper):
            raise ValueError(f"{prefix}lower must be below {prefix}upper, got "
                             f"{float(lower)!r} and {float(upper)!r}")

    def extra_repr(self) -> str:
        return (f"n_plays={self.widths.shape[0]}, n_units={self.centers.shape[0]}, "
                f"lower={float(self.lower):.6g}, upper={float(self.upper):.6g}")


register_operator("generalized_pi_inverse", GeneralizedPIInverse, example=Example(
    lambda: GeneralizedPrandtlIshlinskii(
        torch.tensor([0.0, 0.3, 0.8], dtype=torch.float64), [0.5, 0.3, 0.2],
        linear_weight=0.5, centers=[-0.5, 0.5], slopes=[2.0, 1.0], unit_weights=[0.2, 0.1],
    ).inverse(lower=-3.0, upper=3.0),
    bad_values={"gain": 0.0, "slopes": -1.0}))
