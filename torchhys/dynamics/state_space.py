"""The state-space block :class:`StateSpace` (one or several inputs) and its step."""

# no `from __future__ import annotations`: TorchScript reads the step's class annotations
import math

import numpy as np
import torch
from torch import Tensor, nn

from torchhys._checks import check_int
from torchhys.dynamics._common import as_float64, batched_inputs, radius, start
from torchhys.functional.linear_filter import state_space, state_space_step
from torchhys.operator import HysteresisOperator
from torchhys.step import OperatorStep, StateBlock

__all__ = ["StateSpace", "StateSpaceStep"]


class StateSpaceStep(OperatorStep):
    """One state-space step (:func:`~torchhys.functional.linear_filter.state_space_step`).

    State: ``state`` (n columns, 0 at the first sample). Features: the p outputs.

    Args:
        A: (n, n). B: (n,) with one input, (n, m) with m. C: (p, n). D: (p,) or (p, m).

    Shape: ``forward(x, state)``: x (batch, m) (m = ``n_inputs``; (batch, 1) for the
    protocol) -> y (batch, p) and the new state.
    """

    n_inputs: int

    def __init__(self, A: Tensor, B: Tensor, C: Tensor, D: Tensor) -> None:
        super().__init__()
        for name, m in (("A", A), ("B", B), ("C", C), ("D", D)):
            self.register_buffer(name, m.detach().clone())
        self.n_inputs = 1 if B.dim() == 1 else int(B.shape[1])
        self.n_outputs = int(C.shape[0])
        self.state_spec = [StateBlock("state", int(A.shape[0]))]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        if x.shape[-1] != self.n_inputs:
            raise ValueError("x must have shape (batch, n_inputs) with n_inputs = "
                             + str(self.n_inputs) + ", got " + str(x.shape[-1]) + " columns")
        y, s = state_space_step(x, state[0], self.A, self.B, self.C, self.D)
        return y, [s]


def _contractive(A: np.ndarray) -> np.ndarray:
    """L with ``P = L L^T`` solving ``P - A^T P A = I``: in the coordinates ``L^T s`` the
    matrix ``L^T A L^-T`` has spectral norm below 1 (A stable)."""
    n = A.shape[0]
    P = np.linalg.solve(np.eye(n * n) - np.kron(A.T, A.T), np.eye(n).ravel()).reshape(n, n)
    return np.linalg.cholesky(0.5 * (P + P.T))


class StateSpace(HysteresisOperator):
    """``s[t+1] = A s[t] + B x[t]``, ``y[t] = C s[t] + D x[t]``, with ``||A||_2 <= r < 1``.

    ``A = r W / max(1, ||W||_2)`` (:mod:`torchhys.dynamics`); ``B``, ``C``, ``D`` are free
    (``D = 0`` without feedthrough). ``n_inputs`` inputs (one: the operator's ``x``; several:
    a MIMO block, not an operator of the protocol, whose per-sample step takes x (batch, m)),
    ``n_outputs`` outputs. The sequence path is
    :func:`~torchhys.functional.linear_filter.state_space` (a linear recurrence, no loop over
    samples in Python).

    Args:
        n_states: state dimension n (>= 1).
        n_outputs: outputs p (>= 1).
        n_inputs: inputs m (>= 1). With one, B is (n,) and D (p,); with m > 1, B is (n, m)
            and D (p, m).
        feedthrough: learn the direct gain D; False fixes ``D = 0``.
        max_norm: bound r on ``||A||_2``, in (0, 1).

    Shape:
        - x: (time,) or (batch, time) with one input; (time, m) or (batch, time, m) with m
        - state: (n,) or (batch, n); zeros if None
        - returns ``(y, state)``: y (..., time, p), and the state after the last sample.

    Raises:
        ValueError: x without the ``n_inputs`` columns, NaN or inf in x or the state, a state
            of the wrong shape.

    References:
        ``scipy.signal.dlsim`` (the same convention).
    """

    def __init__(self, n_states: int = 2, n_outputs: int = 1, *, n_inputs: int = 1,
                 feedthrough: bool = True, max_norm: float = 0.999) -> None:
        super().__init__()
        n = check_int(n_states, "n_states", minimum=1)
        self.n_outputs = check_int(n_outputs, "n_outputs", minimum=1)
        self.n_inputs = m = check_int(n_inputs, "n_inputs", minimum=1)
        self.max_norm = radius(max_norm, "max_norm")
        self.W = nn.Parameter(0.5 * torch.randn(n, n) / math.sqrt(n))
        self.B = nn.Parameter(torch.randn((n,) if m == 1 else (n, m)) / math.sqrt(n))
        self.C = nn.Parameter(torch.randn(n_outputs, n) / math.sqrt(n))
        d_shape = (n_outputs,) if m == 1 else (n_outputs, m)
        if feedthrough:
            self.D = nn.Parameter(torch.zeros(d_shape))
        else:
            self.register_buffer("D", torch.zeros(d_shape))

    def matrices(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(A, B, C, D)``: (n, n), (n,) or (n, m), (p, n), (p,) or (p, m)."""
        norm = torch.linalg.matrix_norm(self.W, ord=2)
        return self.max_norm * self.W / norm.clamp_min(1.0), self.B, self.C, self.D

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        xb, squeezed = batched_inputs(x, self.n_inputs)
        if self.n_inputs == 1:
            xb = xb.squeeze(-1)
        A, B, C, D = (m.to(xb.dtype) for m in self.matrices())
        y, s = state_space(xb, A, B, C, D, state=start(state, xb, A.shape[0]))
        return (y[0], s[0]) if squeezed else (y, s)

    def streaming_step(self, dtype: torch.dtype) -> StateSpaceStep:
        """The state-space step with the current matrices, in ``dtype``."""
        return StateSpaceStep(*(m.detach().to(dtype) for m in self.matrices()))

    @classmethod
    def from_matrices(cls, A: Tensor | np.ndarray, B: Tensor | np.ndarray,
                      C: Tensor | np.ndarray, D: Tensor | np.ndarray | None = None, *,
                      max_norm: float | None = None) -> "StateSpace":
        """A float64 block with the given (stable) matrices.

        Where ``||A||_2 >= 1`` the state is changed to coordinates ``L^T s`` in which A is a
        contraction (``P = L L^T`` solves ``P - A^T P A = I``): outputs are unchanged, the
        state is in the new coordinates.

        Args:
            A: (n, n). B: (n,) or (n, 1) for one input; (n, m) for m > 1 inputs (the
                number of inputs is B's column count). C: (p, n). D: (p,) or (p, 1) for one
                input, (p, m) for m; zeros if None.
            max_norm: bound kept in training; default ``max(0.999, (1 + ||A||_2) / 2)``.

        Raises:
            ValueError: wrong shapes, non-finite entries, an eigenvalue of A on or outside the
                unit circle (the message gives its modulus).
        """
        A = as_float64(A, "A", 2)
        n = A.shape[0]
        B = as_float64(B, "B")
        m = B.shape[1] if B.ndim == 2 else 1
        C = as_float64(C, "C", 2)
        p = C.shape[0]
        if m == 1:
            B = B.reshape(-1)
            D = np.zeros(p) if D is None else as_float64(D, "D").reshape(-1)
            if (A.shape != (n, n) or B.shape != (n,) or C.shape != (p, n)
                    or D.shape != (p,)):
                raise ValueError(f"A, B, C, D must have shapes (n, n), (n,), (p, n), (p,), got "
                                 f"{A.shape}, {B.shape}, {C.shape}, {D.shape}")
        else:
            D = np.zeros((p, m)) if D is None else as_float64(D, "D")
            if (A.shape != (n, n) or B.shape != (n, m) or C.shape != (p, n)
                    or D.shape != (p, m)):
                raise ValueError(f"A, B, C, D must have shapes (n, n), (n, m), (p, n), (p, m) "
                                 f"with m = {m} inputs (B's columns), got {A.shape}, "
                                 f"{B.shape}, {C.shape}, {D.shape}")
        rho = float(np.abs(np.linalg.eigvals(A)).max())
        if rho >= 1:
            raise ValueError(f"A is not stable: it has an eigenvalue of magnitude {rho:.6g}; "
                             "eigenvalues must lie strictly inside the unit circle")
        if np.linalg.norm(A, 2) >= 1:
            L = _contractive(A)
            A, B, C = L.T @ A @ np.linalg.inv(L.T), L.T @ B, C @ np.linalg.inv(L.T)
        norm = float(np.linalg.norm(A, 2))
        r = max(0.999, (1 + norm) / 2) if max_norm is None else radius(max_norm, "max_norm")
        if r < norm:
            raise ValueError(f"max_norm must be at least ||A||_2 = {norm:.6g}, got {r!r}")
        block = cls(n, p, n_inputs=m, max_norm=r).double()
        with torch.no_grad():
            for name, v in (("W", A / r), ("B", B), ("C", C), ("D", D)):
                getattr(block, name).copy_(torch.from_numpy(np.ascontiguousarray(v)))
        return block
