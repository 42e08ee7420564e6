"""The paper's inverse-hysteresis network (Eq. (17)) on an expanded input space."""

import copy
from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_choice,
    check_dtype_of,
    check_int,
    fitted_samples,
)
from torchhys.conditions.basis import (
    condition_products,
    scaled_conditions,
    total_degree,
    varying_range,
)
from torchhys.operator import AtomicLoad, HysteresisOperator
from torchhys.protocols import Deployable, Network
from torchhys.registry import make_operator
from torchhys.step import OperatorStep

__all__ = ["ConditionedHead", "FoldedHead", "InverseHysteresisNet"]

_ACTIVATIONS = {
    "sigmoid": nn.Sigmoid, "tanh": nn.Tanh, "relu": nn.ReLU, "gelu": nn.GELU,
    "identity": nn.Identity,
}

Operator = str | Mapping[str, Any] | HysteresisOperator
"""An operator spec of :func:`torchhys.registry.make_operator`: a registered name, a dict
``{"name": NAME, **options}`` or an operator."""


class InverseHysteresisNet(AtomicLoad, nn.Module, Network, Deployable):
    """Elementary operator(s) plus a one-hidden-layer network: ``y = W sigma(V [x, f(x)])``.

    The input is expanded with the outputs of the elementary operators (Theorem 1: the map
    ``(x, f(x)) -> IH[x]`` is one-to-one), normalized with statistics held in buffers
    (:meth:`fit_normalization`), passed through one hidden layer and a linear output, and
    de-normalized: the model takes and returns physical units. ``operator=None`` is the
    plain network of ``x`` alone (multi-valued: the baseline the paper improves on).

    Args:
        operator: an operator spec (:func:`torchhys.registry.make_operator`): a registered
            name (``"eiho"``, ``"zhao_tan"``, ...: see :data:`torchhys.registry.OPERATORS`),
            a dict ``{"name": NAME, **options}`` or a
            :class:`~torchhys.HysteresisOperator`; a list of specs (expanded input space,
            e.g. EIHOs with several ``a`` and play operators); or None.
        hidden: number of hidden units.
        activation: ``"sigmoid"`` (the paper), ``"tanh"``, ``"relu"``, ``"gelu"``, or
            ``"identity"`` (a linear readout of the features: with ``hidden=1``, an affine
            combination of the input and the operators' outputs).
        operator_kwargs: keyword arguments of the operators given by name alone (e.g.
            ``a=...``).
        n_conditions: measured operating conditions (a coil voltage, a supply pressure, a
            temperature) the network also takes, per sample (0: none). The features are then
            the products ``phi_j(x) b_k(c)`` of ``phi = [1, x, f_1(x), ...]`` and a
            tensor-product Legendre basis ``b`` of total degree ``condition_degree`` in the
            conditions (each scaled to [-1, 1] over its training range), the constant
            left out: the hidden layer sees the conditions and how they scale each feature;
            with ``activation="identity"`` and ``hidden=1`` it is the affine readout whose
            weights are polynomials in the conditions
            (:class:`~torchhys.conditions.ScheduledReadout`'s model).
            Its operators may be conditioned themselves (an operator of ``n_inputs = 1 +
            n_conditions``, e.g. :class:`~torchhys.conditions.ConditionedBacklash`, given as
            an instance): they read ``[x, conditions]``.
        condition_degree: the basis's total degree (>= 1) with conditions.

    Raises:
        ValueError: an unknown operator name, bad operator options, bad ``hidden`` or
            ``activation``.
        TypeError: a spec of another type, an operator that does not implement the
            operator protocol.

    Shapes:
        ``forward(x)``: x (time,) or (batch, time) -> y of the same shape, and the list of
        operator states; with conditions ``forward(x, conditions=c)``, c (time, n) or
        (batch, time, n).

    References:
        Eq. (17) of "A neural networks based model of inverse hysteresis" (2011).
    """

    def __init__(
        self, operator: Operator | Sequence[Operator] | None = "eiho", hidden: int = 168, *,
        activation: str = "sigmoid", operator_kwargs: dict | None = None,
        n_conditions: int = 0, condition_degree: int = 1,
    ) -> None:
        super().__init__()
        check_int(hidden, "hidden", minimum=1)
        self.n_conditions = check_int(n_conditions, "n_conditions", minimum=0)
        self.condition_degree = check_int(condition_degree, "condition_degree", minimum=1)
        self.exponents = total_degree(self.n_conditions, self.condition_degree)
        check_choice(activation, "activation", sorted(_ACTIVATIONS))
        several = isinstance(operator, (list, tuple))
        specs = [] if operator is None else list(operator) if several else [operator]
        self.operators = nn.ModuleList([
            s if self._takes_conditions(s) else
            make_operator(s, argument=f"operator[{i}]" if several else "operator",
                          **(operator_kwargs or {}) if isinstance(s, str) else {})
            for i, s in enumerate(specs)])
        n_features = 1 + sum(op.n_outputs for op in self.operators)
        if self.n_conditions:
            # the training conditions' ranges (NaN until fitted): the basis's scaling and
            # the compensator's condition clamp
            for name in ("cond_min", "cond_max"):
                self.register_buffer(name, torch.full((self.n_conditions,), float("nan")))
            n_features = (n_features + 1) * len(self.exponents) - 1
        self.register_buffer("in_mean", torch.zeros(n_features))
        self.register_buffer("in_std", torch.ones(n_features))
        self.register_buffer("out_mean", torch.zeros(()))
        self.register_buffer("out_std", torch.ones(()))
        # range of the training targets (NaN until fitted): the default command limits of
        # an exported compensator
        self.register_buffer("out_min", torch.full((), float("nan")))
        self.register_buffer("out_max", torch.full((), float("nan")))
        # range of the training input and the target's trend in it, their correlation
        # coefficient (NaN until fitted): an exported compensator clamps its input to that
        # range (widened by a margin) and, where the trend is clear, never moves its command
        # against it (torchhys.deploy.streaming)
        self.register_buffer("in_min", torch.full((), float("nan")))
        self.register_buffer("in_max", torch.full((), float("nan")))
        self.register_buffer("trend", torch.full((), float("nan")))
        self.hidden = nn.Linear(n_features, hidden)
        self.activation = _ACTIVATIONS[activation]()
        self.output = nn.Linear(hidden, 1)

    def _takes_conditions(self, op: object) -> bool:
        """Whether ``op`` is a conditioned operator of this network's conditions (a
        :class:`~torchhys.HysteresisOperator` of ``n_inputs == 1 + n_conditions``, e.g.
        :class:`~torchhys.conditions.ConditionedBacklash`): it takes ``[x, conditions]``
        (batch, time, 1 + n), and its step the compensator's ``[x, conditions]``."""
        return (self.n_conditions > 0 and isinstance(op, HysteresisOperator)
                and getattr(op, "n_inputs", 1) == 1 + self.n_conditions)

    def _op_input(self, op: nn.Module, xb: Tensor, cb: Tensor | None) -> Tensor:
        """What ``op`` reads: x (batch, time), or ``[x, conditions]`` for a conditioned one."""
        if cb is not None and self._takes_conditions(op):
            return torch.cat([xb.unsqueeze(-1), cb], -1)
        return xb

    def _conditions(self, xb: Tensor, conditions: Tensor | None, squeezed: bool) -> Tensor | None:
        """``conditions`` as (batch, time, n) in x's dtype, checked against x (batch, time)."""
        n = self.n_conditions
        if n == 0:
            if conditions is not None:
                raise ValueError("conditions given to a network without conditions "
                                 "(n_conditions=0)")
            return None
        if conditions is None:
            raise ValueError(f"conditions missing: the network takes {n} condition "
                             f"input(s) per sample, conditions (batch, time, {n})")
        if not isinstance(conditions, Tensor) or not conditions.is_floating_point():
            raise TypeError(f"conditions must be a floating-point tensor, got "
                            f"{getattr(conditions, 'dtype', type(conditions).__name__)}")
        cb = conditions.unsqueeze(0) if squeezed else conditions
        want = (*xb.shape, n)
        if tuple(cb.shape) != want:
            raise ValueError(f"conditions must have shape {want[int(squeezed):]} (x's shape "
                             f"and {n} condition column(s)), got {tuple(conditions.shape)}")
        return cb.to(xb.dtype)

    def features(
        self, x: Tensor, state: list | None = None, *,
        target: Tensor | None = None, segment_a: Tensor | None = None,
        conditions: Tensor | None = None,
    ) -> tuple[Tensor, list]:
        """Physical-unit input space ``[x, f_1(x), ...]``: (batch, time, features), states;
        with conditions, its products with their basis (see ``n_conditions``).

        Raises:
            TypeError: ``x`` (or ``target``) of a wider float dtype than the network's (a
                narrower one is widened).
            ValueError: conditions missing, given to a network without, or of another
                shape than x's with ``n_conditions`` columns."""
        xb, squeezed = as_batched_sequence(x, "x")
        cb = self._conditions(xb, conditions, squeezed)
        xb = check_dtype_of(xb, "x", self.hidden.weight.dtype, "network")
        if state is not None and len(state) != len(self.operators):
            raise ValueError(f"state must hold {len(self.operators)} states, got {len(state)}")
        yb = None if target is None else check_dtype_of(
            as_batched_sequence(target, "target")[0], "target", xb.dtype, "network")
        feats, states = [xb.unsqueeze(-1)], []
        for i, op in enumerate(self.operators):
            prev = None if state is None else state[i]
            if op.causal:
                f, s = op(self._op_input(op, xb, cb), prev)
            else:  # a non-causal operator takes the target (the paper's per-segment EIHO)
                f, s = op(xb, prev, target=yb, segment_a=segment_a)
            feats.append(f.unsqueeze(-1) if f.dim() == 2 else f)
            states.append(s)
        out = torch.cat(feats, dim=-1)
        if cb is not None:
            c = scaled_conditions(cb, self.cond_min, self.cond_max)
            out = condition_products(out, c, self.exponents, self.condition_degree)
        return out, states

    def head(self, features: Tensor) -> Tensor:
        """Network of physical-unit features (..., features) -> physical output (...)."""
        z = (features - self.in_mean) / self.in_std
        out = self.output(self.activation(self.hidden(z))).squeeze(-1)
        return out * self.out_std + self.out_mean

    def forward(
        self, x: Tensor, state: list | None = None, *,
        target: Tensor | None = None, segment_a: Tensor | None = None,
        conditions: Tensor | None = None,
    ) -> tuple[Tensor, list]:
        """Inverse-model output for ``x`` (time,) or (batch, time), continuing from ``state``
        (and the conditions (time, n) or (batch, time, n) of a network with conditions).

        ``target`` / ``segment_a`` are only used by per-segment (non-causal) EIHOs.
        """
        feats, states = self.features(x, state, target=target, segment_a=segment_a,
                                      conditions=conditions)
        y = self.head(feats)
        return (y[0] if x.dim() == 1 else y), states

    @torch.no_grad()
    def fit_normalization(self, x: Tensor, y: Tensor, *, mask: Tensor | None = None,
                          conditions: Tensor | None = None) -> None:
        """Fit the input/output normalization buffers to training data (physical units).

        Args:
            x: model input, (time,) or (batch, time).
            y: targets, same shape.
            mask: the samples the statistics are taken over, bool, the shape of ``x``
                (False: left out, e.g. a held-out block or a shorter row's padding; the
                operators still run through them); None: every sample.
            conditions: the conditions of a network with conditions, (time, n) or (batch,
                time, n); their ranges over the masked samples are recorded first
                (``cond_min``, ``cond_max``: the basis's scaling).

        Each operator's data-dependent settings are calibrated on ``x`` first
        (:meth:`~torchhys.HysteresisOperator.calibrate`, e.g. a ``threshold="auto"``).

        Raises:
            ValueError: mismatched shapes, fewer than 2 samples, a constant ``x`` or ``y``,
                a bad ``mask``; conditions missing, non-finite in the masked samples or
                constant over them (a constant condition schedules nothing).
        """
        xb, squeezed = as_batched_sequence(x, "x")
        cb = self._conditions(xb, conditions, squeezed)
        yb, _ = as_batched_sequence(y, "y")
        if yb.shape != xb.shape:
            raise ValueError(f"y must have the shape of x {tuple(xb.shape)}, got {tuple(y.shape)}")
        m = None if mask is None else fitted_samples(mask, tuple(xb.shape), 0).to(xb.device)
        if (xb.shape[-1] if m is None else int(m.sum())) < 2:
            raise ValueError(
                f"x must hold at least 2 samples to fit a normalization, got {tuple(x.shape)}"
                + ("" if m is None else f" with {int(m.sum())} in its mask")
            )
        xs, ys = (xb, yb) if m is None else (xb[m], yb[m])
        for name, v in (("x", xs), ("y", ys)):
            if float(v.std()) == 0.0:
                raise ValueError(f"{name} is constant (std 0): cannot fit a normalization")
        if cb is not None:
            cs = cb.reshape(-1, self.n_conditions) if m is None else cb[m]
            if not bool(torch.isfinite(cs).all()):
                raise ValueError("conditions must be finite in the fitted samples")
            lo, hi = varying_range(cs, "condition {i} is constant over the fitted samples "
                                   "({value}): it cannot schedule the network (drop it, or "
                                   "fit on several conditions)")
            self.cond_min.copy_(lo)
            self.cond_max.copy_(hi)
        for op in self.operators:
            op.calibrate(self._op_input(op, xb, cb))
        feats, _ = self.features(xb, target=yb, conditions=cb)
        flat = feats.reshape(-1, feats.shape[-1]) if m is None else feats[m]
        std = flat.std(dim=0)
        self.in_mean.copy_(flat.mean(dim=0))
        self.in_std.copy_(torch.where(std > 0, std, torch.ones_like(std)))
        self.out_mean.copy_(ys.mean())
        self.out_std.copy_(ys.std())
        self.out_min.copy_(ys.min())
        self.out_max.copy_(ys.max())
        self.in_min.copy_(xs.min())
        self.in_max.copy_(xs.max())
        # the correlation coefficient of x and y: its sign is the target's direction in x
        xc, yc = xs - xs.mean(), ys - ys.mean()
        self.trend.fill_(float((xc * yc).sum() / (xc.square().sum() * yc.square().sum()).sqrt()))

    def streaming_steps(self, dtype: torch.dtype) -> list[OperatorStep]:
        """The operators' per-sample steps in ``dtype`` (for
        :class:`~torchhys.deploy.streaming.StreamingCompensator`)."""
        return [op.streaming_step(dtype) for op in self.operators]

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        """The network on a step's features (batch, features) -> (batch, 1), physical units,
        with the normalization folded into its two layers (:class:`FoldedHead`); with
        conditions, on ``[x, conditions..., features...]`` (:class:`ConditionedHead`)."""
        if self.n_conditions:
            if not bool(torch.isfinite(self.cond_min).all()):
                raise ValueError("the network's condition ranges are not fitted: call "
                                 "fit_normalization(x, y, conditions=...) before streaming")
            return ConditionedHead(self, dtype)
        return FoldedHead(self, dtype)


class FoldedHead(nn.Module):
    """:meth:`InverseHysteresisNet.head` with the normalization folded into the layers.

    ``(f - mean) / std`` is folded into the hidden layer and ``out * std + mean`` into the
    output layer (in float64, then cast to ``dtype``): ``addmm``, activation, ``addmm``.
    Equal to the network up to float rounding.

    Shapes: ``forward(features)``: (batch, features) -> (batch, 1).
    """

    def __init__(self, net: InverseHysteresisNet, dtype: torch.dtype) -> None:
        super().__init__()
        self.activation = copy.deepcopy(net.activation)
        self.collapsed: bool = isinstance(net.activation, nn.Identity)
        with torch.no_grad():
            w1, b1 = net.hidden.weight.double(), net.hidden.bias.double()
            mean, std = net.in_mean.double(), net.in_std.double()
            w2, b2 = net.output.weight.double(), net.output.bias.double()
            o_mean, o_std = net.out_mean.double(), net.out_std.double()
            w1s = w1 / std
            self.register_buffer("w1t", w1s.t().contiguous().to(dtype))
            self.register_buffer("b1", (b1 - w1 @ (mean / std)).to(dtype))
            self.register_buffer("w2t", (w2 * o_std).t().contiguous().to(dtype))
            self.register_buffer("b2", (b2 * o_std + o_mean).to(dtype))

    def forward(self, features: Tensor) -> Tensor:
        h = self.activation(torch.addmm(self.b1, features, self.w1t))
        return torch.addmm(self.b2, h, self.w2t)

    def readout_basis(self, features: Tensor) -> Tensor:
        """The affine readout's regressors (:class:`~torchhys.protocols.AffineReadout`):
        ``[features, 1]`` with an identity activation (the two layers are one affine map),
        else ``[hidden activations, 1]`` (the output layer is the readout)."""
        h = features if self.collapsed else self.activation(
            torch.addmm(self.b1, features, self.w1t))
        return torch.cat([h, torch.ones_like(h[:, :1])], 1)

    def readout_weights(self) -> Tensor:
        """The readout's weights (m,) of :meth:`readout_basis` (the two layers' product and
        bias with an identity activation, computed in float64)."""
        if self.collapsed:
            w2t = self.w2t.double()
            w = torch.cat([self.w1t.double() @ w2t, self.b1.double().unsqueeze(0) @ w2t
                           + self.b2.double()], 0)
            return w.squeeze(1).to(self.w2t.dtype)
        return torch.cat([self.w2t.squeeze(1), self.b2], 0)


class ConditionedHead(nn.Module):
    """The head of a network with conditions on ``[x, conditions..., features...]`` (batch,
    1 + n + nf): the features' products with the conditions' basis, then
    :class:`FoldedHead` (the compensator gives the conditions after its clamp)."""

    exponents: list[list[int]]
    n: int
    degree: int

    def __init__(self, net: InverseHysteresisNet, dtype: torch.dtype) -> None:
        super().__init__()
        lo, hi = net.cond_min.double(), net.cond_max.double()
        scale = 2.0 / (hi - lo)  # c~ = c * scale + shift maps [lo, hi] to [-1, 1]
        self.register_buffer("scale", scale.to(dtype))
        self.register_buffer("shift", (-1.0 - lo * scale).to(dtype))
        self.exponents, self.n = net.exponents, net.n_conditions
        self.degree = net.condition_degree
        self.folded = FoldedHead(net, dtype)

    def forward(self, z: Tensor) -> Tensor:
        c = z[:, 1:1 + self.n] * self.scale + self.shift
        f = torch.cat([z[:, :1], z[:, 1 + self.n:]], 1)
        return self.folded(condition_products(f, c, self.exponents, self.degree))

    def readout_basis(self, z: Tensor) -> Tensor:
        """:meth:`FoldedHead.readout_basis` of the features' products with the conditions."""
        c = z[:, 1:1 + self.n] * self.scale + self.shift
        f = torch.cat([z[:, :1], z[:, 1 + self.n:]], 1)
        return self.folded.readout_basis(condition_products(f, c, self.exponents, self.degree))

    def readout_weights(self) -> Tensor:
        """:meth:`FoldedHead.readout_weights`."""
        return self.folded.readout_weights()
