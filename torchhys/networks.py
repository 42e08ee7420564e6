"""The paper's inverse-hysteresis network (Eq. (17)) on an expanded input space."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence
from torchhys.eiho import EIHO, ZhaoTanOperator

__all__ = ["InverseHysteresisNet"]

_ACTIVATIONS = {"sigmoid": nn.Sigmoid, "tanh": nn.Tanh, "relu": nn.ReLU, "gelu": nn.GELU}
_OPERATORS = {"eiho": EIHO, "zhao_tan": ZhaoTanOperator}

Operator = str | nn.Module


def _make_operator(spec: Operator, kwargs: dict) -> nn.Module:
    if isinstance(spec, nn.Module):
        return spec
    if spec not in _OPERATORS:
        raise ValueError(
            f"operator must be one of {sorted(_OPERATORS)}, None, a module or a list of them, "
            f"got {spec!r}"
        )
    return _OPERATORS[spec](**kwargs)


class InverseHysteresisNet(nn.Module):
    """Elementary operator(s) plus a one-hidden-layer network: ``y = W sigma(V [x, f(x)])``.

    The input is expanded with the outputs of the elementary operators (Theorem 1: the map
    ``(x, f(x)) -> IH[x]`` is one-to-one), normalized with statistics held in buffers
    (:meth:`fit_normalization`), passed through one hidden layer and a linear output, and
    de-normalized: the model takes and returns physical units. ``operator=None`` is the
    plain network of ``x`` alone (multi-valued: the baseline the paper improves on).

    Args:
        operator: ``"eiho"``, ``"zhao_tan"``, a module with ``forward(x, state) -> (f, state)``
            (``f`` (batch, time) or (batch, time, n)), a list of those (expanded input space,
            e.g. EIHOs with several ``a`` and play operators), or None.
        hidden: number of hidden units.
        activation: ``"sigmoid"`` (the paper), ``"tanh"``, ``"relu"`` or ``"gelu"``.
        operator_kwargs: keyword arguments of string-specified operators (e.g. ``a=...``).

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
        if isinstance(hidden, bool) or not isinstance(hidden, int) or hidden < 1:
            raise ValueError(f"hidden must be a positive int, got {hidden!r}")
        if activation not in _ACTIVATIONS:
            raise ValueError(
                f"activation must be one of {sorted(_ACTIVATIONS)}, got {activation!r}"
            )
        specs = [] if operator is None else (
            list(operator) if isinstance(operator, (list, tuple)) else [operator]
        )
        self.operators = nn.ModuleList([_make_operator(s, operator_kwargs or {}) for s in specs])
        n_features = 1 + sum(
            int(getattr(op, "n_outputs", getattr(op, "n_operators", 1))) for op in self.operators
        )
        self.register_buffer("in_mean", torch.zeros(n_features))
        self.register_buffer("in_std", torch.ones(n_features))
        self.register_buffer("out_mean", torch.zeros(()))
        self.register_buffer("out_std", torch.ones(()))
        # range of the training targets (NaN until fitted): the default command limits of
        # an exported compensator
        self.register_buffer("out_min", torch.full((), float("nan")))
        self.register_buffer("out_max", torch.full((), float("nan")))
        self.hidden = nn.Linear(n_features, hidden)
        self.activation = _ACTIVATIONS[activation]()
        self.output = nn.Linear(hidden, 1)

    def features(
        self, x: Tensor, state: list | None = None, *,
        target: Tensor | None = None, segment_a: Tensor | None = None,
    ) -> tuple[Tensor, list]:
        """Physical-unit input space ``[x, f_1(x), ...]``: (batch, time, features), states."""
        xb, _ = as_batched_sequence(x, "x")
        if state is not None and len(state) != len(self.operators):
            raise ValueError(f"state must hold {len(self.operators)} states, got {len(state)}")
        yb = None if target is None else as_batched_sequence(target, "target")[0]
        feats, states = [xb.unsqueeze(-1)], []
        for i, op in enumerate(self.operators):
            prev = None if state is None else state[i]
            if getattr(op, "per_segment", False):
                f, s = op(xb, prev, target=yb, segment_a=segment_a)
            else:
                f, s = op(xb, prev)
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

    def _load_from_state_dict(
        self, state_dict: dict, prefix: str, *args: object, **kwargs: object
    ) -> None:
        # state dicts saved before the target range was recorded: keep it unknown (NaN)
        for name in ("out_min", "out_max"):
            state_dict.setdefault(prefix + name, torch.full((), float("nan")))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @torch.no_grad()
    def fit_normalization(self, x: Tensor, y: Tensor) -> None:
        """Fit the input/output normalization buffers to training data (physical units).

        Args:
            x: model input, (time,) or (batch, time).
            y: targets, same shape.

        Operators with an uncalibrated ``threshold="auto"`` are calibrated on ``x`` first.

        Raises:
            ValueError: mismatched shapes, fewer than 2 samples, a constant ``x`` or ``y``.
        """
        xb, _ = as_batched_sequence(x, "x")
        yb, _ = as_batched_sequence(y, "y")
        if yb.shape != xb.shape:
            raise ValueError(f"y must have the shape of x {tuple(xb.shape)}, got {tuple(y.shape)}")
        if xb.shape[-1] < 2:
            raise ValueError(
                f"x must hold at least 2 samples to fit a normalization, got {tuple(x.shape)}"
            )
        for name, v in (("x", xb), ("y", yb)):
            if float(v.std()) == 0.0:
                raise ValueError(f"{name} is constant (std 0): cannot fit a normalization")
        for op in self.operators:
            th = getattr(op, "threshold", None)
            if isinstance(th, Tensor) and bool(torch.isnan(th).any()):
                op.calibrate_threshold(xb)
        feats, _ = self.features(xb, target=yb)
        flat = feats.reshape(-1, feats.shape[-1])
        std = flat.std(dim=0)
        self.in_mean.copy_(flat.mean(dim=0))
        self.in_std.copy_(torch.where(std > 0, std, torch.ones_like(std)))
        self.out_mean.copy_(yb.mean())
        self.out_std.copy_(yb.std())
        self.out_min.copy_(yb.min())
        self.out_max.copy_(yb.max())
