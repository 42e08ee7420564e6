"""The SISO transfer function block :class:`TransferFunction` and its DF2T step."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from torchhys._checks import as_batched_sequence
from torchhys.dynamics._common import (
    causal_rational,
    padded,
    pole_radius,
    pole_sections,
    stable_poles,
    start,
)
from torchhys.dynamics.transfer_function_matrix import TransferFunctionMatrix
from torchhys.functional.linear_filter import df2t_step, lfilter
from torchhys.step import OperatorStep, StateBlock

__all__ = ["TransferFunction", "TransferFunctionStep"]


class TransferFunctionStep(OperatorStep):
    """One DF2T step (:func:`~torchhys.functional.linear_filter.df2t_step`).

    State: ``filter`` (the ``order`` delays, 0 at the first sample). Features: the output.

    Args:
        b: numerator, (order + 1,). a: denominator without its leading 1, (order,).
    """

    def __init__(self, b: Tensor, a: Tensor) -> None:
        super().__init__()
        self.register_buffer("b", b.detach().clone())
        self.register_buffer("a", a.detach().clone())
        self.n_outputs = 1
        self.state_spec = [StateBlock("filter", int(a.shape[0]))]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        y, z = df2t_step(x, state[0], self.b, self.a)
        return y, [z]


class TransferFunction(TransferFunctionMatrix):
    """A SISO discrete-time transfer function ``B(z) / A(z)`` with poles inside radius r.

    The 1 x 1 case of :class:`~torchhys.dynamics.TransferFunctionMatrix` without its entry
    axes: the parameters, the coefficients and the state are those of one filter (``alpha``
    (sections,), ``numerator`` (order + 1,), ``coefficients()`` (order + 1,), the state
    (order,)), x (time,) or (batch, time) gives y of its shape. ``A(z)`` is a product of
    stable sections (:mod:`torchhys.dynamics`); ``B(z)`` has ``order + 1`` free coefficients
    (``b[0] = 0`` without feedthrough). The sequence path is
    :func:`~torchhys.functional.linear_filter.lfilter`; the step is one DF2T step with the
    same coefficients (bit for bit equal on the CPU kernel). Initialised with poles of
    modulus 0.5 and a DC gain of 1.

    Args:
        order: number of poles (>= 1).
        feedthrough: whether ``y[t]`` depends on ``x[t]`` (``b[0]``, the direct gain);
            False makes the block strictly proper.
        max_pole_radius: bound r on the pole moduli, in (0, 1).

    Shape:
        - x: (time,) or (batch, time)
        - state: the DF2T delays, (order,) or (batch, order); zeros if None
        - returns ``(y, state)``: y of x's shape, and the delays after the last sample.
    """

    def __init__(self, order: int = 2, *, feedthrough: bool = True,
                 max_pole_radius: float = 0.999) -> None:
        super().__init__(order, feedthrough=feedthrough, max_pole_radius=max_pole_radius)

    def _entry_shape(self) -> tuple[int, ...]:
        """No entry axes: the parameters and coefficients of one filter."""
        return ()

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        xb, squeezed = as_batched_sequence(x, "x")
        b, a = (c.to(xb.dtype) for c in self.coefficients())
        y, zf = lfilter(xb, b, a, state=start(state, xb, self.order))
        return (y[0], zf[0]) if squeezed else (y, zf)

    def streaming_step(self, dtype: torch.dtype) -> TransferFunctionStep:
        """The DF2T step with the current coefficients, in ``dtype``."""
        b, a = (c.detach().to(dtype) for c in self.coefficients())
        return TransferFunctionStep(b, a[1:])

    @classmethod
    def from_coefficients(cls, b: Sequence[float] | Tensor, a: Sequence[float] | Tensor, *,
                          feedthrough: bool = True, max_pole_radius: float | None = None
                          ) -> TransferFunction:
        """The block with ``B(z) / A(z)`` in lfilter's convention (powers of ``z^-1``).

        The order is ``max(len(a), len(b)) - 1`` (a longer ``b`` adds poles at 0). The poles
        are paired into sections (complex conjugates together, real ones in ascending order).

        Args:
            b: numerator, (nb,). a: denominator, (na,), ``a[0] != 0``.
            feedthrough: as the constructor; False needs ``b[0] = 0``.
            max_pole_radius: bound kept in training; default ``max(0.999, (1 + m) / 2)``
                for the largest pole modulus m.

        Returns:
            A float64 block whose ``coefficients()`` equal ``(b, a) / a[0]`` (zero-padded to
            ``order + 1``) to the rounding of the root finding (about 1e-15 relative).

        Raises:
            ValueError: ``a[0] = 0`` (not causal), a pole on or outside the unit circle (the
                message gives its modulus), order 0, ``b[0] != 0`` without feedthrough,
                ``max_pole_radius`` not above every pole.
        """
        bn, an = causal_rational(b, a)
        order = max(len(an), len(bn)) - 1
        if order < 1:
            raise ValueError("order = max(len(a), len(b)) - 1 must be >= 1 (a static gain has "
                             f"no dynamics), got b = {bn}, a = {an}")
        bn, an = padded(bn, an, order, feedthrough)
        poles, m = stable_poles(an)
        r = pole_radius(max_pole_radius, m)
        alpha, beta, gamma = pole_sections(poles, order, r)
        block = cls(order, feedthrough=feedthrough, max_pole_radius=r)
        with torch.no_grad():
            block.double()
            block.alpha.copy_(alpha)
            block.beta.copy_(beta)
            block.gamma.copy_(gamma)
            block.numerator.copy_(torch.from_numpy(bn))
        return block
