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
from torchhys.operator import AtomicLoad, HysteresisOperator
from torchhys.protocols import Deployable, Network
from torchhys.registry import make_operator
from torchhys.step import OperatorStep

__all__ = ["InverseHysteresisNet"]

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

    Raises:
        ValueError: an unknown operator name, bad operator options, bad ``hidden`` or
            ``activation``.
        TypeError: a spec of another type, an operator that does not implement the
            operator protocol.

    Shapes:
        ``forward(x)``: x (time,) or (batch, time) -> y of the same shape, and the list of
        operator states.

    References:
        Eq. (17) of "A neural networks based model of inverse hysteresis" (2011).
    """

    def __init__(
        self, operator: Operator | Sequence[Operator] | None = "eiho", hidden: int = 168, *,
        activation: str = "sigmoid", operator_kwargs: dict | None = None,
    ) -> None:
        super().__init__()
        check_int(hidden, "hidden", minimum=1)
        check_choice(activation, "activation", sorted(_ACTIVATIONS))
        several = isinstance(operator, (list, tuple))
        specs = [] if operator is None else list(operator) if several else [operator]
        self.operators = nn.ModuleList([
            make_operator(s, argument=f"operator[{i}]" if several else "operator",
                          **(operator_kwargs or {}) if isinstance(s, str) else {})
            for i, s in enumerate(specs)])
        n_features = 1 + sum(op.n_outputs for op in self.operators)
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

    def features(
        self, x: Tensor, state: list | None = None, *,
        target: Tensor | None = None, segment_a: Tensor | None = None,
    ) -> tuple[Tensor, list]:
        """Physical-unit input space ``[x, f_1(x), ...]``: (batch, time, features), states.

        Raises:
            TypeError: ``x`` (or ``target``) of a wider float dtype than the network's (a
                narrower one is widened)."""
        xb, _ = as_batched_sequence(x, "x")
        xb = check_dtype_of(xb, "x", self.hidden.weight.dtype, "network")
        if state is not None and len(state) != len(self.operators):
            raise ValueError(f"state must hold {len(self.operators)} states, got {len(state)}")
        yb = None if target is None else check_dtype_of(
            as_batched_sequence(target, "target")[0], "target", xb.dtype, "network")
        feats, states = [xb.unsqueeze(-1)], []
        for i, op in enumerate(self.operators):
            prev = None if state is None else state[i]
            if op.causal:
                f, s = op(xb, prev)
            else:  # a non-causal operator takes the target (the paper's per-segment EIHO)
                f, s = op(xb, prev, target=yb, segment_a=segment_a)
            feats.append(f.unsqueeze(-1) if f.dim() == 2 else f)
            states.append(s)
        return torch.cat(feats, dim=-1), states

    def head(self, features: Tensor) -> Tensor:
        """Network of physical-unit features (..., features) -> physical output (...)."""
        z = (features - self.in_mean) / self.in_std
        out = self.output(self.activation(self.hidden(z))).squeeze(-1)
        return out * self.out_std + self.out_mean

    def forward(
        self, x: Tensor, state: list | None = None, *,
        target: Tensor | None = None, segment_a: Tensor | None = None,
    ) -> tuple[Tensor, list]:
        """Inverse-model output for ``x`` (time,) or (batch, time), continuing from ``state``.

        ``target`` / ``segment_a`` are only used by per-segment (non-causal) EIHOs.
        """
        feats, states = self.features(x, state, target=target, segment_a=segment_a)
        y = self.head(feats)
        return (y[0] if x.dim() == 1 else y), states

    @torch.no_grad()
    def fit_normalization(self, x: Tensor, y: Tensor, *, mask: Tensor | None = None) -> None:
        """Fit the input/output normalization buffers to training data (physical units).

        Args:
            x: model input, (time,) or (batch, time).
            y: targets, same shape.
            mask: the samples the statistics are taken over, bool, the shape of ``x``
                (False: left out, e.g. a held-out block or a shorter row's padding; the
                operators still run through them); None: every sample.

        Each operator's data-dependent settings are calibrated on ``x`` first
        (:meth:`~torchhys.HysteresisOperator.calibrate`, e.g. a ``threshold="auto"``).

        Raises:
            ValueError: mismatched shapes, fewer than 2 samples, a constant ``x`` or ``y``,
                a bad ``mask``.
        """
        xb, _ = as_batched_sequence(x, "x")
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
        for op in self.operators:
            op.calibrate(xb)
        feats, _ = self.features(xb, target=yb)
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
        with the normalization folded into its two layers (:class:`FoldedHead`)."""
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
