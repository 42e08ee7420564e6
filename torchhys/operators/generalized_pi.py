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
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_bool,
    check_finite,
    check_int,
    check_same_shape,
    check_tensor,
    fitted_samples,
)
from torchhys.functional.backlash import backlash, check_play_state, play_step
from torchhys.functional.prandtl_ishlinskii import pi_output
from torchhys.identification._nnls import check_penalty
from torchhys.identification.fitting import fit_full_batch, fit_prandtl_ishlinskii
from torchhys.operator import (
    Example,
    HysteresisOperator,
    OperatorStep,
    StateBlock,
    register_operator,
)
from torchhys.operators.backlash import _inverse_softplus, _Widths
from torchhys.operators.prandtl_ishlinskii import PrandtlIshlinskii

if TYPE_CHECKING:
    from torchhys.operators.generalized_pi_inverse import GeneralizedPIInverse

__all__ = ["GeneralizedPIStep", "GeneralizedPrandtlIshlinskii", "fit_generalized_pi",
           "monotone_output"]


def monotone_output(v: Tensor, gain: Tensor, unit_weights: Tensor, centers: Tensor,
                    slopes: Tensor, offset: Tensor) -> Tensor:
    """``g(v) = gain v + sum_k c_k tanh(s_k (v - b_k)) + offset``: v (...) -> (...).

    ``gain``, ``offset``: 0-dim; ``unit_weights`` (c), ``centers`` (b), ``slopes`` (s):
    (K,), K >= 0. Strictly increasing when ``gain > 0``, ``c >= 0``, ``s > 0``. With
    ``c = 0`` (or K = 0), ``gain = 1``, ``offset = 0`` it returns v exactly. Scriptable: the
    sequence path and the step call it.
    """
    units = torch.tanh(slopes * (v.unsqueeze(-1) - centers))
    return gain * v + (units * unit_weights).sum(-1) + offset


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
        centers: centres b_k of the tanh units of g, shape (K,) (K >= 0); default
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
        y = backlash(x, widths, y0=state)
        w, w0, a, c, b, s, off = (t.to(y.dtype) for t in rest)
        return monotone_output(pi_output(x, y, w, w0), a, c, b, s, off), y[..., -1, :]

    def predictor(self, x: Tensor) -> Callable[[], Tensor]:
        """The output on a fixed input x (batch, time), zero initial state, as a closure of
        the parameters, for fitting (:func:`~torchhys.identification.fitting.fit_full_batch` calls
        it at
        every step). With fixed widths the plays are computed once and ``p`` and ``g`` are
        matrix products: about half the time of :meth:`forward` per call on 1e5 samples,
        equal to it up to rounding (forward sums in a fixed order, so that chunked calls
        equal one call; this closure does not need that)."""
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
        ``[lower, upper]`` (see :mod:`torchhys.operators.generalized_pi_inverse`).

        Raises:
            ValueError: the PI part's loading curve is not strictly increasing.
        """
        from torchhys.operators.generalized_pi_inverse import GeneralizedPIInverse

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


def fit_generalized_pi(
    x: Tensor, y: Tensor, widths: Tensor, *, units: int = 6, ridge: float = 0.0,
    adam_epochs: int = 0, lbfgs_epochs: int = 1000, lr: float = 1e-2, warmup: int = 0,
    anchor: float = 1e-6, mask: Tensor | None = None,
) -> GeneralizedPrandtlIshlinskii:
    """Fit a :class:`GeneralizedPrandtlIshlinskii` model ``y ~ g(p[x])``.

    Initialisation: ``p`` from the non-negative PI fit
    (``fit_prandtl_ishlinskii(x, y, widths, ridge=ridge, nonnegative=True)``), its play
    weights raised to at least 1% of the largest (so that none starts dead); ``g`` with
    ``units`` tanh units centred on quantiles of that fit's output, slopes ``2 / spacing``
    and weights ``0.1 spacing`` (spacing: the output's span / units), gain 1, offset 0. Then
    full-batch training of every parameter but the widths and ``w0`` on the mean squared
    error plus ``anchor * (|log a - log a_init|^2 + |log s - log s_init|^2)``
    (:func:`~torchhys.identification.fitting.fit_full_batch`: Adam, then L-BFGS). The fit sees y
    divided by
    its standard deviation over the scored samples (then ``a``, ``c_k`` and the offset are
    scaled back), so that the fit, its tolerances and the anchor mean the same in any units
    of y.

    Why ``w0`` is held and the logarithms anchored: the model is unchanged when ``p`` is
    scaled by k and ``g``'s input by 1 / k (``w, w0, b`` times k, ``a, s`` over k), and
    nearly unchanged when a unit's slope shrinks while its weight grows (it becomes a
    linear term) or when the gain vanishes and the units carry ``g``. Left free, the fit
    drifts along these directions until parameters underflow (a gain or slope of 0: no
    inverse) or the loss turns NaN; holding ``w0`` removes the first, and the anchor (small
    next to the error of a fit) stops the others.

    Args:
        x: input, (time,) or (batch, time); y: output, same shape.
        widths: full dead-band widths, (N,).
        units: tanh units of g, >= 0.
        ridge: ridge weight of the initial PI fit (e.g. from
            :func:`~torchhys.identification.fitting.select_pi_ridge`).
        adam_epochs, lbfgs_epochs, lr: as in
        :func:`~torchhys.identification.fitting.fit_full_batch`.
        warmup: samples at the start of each row left out of the initial fit, the centres of
            g and the loss (they still run the plays), to forget the zero initial state.
        anchor: weight of the penalty on the log-gain and log-slopes moving from their
            initial values (y in units of its standard deviation), >= 0 (0: none).
        mask: the scored samples, bool, the shape of ``x`` (False: left out of the initial
            fit, the centres, the scale of y and the loss, as the warm-up; the plays still run
            through them, e.g. a held-out block or a shorter row's padding); None: every
            sample (after ``warmup`` in both cases).

    Returns:
        The model, in x's dtype.

    Raises:
        TypeError, ValueError: bad input (see
        :func:`~torchhys.identification.fitting.fit_prandtl_ishlinskii`),
            y constant over the scored samples, or y that does not increase with x (the
            initial fit has no positive linear weight).
    """
    check_int(units, "units", minimum=0)
    anchor = check_penalty(anchor, "anchor")
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, xb, "y", "x")
    pi = fit_prandtl_ishlinskii(xb, yb, widths, ridge=ridge, nonnegative=True, warmup=warmup,
                                mask=mask)
    scored = fitted_samples(mask, tuple(xb.shape), warmup).to(xb.device)
    sy = float(yb[scored].std())
    if not sy > 0:
        raise ValueError("y must vary over the scored samples (after warmup)")
    w0 = float(pi.linear_weight) / sy
    if not w0 > 0:
        raise ValueError("y does not increase with x (the least-squares static gain is not "
                         "positive): a generalized PI model of increasing loops does not fit")
    with torch.no_grad():
        v = pi(xb)[0][scored] / sy
        q = (torch.arange(units, dtype=v.dtype, device=v.device) + 0.5) / max(units, 1)
        centers = torch.quantile(v, q) if units else v.new_zeros(0)
        spacing = float((v.max() - v.min()).clamp_min(1e-12)) / max(units, 1)
        weights = pi.weights.clamp_min(0.01 * float(pi.weights.max())) / sy
    model = GeneralizedPrandtlIshlinskii(
        pi.get_widths(), weights, linear_weight=w0, centers=centers,
        slopes=torch.full_like(centers, 2.0 / spacing),
        unit_weights=torch.full_like(centers, 0.1 * spacing),
    ).to(xb.device)
    log_gain, log_slopes = model.log_gain.detach().clone(), model.log_slopes.detach().clone()

    def drift() -> Tensor:
        return anchor * ((model.log_gain - log_gain).square()
                         + (model.log_slopes - log_slopes).square().sum())

    model.log_linear_weight.requires_grad_(False)
    try:
        fit_full_batch(model, xb, yb / sy, adam_epochs=adam_epochs, lbfgs_epochs=lbfgs_epochs,
                       lr=lr, warmup=warmup, penalty=drift if anchor > 0 else None,
                       mask=mask)
    finally:
        model.log_linear_weight.requires_grad_(True)
    with torch.no_grad():  # g's output back to the units of y
        model.log_gain.add_(math.log(sy))
        model.raw_unit_weights.copy_(_inverse_softplus(F.softplus(model.raw_unit_weights) * sy))
        model.offset.mul_(sy)
    return model


register_operator("generalized_pi", GeneralizedPrandtlIshlinskii, example=Example(
    # every value of the parameters is a valid model (logarithms and softplus); fixed widths
    # must be >= 0
    lambda: GeneralizedPrandtlIshlinskii(
        torch.tensor([0.0, 0.3, 0.8], dtype=torch.float64), [0.5, 0.3, 0.2],
        linear_weight=0.5, centers=[-0.5, 0.5], slopes=[2.0, 1.0], unit_weights=[0.2, 0.1]),
    bad_values={"fixed_widths": -1.0}))
