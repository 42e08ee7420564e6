"""A scheduled readout: hysteresis operators on the input, an affine readout whose weights
are smooth functions of measured operating conditions (a coil voltage, a supply pressure, a
temperature).

The model is ``y = sum_j sum_k W[j, k] phi_j(x) b_k(c)``: ``phi = [1, x, f_1(x), ...]`` are
the operators' features of the input (the operators do not see the conditions) and
``b = [1, P_1(c~), ...]`` a tensor-product Legendre basis of total degree ``degree`` in the
conditions, each scaled to ``c~ in [-1, 1]`` over its training range. With ``degree=0`` it is
the ordinary affine readout of the operators, the same for every condition. ``W`` is solved
by ridge-regularized least squares in float64 (:meth:`ScheduledReadout.fit`), as the model
families' readouts are; the operators' data-dependent settings are calibrated on the
training input first.

It deploys as any model (:class:`~torchhys.protocols.Conditioned`): the compensator's
``step(x_t, conditions)`` runs the operators' steps on x and this head on ``[x,
conditions..., features...]``; every export carries the conditions.
"""

# no `from __future__ import annotations`: TorchScript reads the head's class annotations
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_int,
    check_nonnegative,
    check_tensor,
    concrete,
    fitted_samples,
)
from torchhys.conditions.basis import legendre_basis, total_degree, varying_range
from torchhys.deploy.ranges import RANGES, training_ranges
from torchhys.operator import HysteresisOperator
from torchhys.step import OperatorStep

__all__ = ["ScheduledReadout"]


class _ScheduledHead(nn.Module):
    """The readout on the compensator's features ``[x, conditions..., features...]`` (batch,
    1 + n + nf) -> (batch, 1), in physical units."""

    exponents: list[list[int]]
    n: int
    degree: int

    def __init__(self, weight: Tensor, low: Tensor, high: Tensor,
                 exponents: list[list[int]], degree: int, dtype: torch.dtype) -> None:
        super().__init__()
        self.register_buffer("weight", weight.detach().to(dtype).clone())
        # c~ = c * scale + shift maps [low, high] to [-1, 1]
        scale = 2.0 / (high.double() - low.double())
        self.register_buffer("scale", scale.to(dtype))
        self.register_buffer("shift", (-1.0 - low.double() * scale).to(dtype))
        self.exponents, self.n, self.degree = exponents, int(low.numel()), degree

    def forward(self, z: Tensor) -> Tensor:
        x = z[:, :1]
        c = z[:, 1:1 + self.n] * self.scale + self.shift
        phi = torch.cat([torch.ones_like(x), x, z[:, 1 + self.n:]], 1)
        b = legendre_basis(c, self.exponents, self.degree)
        return (torch.mm(phi, self.weight) * b).sum(1, keepdim=True)

    def readout_basis(self, z: Tensor) -> Tensor:
        """The regressors ``phi_i b_j`` (batch, n_phi * n_basis), row-major as the weight
        (:class:`~torchhys.protocols.AffineReadout`)."""
        x = z[:, :1]
        c = z[:, 1:1 + self.n] * self.scale + self.shift
        phi = torch.cat([torch.ones_like(x), x, z[:, 1 + self.n:]], 1)
        b = legendre_basis(c, self.exponents, self.degree)
        return (phi.unsqueeze(2) * b.unsqueeze(1)).flatten(1)

    def readout_weights(self) -> Tensor:
        """The readout's weights, flattened row-major (n_phi * n_basis,)."""
        return self.weight.flatten()


class ScheduledReadout(nn.Module):
    """Operators on the input, an affine readout scheduled on the operating conditions.

    Args:
        operators: causal hysteresis operators (:class:`~torchhys.HysteresisOperator`) whose
            features the readout weighs; none: a memoryless model in x and the conditions.
        n_conditions: condition inputs per sample (>= 1).
        degree: total degree of the readout's polynomial in the conditions (>= 0; 0: one
            readout for every condition).
        ridge: ridge penalty of the least squares, relative to each column's mean square.

    Shapes: ``forward(x, conditions)``: x (batch, time) or (time,), conditions (batch,
    time, n_conditions) or (time, n_conditions) -> y, the shape of x.
    """

    def __init__(self, operators: Sequence[nn.Module] = (), n_conditions: int = 1, *,
                 degree: int = 2, ridge: float = 1e-9) -> None:
        super().__init__()
        ops = list(operators)
        for i, op in enumerate(ops):
            if not isinstance(op, HysteresisOperator) or not op.causal:
                raise TypeError(f"operators[{i}] must be a causal torchhys "
                                f"HysteresisOperator, got {type(op).__name__}")
        self.operators = nn.ModuleList(ops)
        self.n_conditions = check_int(n_conditions, "n_conditions", minimum=1)
        self.degree = check_int(degree, "degree", minimum=0)
        self.ridge = check_nonnegative(ridge, "ridge")
        self.exponents = total_degree(self.n_conditions, self.degree)
        n_features = 2 + sum(op.n_outputs for op in ops)
        self.register_buffer("weight", torch.zeros(n_features, len(self.exponents)))
        n = self.n_conditions
        for name in ("cond_min", "cond_max"):
            self.register_buffer(name, torch.full((n,), float("nan")))
        for name in RANGES:
            self.register_buffer(name, torch.full((), float("nan")))

    @property
    def fitted(self) -> bool:
        """Whether :meth:`fit` has run (the condition ranges are recorded)."""
        return bool(torch.isfinite(self.cond_min).all())

    def _inputs(self, x: Tensor, conditions: Tensor) -> tuple[Tensor, Tensor, bool]:
        xb, squeezed = as_batched_sequence(x, "x")
        c = check_tensor(conditions, "conditions")
        cb = c.unsqueeze(0) if squeezed else c
        want = (*xb.shape, self.n_conditions)
        if tuple(cb.shape) != want:
            raise ValueError(f"conditions must have shape {want[int(squeezed):]} (x's shape and "
                             f"{self.n_conditions} condition column(s)), got {tuple(c.shape)}")
        return xb, cb.to(xb.dtype), squeezed

    def features(self, x: Tensor) -> Tensor:
        """``[x, f_1(x), ...]`` of x (batch, time): (batch, time, 1 + operators' outputs)."""
        feats = [x.unsqueeze(-1)]
        for op in self.operators:
            f, _ = op(x)
            feats.append(f if f.dim() == 3 else f.unsqueeze(-1))
        return torch.cat(feats, -1)

    def _design(self, x: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
        """phi (batch, time, nf + 1) and the basis b (batch, time, nb) of x and c."""
        f = self.features(x)
        phi = torch.cat([torch.ones_like(f[..., :1]), f], -1)
        lo, hi = self.cond_min.to(c.dtype), self.cond_max.to(c.dtype)
        b = legendre_basis(2 * (c - lo) / (hi - lo) - 1, self.exponents, self.degree)
        return phi, b

    def forward(self, x: Tensor, conditions: Tensor) -> Tensor:
        xb, c, squeezed = self._inputs(x, conditions)
        phi, b = self._design(xb, c)
        y = ((phi @ self.weight.to(phi.dtype)) * b).sum(-1)
        return y[0] if squeezed else y

    @torch.no_grad()
    def fit(self, x: Tensor, conditions: Tensor, y: Tensor, *,
            mask: Tensor | None = None) -> "ScheduledReadout":
        """Calibrate the operators on x, record the ranges and solve the readout's weights by
        least squares on the samples of ``mask`` (bool, the shape of x; None: all).

        Raises:
            ValueError: shapes that do not match, a non-finite sample in the fitted ones, a
                constant x, y or condition (it cannot schedule anything: drop the condition).
        """
        xb, c, _ = self._inputs(x, conditions)
        yb, _ = as_batched_sequence(y, "y")
        if yb.shape != xb.shape:
            raise ValueError(f"y must have the shape of x {tuple(xb.shape)}, got "
                             f"{tuple(y.shape)}")
        m = (torch.ones_like(xb, dtype=torch.bool) if mask is None
             else fitted_samples(mask, tuple(xb.shape), 0).to(xb.device))
        if concrete(xb, c, yb):
            for name, v in (("x", xb[m]), ("conditions", c[m]), ("y", yb[m])):
                if not bool(torch.isfinite(v).all()):
                    raise ValueError(f"{name} must be finite in the fitted samples")
        xs, ys, cs = xb[m], yb[m], c[m]
        for name, v in (("x", xs), ("y", ys)):
            if v.numel() < 2 or float(v.std()) == 0.0:
                raise ValueError(f"{name} is constant (or has < 2 samples): cannot fit")
        lo, hi = varying_range(cs, "condition column {i} is constant over the fitted samples "
                                   "({value}): it cannot schedule the readout")
        self.cond_min.copy_(lo)
        self.cond_max.copy_(hi)
        for op in self.operators:
            op.calibrate(xb)
        phi, b = self._design(xb, c)
        rows = (phi.unsqueeze(-1) * b.unsqueeze(-2))[m].reshape(int(m.sum()), -1).double()
        scale = rows.square().mean(0).sqrt().clamp_min(1e-300)
        a = rows / scale
        k = a.shape[1]
        lhs = torch.cat([a, self.ridge ** 0.5 * torch.eye(k, dtype=a.dtype)], 0)
        rhs = torch.cat([ys.double(), torch.zeros(k, dtype=torch.float64)])
        # gelsd (SVD): a rank-deficient design (a play of width 0 is x) still gets the
        # least-squares solution, which gelsy's pivoted QR missed here
        sol = torch.linalg.lstsq(lhs, rhs.unsqueeze(1), driver="gelsd").solution
        w = sol.squeeze(1) / scale
        self.weight.copy_(w.reshape(self.weight.shape))
        for name, value in zip(RANGES, training_ranges(xs, ys), strict=True):
            getattr(self, name).fill_(value)
        return self

    def streaming_steps(self, dtype: torch.dtype) -> list[OperatorStep]:
        """The operators' per-sample steps in ``dtype`` (each on x alone)."""
        if not self.fitted:
            raise ValueError("ScheduledReadout is not fitted: call fit(x, conditions, y) "
                             "before streaming or export")
        return [op.streaming_step(dtype) for op in self.operators]

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        """The readout on ``[x, conditions..., features...]`` (batch, n) -> (batch, 1)."""
        return _ScheduledHead(self.weight, self.cond_min, self.cond_max, self.exponents,
                              self.degree, dtype)
