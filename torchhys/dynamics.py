"""Linear dynamic blocks, stable by construction: a transfer function and a state-space model.

Both are operators of the protocol (:mod:`torchhys.operator`): they train inside an
:class:`~torchhys.InverseHysteresisNet`, stream through the
:class:`~torchhys.streaming.StreamingCompensator` and export, with a per-sample step that
calls the same maths as the sequence path (:mod:`torchhys.functional.linear_filter`).

Stable parametrisations (poles strictly inside a circle of radius ``r < 1`` for every value
of the parameters):

- :class:`TransferFunction`: the denominator is a product of second-order sections
  ``1 + a1 z^-1 + a2 z^-2`` (and one first-order section for an odd order). Each section lies
  in the stability triangle scaled to radius r: ``c2 = tanh(alpha)``,
  ``c1 = (1 + c2) tanh(beta)``, ``a1 = r c1``, ``a2 = r^2 c2``; every real or complex pole
  pair of modulus below r is reached. The numerator is free.
- :class:`StateSpace`: ``A = r W / max(1, ||W||_2)``, so ``||A||_2 <= r`` (a contraction:
  spectral radius below r). Every stable system has such a realisation
  (:meth:`StateSpace.from_matrices` changes coordinates where ``||A||_2 >= 1``).

References:
    A. V. Oppenheim and R. W. Schafer, Discrete-Time Signal Processing, 3rd ed., 2010,
    Secs. 6.3-6.5 (cascade of second-order sections, transposed forms); E. I. Jury, Theory
    and Application of the z-Transform Method, 1964 (the stability triangle);
    ``scipy.signal.lfilter`` and ``scipy.signal.dlsim`` (the conventions).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence, check_finite, check_floating, check_int
from torchhys.functional.linear_filter import df2t_step, lfilter, state_space, state_space_step
from torchhys.operator import HysteresisOperator, OperatorStep, StateBlock, register_operator

__all__ = ["StateSpace", "StateSpaceStep", "TransferFunction", "TransferFunctionStep"]


def _radius(value: float, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value < 1:
        raise ValueError(f"{name} must be a float in (0, 1), got {value!r}")
    return float(value)


def _start(state: Tensor | None, xb: Tensor, n: int) -> Tensor | None:
    """The carried state as (batch, n) in x's dtype: None, (n,) or (batch, n)."""
    if state is None:
        return None
    if not isinstance(state, Tensor):
        raise TypeError(f"state must be a torch.Tensor or None, got {type(state).__name__}")
    check_floating(state, "state")
    B = xb.shape[0]
    if state.shape not in (torch.Size([n]), torch.Size([B, n])):
        raise ValueError(f"state must have shape ({n},) or ({B}, {n}) for batch {B}, got "
                         f"shape {tuple(state.shape)}")
    check_finite(state, "state")
    return state.to(xb.dtype).expand(B, n)


def _as_float64(v: object, name: str, dims: int | None = None) -> np.ndarray:
    """``v`` (a tensor, array or sequence) as a float64 array; ``dims`` dimensions if given."""
    arr = np.asarray(v.detach().cpu() if isinstance(v, Tensor) else v, dtype=np.float64)
    if (dims is not None and arr.ndim != dims) or arr.size == 0:
        want = "non-empty" if dims is None else f"non-empty with {dims} dimension(s)"
        raise ValueError(f"{name} must be {want}, got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite, got {arr}")
    return arr


# --- transfer function -------------------------------------------------------------------------


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


def _section_parameters(a1: Tensor, a2: Tensor, r: float) -> tuple[Tensor, Tensor]:
    """(alpha, beta) of sections ``1 + a1 z^-1 + a2 z^-2`` with poles inside radius r."""
    c2 = a2 / r**2
    return torch.atanh(c2), torch.atanh(a1 / r / (1 + c2))


class TransferFunction(HysteresisOperator):
    """A SISO discrete-time transfer function ``B(z) / A(z)`` with poles inside radius r.

    ``A(z)`` is a product of stable sections (module docstring); ``B(z)`` has ``order + 1``
    free coefficients (``b[0] = 0`` without feedthrough). The sequence path is
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

    n_outputs = 1

    def __init__(self, order: int = 2, *, feedthrough: bool = True,
                 max_pole_radius: float = 0.999) -> None:
        super().__init__()
        self.order = check_int(order, "order", minimum=1)
        self.feedthrough = bool(feedthrough)
        self.max_pole_radius = _radius(max_pole_radius, "max_pole_radius")
        n2 = order // 2
        angles = torch.arange(1, n2 + 1, dtype=torch.float64) * math.pi / (2 * n2 + 2)
        alpha, beta = _section_parameters(-torch.cos(angles), torch.full((n2,), 0.25),
                                          self.max_pole_radius)
        dtype = torch.get_default_dtype()
        self.alpha = nn.Parameter(alpha.to(dtype))
        self.beta = nn.Parameter(beta.to(dtype))
        pole = torch.full((order % 2,), 0.5, dtype=dtype)  # a first-order section's real pole
        self.gamma = nn.Parameter(torch.atanh(-pole / self.max_pole_radius))
        mask = torch.ones(order + 1)
        mask[0] = float(self.feedthrough)
        self.register_buffer("numerator_mask", mask)
        with torch.no_grad():
            gain = float(self.denominator().sum())
        self.numerator = nn.Parameter(torch.zeros(order + 1))
        with torch.no_grad():
            self.numerator[0 if self.feedthrough else 1] = gain

    def denominator(self) -> Tensor:
        """``a`` (order + 1,) with ``a[0] = 1``: the product of the sections."""
        r = self.max_pole_radius
        c2 = torch.tanh(self.alpha)
        a1, a2 = r * (1 + c2) * torch.tanh(self.beta), r**2 * c2
        a = torch.ones(1, dtype=self.alpha.dtype, device=self.alpha.device)
        sections = list(zip(a1, a2, strict=True)) + [(r * torch.tanh(g),) for g in self.gamma]
        for s in sections:
            # a * (1 + s[0] z^-1 + ...), the coefficients of a product of polynomials
            a = F.pad(a, (0, len(s))) + sum(F.pad(c * a, (k + 1, len(s) - k - 1))
                                            for k, c in enumerate(s))
        return a

    def coefficients(self) -> tuple[Tensor, Tensor]:
        """``(b, a)``, both (order + 1,), ``a[0] = 1`` (scipy's lfilter convention)."""
        return self.numerator * self.numerator_mask, self.denominator()

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        xb, squeezed = as_batched_sequence(x, "x")
        b, a = (c.to(xb.dtype) for c in self.coefficients())
        y, zf = lfilter(xb, b, a, zi=_start(state, xb, self.order))
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
        bn, an = _as_float64(b, "b", 1), _as_float64(a, "a", 1)
        if an[0] == 0:
            raise ValueError("a[0] must be non-zero: with a[0] = 0 the output y[t] would not "
                             f"be defined by past outputs (a non-causal block), got a = {an}")
        order = max(len(an), len(bn)) - 1
        if order < 1:
            raise ValueError("order = max(len(a), len(b)) - 1 must be >= 1 (a static gain has "
                             f"no dynamics), got b = {bn}, a = {an}")
        bn = np.pad(bn, (0, order + 1 - len(bn))) / an[0]
        an = np.pad(an, (0, order + 1 - len(an))) / an[0]
        if not feedthrough and bn[0] != 0:
            raise ValueError(f"b[0] must be 0 without feedthrough, got b[0] = {bn[0]:.6g}")
        poles = np.roots(an)
        m = float(np.abs(poles).max())
        if m >= 1:
            worst = poles[np.abs(poles).argmax()]
            raise ValueError(f"a is not stable: it has a pole of magnitude {m:.6g} (at "
                             f"{worst:.6g}); poles must lie strictly inside the unit circle")
        r = max(0.999, (1 + m) / 2) if max_pole_radius is None else max_pole_radius
        if _radius(r, "max_pole_radius") <= m:
            raise ValueError(f"max_pole_radius must exceed the largest pole magnitude {m:.6g},"
                             f" got {r!r}")
        pairs = sorted(poles[poles.imag > 0], key=lambda p: (abs(p), p.imag))
        real = np.sort(poles[poles.imag == 0].real)
        twos = real[: len(real) // 2 * 2].reshape(-1, 2)  # a leftover real pole: first order
        a1 = [-2 * p.real for p in pairs] + list(-twos.sum(1))
        a2 = [abs(p) ** 2 for p in pairs] + list(twos.prod(1))
        block = cls(order, feedthrough=feedthrough, max_pole_radius=r)
        alpha, beta = _section_parameters(torch.tensor(a1, dtype=torch.float64),
                                          torch.tensor(a2, dtype=torch.float64), r)
        with torch.no_grad():
            block.double()
            block.alpha.copy_(alpha)
            block.beta.copy_(beta)
            block.gamma.copy_(torch.tensor(-real[-1:] / r if order % 2 else []).atanh())
            block.numerator.copy_(torch.from_numpy(bn))
        return block


# --- state space -------------------------------------------------------------------------------


class StateSpaceStep(OperatorStep):
    """One state-space step (:func:`~torchhys.functional.linear_filter.state_space_step`).

    State: ``state`` (n columns, 0 at the first sample). Features: the p outputs.
    """

    def __init__(self, A: Tensor, B: Tensor, C: Tensor, D: Tensor) -> None:
        super().__init__()
        for name, m in (("A", A), ("B", B), ("C", C), ("D", D)):
            self.register_buffer(name, m.detach().clone())
        self.n_outputs = int(C.shape[0])
        self.state_spec = [StateBlock("state", int(A.shape[0]))]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
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

    ``A = r W / max(1, ||W||_2)`` (module docstring); ``B``, ``C``, ``D`` are free (``D = 0``
    without feedthrough). One input (the operator's ``x``), ``n_outputs`` outputs. The
    sequence path is :func:`~torchhys.functional.linear_filter.state_space`.

    Args:
        n_states: state dimension n (>= 1).
        n_outputs: outputs p (>= 1).
        feedthrough: learn the direct gain D; False fixes ``D = 0``.
        max_norm: bound r on ``||A||_2``, in (0, 1).

    Shape:
        - x: (time,) or (batch, time)
        - state: (n,) or (batch, n); zeros if None
        - returns ``(y, state)``: y ``x.shape + (p,)``, and the state after the last sample.

    References:
        ``scipy.signal.dlsim`` (the same convention).
    """

    def __init__(self, n_states: int = 2, n_outputs: int = 1, *, feedthrough: bool = True,
                 max_norm: float = 0.999) -> None:
        super().__init__()
        n = check_int(n_states, "n_states", minimum=1)
        self.n_outputs = check_int(n_outputs, "n_outputs", minimum=1)
        self.max_norm = _radius(max_norm, "max_norm")
        self.W = nn.Parameter(0.5 * torch.randn(n, n) / math.sqrt(n))
        self.B = nn.Parameter(torch.randn(n) / math.sqrt(n))
        self.C = nn.Parameter(torch.randn(n_outputs, n) / math.sqrt(n))
        if feedthrough:
            self.D = nn.Parameter(torch.zeros(n_outputs))
        else:
            self.register_buffer("D", torch.zeros(n_outputs))

    def matrices(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(A, B, C, D)``: (n, n), (n,), (p, n), (p,)."""
        norm = torch.linalg.matrix_norm(self.W, ord=2)
        return self.max_norm * self.W / norm.clamp_min(1.0), self.B, self.C, self.D

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        xb, squeezed = as_batched_sequence(x, "x")
        A, B, C, D = (m.to(xb.dtype) for m in self.matrices())
        y, s = state_space(xb, A, B, C, D, s0=_start(state, xb, A.shape[0]))
        return (y[0], s[0]) if squeezed else (y, s)

    def streaming_step(self, dtype: torch.dtype) -> StateSpaceStep:
        """The state-space step with the current matrices, in ``dtype``."""
        return StateSpaceStep(*(m.detach().to(dtype) for m in self.matrices()))

    @classmethod
    def from_matrices(cls, A: Tensor | np.ndarray, B: Tensor | np.ndarray,
                      C: Tensor | np.ndarray, D: Tensor | np.ndarray | None = None, *,
                      max_norm: float | None = None) -> StateSpace:
        """A float64 block with the given (stable) matrices.

        Where ``||A||_2 >= 1`` the state is changed to coordinates ``L^T s`` in which A is a
        contraction (``P = L L^T`` solves ``P - A^T P A = I``): outputs are unchanged, the
        state is in the new coordinates.

        Args:
            A: (n, n). B: (n,) or (n, 1). C: (p, n). D: (p,) or (p, 1); zeros if None.
            max_norm: bound kept in training; default ``max(0.999, (1 + ||A||_2) / 2)``.

        Raises:
            ValueError: wrong shapes, non-finite entries, an eigenvalue of A on or outside the
                unit circle (the message gives its modulus).
        """
        A = _as_float64(A, "A", 2)
        n = A.shape[0]
        B = _as_float64(B, "B").reshape(-1)
        C = _as_float64(C, "C", 2)
        p = C.shape[0]
        D = np.zeros(p) if D is None else _as_float64(D, "D").reshape(-1)
        if A.shape != (n, n) or B.shape != (n,) or C.shape != (p, n) or D.shape != (p,):
            raise ValueError(f"A, B, C, D must have shapes (n, n), (n,), (p, n), (p,), got "
                             f"{A.shape}, {B.shape}, {C.shape}, {D.shape}")
        rho = float(np.abs(np.linalg.eigvals(A)).max())
        if rho >= 1:
            raise ValueError(f"A is not stable: it has an eigenvalue of magnitude {rho:.6g}; "
                             "eigenvalues must lie strictly inside the unit circle")
        if np.linalg.norm(A, 2) >= 1:
            L = _contractive(A)
            A, B, C = L.T @ A @ np.linalg.inv(L.T), L.T @ B, C @ np.linalg.inv(L.T)
        norm = float(np.linalg.norm(A, 2))
        r = max(0.999, (1 + norm) / 2) if max_norm is None else _radius(max_norm, "max_norm")
        if r < norm:
            raise ValueError(f"max_norm must be at least ||A||_2 = {norm:.6g}, got {r!r}")
        block = cls(n, p, max_norm=r).double()
        with torch.no_grad():
            for name, m in (("W", A / r), ("B", B), ("C", C), ("D", D)):
                getattr(block, name).copy_(torch.from_numpy(np.ascontiguousarray(m)))
        return block


register_operator("transfer_function", TransferFunction)
register_operator("state_space", StateSpace)
