"""The MIMO transfer function block :class:`TransferFunctionMatrix` and its step."""

# no `from __future__ import annotations`: TorchScript reads the step's class annotations
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from torchhys._checks import check_int
from torchhys.dynamics._common import (
    batched_inputs,
    causal_rational,
    initial_sections,
    padded,
    pole_radius,
    pole_sections,
    radius,
    section_polynomial,
    stable_poles,
    start,
)
from torchhys.functional.linear_filter import df2t_step, lfilter
from torchhys.operator import HysteresisOperator
from torchhys.step import OperatorStep, StateBlock

__all__ = ["TransferFunctionMatrix", "TransferFunctionMatrixStep"]


class TransferFunctionMatrixStep(OperatorStep):
    """One DF2T step of every entry (:func:`~torchhys.functional.linear_filter.df2t_step`),
    then the sum over inputs.

    State: ``filter`` (the ``p * m * order`` delays, entry (i, j)'s delays at columns
    ``((i * m + j) * order, ...)``, 0 at the first sample). Features: the p outputs.

    Args:
        b: numerators, (p, m, order + 1). a: denominators without their leading 1,
            (p, m, order).

    Shape: ``forward(x, state)``: x (batch, m) (m = ``n_inputs``; (batch, 1) for the
    protocol) -> y (batch, p) and the new state.
    """

    n_inputs: int
    order: int

    def __init__(self, b: Tensor, a: Tensor) -> None:
        super().__init__()
        self.register_buffer("b", b.detach().clone())
        self.register_buffer("a", a.detach().clone())
        p, m, n = a.shape
        self.n_outputs, self.n_inputs, self.order = int(p), int(m), int(n)
        self.state_spec = [StateBlock("filter", int(p * m * n))]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        if x.shape[-1] != self.n_inputs:
            raise ValueError("x must have shape (batch, n_inputs) with n_inputs = "
                             + str(self.n_inputs) + ", got " + str(x.shape[-1]) + " columns")
        z = state[0].reshape([-1, self.n_outputs, self.n_inputs, self.order])
        y, z = df2t_step(x.reshape([-1, 1, self.n_inputs, 1]), z, self.b, self.a)
        size = self.n_outputs * self.n_inputs * self.order
        return y.squeeze(-1).sum(-1), [z.reshape([-1, size])]


class TransferFunctionMatrix(HysteresisOperator):
    """A p x m matrix of SISO transfer functions: ``y_i = sum_j H_ij(z) x_j``.

    Each entry ``H_ij = B_ij(z) / A_ij(z)`` has its own denominator, a product of stable
    sections with poles inside radius r (:mod:`torchhys.dynamics`, as
    :class:`~torchhys.dynamics.TransferFunction`), and its own ``order + 1`` free numerator
    coefficients (``b[0] = 0`` without feedthrough). Its 1 x 1 case without the entry axes is
    :class:`~torchhys.dynamics.TransferFunction` (a subclass): that block's parameter
    shapes, its (time,) -> (time,) input and output, its state and its saved state dicts stay
    those of a SISO filter, while this one's parameters carry the (p, m) entry axes and its
    output is (..., time, p) for every p and m.

    The sequence path filters all ``p * m`` entries in one
    :func:`~torchhys.functional.linear_filter.lfilter` call (one filter per row) and sums over
    the inputs; the step is one DF2T step per entry with the same coefficients. Every entry
    starts as :class:`~torchhys.dynamics.TransferFunction` ``(order)`` does (poles of modulus
    0.5, DC gain 1). With one input it is an operator of the protocol (p features); with
    several, its step takes x (batch, m) and it cannot stand where an operator is expected
    (:func:`~torchhys.operator.check_operator` names ``n_inputs``).

    Args:
        order: poles of each entry (>= 1).
        n_inputs: inputs m (>= 1).
        n_outputs: outputs p (>= 1).
        feedthrough: whether ``y[t]`` depends on ``x[t]`` (each entry's ``b[0]``).
        max_pole_radius: bound r on the pole moduli, in (0, 1).

    Shape:
        - x: (time,) or (batch, time) with one input; (time, m) or (batch, time, m) with m
        - state: the DF2T delays, (p, m, order) or (batch, p, m, order); zeros if None
        - returns ``(y, state)``: y (..., time, p), and the delays after the last sample.

    Raises:
        ValueError: x without the ``n_inputs`` columns, NaN or inf in x or the state, a state
            of the wrong shape.
    """

    def __init__(self, order: int = 2, n_inputs: int = 1, n_outputs: int = 1, *,
                 feedthrough: bool = True, max_pole_radius: float = 0.999) -> None:
        super().__init__()
        self.order = check_int(order, "order", minimum=1)
        self.n_inputs = check_int(n_inputs, "n_inputs", minimum=1)
        self.n_outputs = check_int(n_outputs, "n_outputs", minimum=1)
        self.feedthrough = bool(feedthrough)
        self.max_pole_radius = radius(max_pole_radius, "max_pole_radius")
        entries = self._entry_shape()
        sections = initial_sections(order, self.max_pole_radius, torch.get_default_dtype())
        alpha, beta, gamma = (s.expand(*entries, -1).clone() for s in sections)
        self.alpha = nn.Parameter(alpha)
        self.beta = nn.Parameter(beta)
        self.gamma = nn.Parameter(gamma)
        mask = torch.ones(order + 1)
        mask[0] = float(self.feedthrough)
        self.register_buffer("numerator_mask", mask)
        with torch.no_grad():
            gain = self.denominator().sum(-1)
        self.numerator = nn.Parameter(torch.zeros(*entries, order + 1))
        with torch.no_grad():
            self.numerator[..., 0 if self.feedthrough else 1] = gain

    def _entry_shape(self) -> tuple[int, ...]:
        """The entry axes of the parameters and coefficients: ``(p, m)``."""
        return (self.n_outputs, self.n_inputs)

    def denominator(self) -> Tensor:
        """``a`` (p, m, order + 1) with ``a[..., 0] = 1``: each entry's product of sections."""
        return section_polynomial(self.alpha, self.beta, self.gamma, self.max_pole_radius)

    def coefficients(self) -> tuple[Tensor, Tensor]:
        """``(b, a)``, both (p, m, order + 1), ``a[..., 0] = 1``: entry (i, j) is
        ``H_ij`` in scipy's lfilter convention."""
        return self.numerator * self.numerator_mask, self.denominator()

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        xb, squeezed = batched_inputs(x, self.n_inputs)  # (batch, time, m)
        p, m, n = self.n_outputs, self.n_inputs, self.order
        batch, T = xb.shape[:2]
        b, a = (c.to(xb.dtype).reshape(p * m, n + 1) for c in self.coefficients())
        rows = xb.mT.unsqueeze(1).expand(batch, p, m, T).reshape(batch, p * m, T)
        zi = start(state, xb, (p, m, n))
        y, zf = lfilter(rows, b, a, state=None if zi is None else zi.reshape(batch, p * m, n))
        y = y.reshape(batch, p, m, T).sum(2).mT  # (batch, time, p)
        zf = zf.reshape(batch, p, m, n)
        return (y[0], zf[0]) if squeezed else (y, zf)

    def streaming_step(self, dtype: torch.dtype) -> TransferFunctionMatrixStep:
        """The DF2T steps with the current coefficients, in ``dtype``."""
        b, a = (c.detach().to(dtype) for c in self.coefficients())
        return TransferFunctionMatrixStep(b, a[..., 1:])

    @classmethod
    def from_coefficients(cls, coefficients: Sequence[Sequence[tuple[object, object]]], *,
                          feedthrough: bool = True, max_pole_radius: float | None = None
                          ) -> "TransferFunctionMatrix":
        """The block with ``H_ij = B_ij(z) / A_ij(z)`` in lfilter's convention.

        The order is the largest ``max(len(a), len(b)) - 1`` of the entries; shorter entries
        get poles at 0 (zero-padded ``a``), and each entry's poles are paired into sections as
        in :meth:`TransferFunction.from_coefficients`.

        Args:
            coefficients: p rows of m pairs ``(b, a)`` (1-D sequences, arrays or tensors;
                ``a[0] != 0``): ``coefficients[i][j]`` is the entry from input j to output i.
            feedthrough: as the constructor; False needs every ``b[0] = 0``.
            max_pole_radius: bound kept in training; default ``max(0.999, (1 + m) / 2)`` for
                the largest pole modulus m of all entries.

        Returns:
            A float64 block whose ``coefficients()`` equal each ``(b, a) / a[0]``
            (zero-padded to ``order + 1``) to the rounding of the root finding.

        Raises:
            ValueError: not p rows of m ``(b, a)`` pairs, ``a[0] = 0`` (not causal), a pole on
                or outside the unit circle, order 0 (every entry a static gain), ``b[0] != 0``
                without feedthrough, ``max_pole_radius`` not above every pole; the message
                names the entry ``H[i][j]``.
        """
        rows = _entries(coefficients)
        p, m = len(rows), len(rows[0])
        raw = [[causal_rational(b, a, f"H[{i}][{j}]: ") for j, (b, a) in enumerate(row)]
               for i, row in enumerate(rows)]
        order = max(max(len(b), len(a)) for row in raw for b, a in row) - 1
        if order < 1:
            raise ValueError("order = max(len(a), len(b)) - 1 over the entries must be >= 1 "
                             "(static gains have no dynamics)")
        norm = [[padded(b, a, order, feedthrough, f"H[{i}][{j}]: ")
                 for j, (b, a) in enumerate(row)] for i, row in enumerate(raw)]
        poles = [[stable_poles(a, f"H[{i}][{j}]: ")[0] for j, (_, a) in enumerate(row)]
                 for i, row in enumerate(norm)]
        largest = max(float(np.abs(e).max()) for row in poles for e in row)
        r = pole_radius(max_pole_radius, largest)
        block = cls(order, m, p, feedthrough=feedthrough, max_pole_radius=r).double()
        with torch.no_grad():
            for i in range(p):
                for j in range(m):
                    alpha, beta, gamma = pole_sections(poles[i][j], order, r)
                    block.alpha[i, j] = alpha
                    block.beta[i, j] = beta
                    block.gamma[i, j] = gamma
                    block.numerator[i, j] = torch.from_numpy(norm[i][j][0])
        return block


def _entries(coefficients: object) -> list[list[tuple[object, object]]]:
    """``coefficients`` as p rows of m ``(b, a)`` pairs; ValueError naming what is wrong."""
    shape = "p rows of m (b, a) pairs, e.g. [[(b00, a00), (b01, a01)]]"
    if isinstance(coefficients, (str, bytes, Tensor, np.ndarray)) or not isinstance(
            coefficients, Sequence) or len(coefficients) == 0:
        raise ValueError(f"coefficients must be {shape}, got {type(coefficients).__name__}")
    rows = []
    for i, row in enumerate(coefficients):
        if not isinstance(row, Sequence) or isinstance(row, (str, bytes)) or len(row) == 0:
            raise ValueError(f"coefficients must be {shape}: row {i} is not a non-empty "
                             f"sequence of pairs")
        entries = []
        for j, pair in enumerate(row):
            if isinstance(pair, (str, bytes)) or not isinstance(pair, Sequence) or len(pair) != 2:
                raise ValueError(f"coefficients must be {shape}: entry [{i}][{j}] is not a "
                                 f"(b, a) pair")
            entries.append((pair[0], pair[1]))
        if rows and len(entries) != len(rows[0]):
            raise ValueError(f"coefficients must be {shape}: row {i} has {len(entries)} "
                             f"entries, row 0 has {len(rows[0])}")
        rows.append(entries)
    return rows
