"""A piezo-stage-like plant: rate-independent hysteresis followed by lightly damped dynamics.

Model (the Hammerstein structure of a piezo-actuated positioning stage)::

    h = H[u]                                     hysteresis: Prandtl-Ishlinskii by default
    y'' + 2 zeta w_n y' + w_n^2 y = w_n^2 h      the stage: w_n = 2 pi f_n, unit DC gain

Slow inputs give ``y = H[u]``; faster ones see the stage's resonance: a sine of frequency f
is scaled by ``|G| = 1 / |1 - r^2 + 2j zeta r|``, ``r = f / f_n``, and delayed (with
``zeta = 0.07``: +1.0 % gain and 0.8 degrees of lag at ``r = 0.1``, +4.1 % and 1.7 degrees
at ``r = 0.2``, +33 % at ``r = 0.5``, ``1 / (2 zeta) = 7.1`` at resonance). A compensator
that inverts ``H`` alone is therefore only right at low rates: see ``docs/compensation.md``
(the piezo stage).

Discretisation: exact under a zero-order hold (the input ``h`` held constant over each sample
interval ``dt``, as a DAC holds a command). In the scaled state ``s = (y, y' / w_n)``::

    A = w_n [[0, 1], [-1, -2 zeta]],   B = w_n [0, 1]^T,   C = [1, 0]
    expm([[A, B], [0, 0]] dt) = [[A_d, B_d], [0, 1]]
    s[k + 1] = A_d s[k] + B_d h[k],    y[k] = C s[k]

so ``y[k]`` is the continuous response at ``t_k`` to the held input, with no truncation error
(``scipy.signal.cont2discrete(..., method="zoh")`` and ``scipy.signal.dlsim``: the same
convention). ``y[k]`` depends on ``h[0..k-1]`` only (a strictly proper sampled plant: one
sample of delay); the stage starts at rest (``s[0] = 0``, the plays at 0). The matrix
exponential (``torch.linalg.matrix_exp``) is differentiable, so the output is differentiable
in the input, in ``f_n`` and ``zeta`` and in the hysteresis parameters; the recursion runs in
:func:`torchhys.functional.linear_filter.state_space` (a compiled kernel on the CPU).

References:
    K. K. Leang, S. Devasia, "Feedback-linearized inverse feedforward for creep, hysteresis,
    and vibration compensation in AFM piezoactuators", IEEE Trans. Control Syst. Technol. 15
    (2007) 927-935 (hysteresis followed by the stage's vibrational dynamics);
    G. F. Franklin, J. D. Powell, M. Workman, Digital Control of Dynamic Systems, 3rd ed.,
    1998, Sec. 4.3 (zero-order-hold equivalents).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence, check_floating, check_tensor
from torchhys.functional.linear_filter import state_space
from torchhys.operator import check_operator
from torchhys.operators.prandtl_ishlinskii import PrandtlIshlinskii
from torchhys.plants.bouc_wen import BoucWen

__all__ = ["PiezoStage", "default_stage_hysteresis", "second_order_zoh"]


def default_stage_hysteresis() -> PrandtlIshlinskii:
    """The default hysteresis of :class:`PiezoStage`: a Prandtl-Ishlinskii model.

    15 plays of full widths ``k / 3``, ``k = 1..15`` (twice the paper plant's), weights 0.1,
    linear weight 0.5 (so it has an exact inverse), float64. For ``u = 6 sin(w t)`` from rest
    the output spans +-10 and the loop is 4 wide at ``u = 0`` (20 % of the output range).
    """
    widths = torch.arange(1, 16, dtype=torch.float64) / 3.0
    return PrandtlIshlinskii(widths, torch.full((15,), 0.1, dtype=torch.float64),
                             linear_weight=0.5)


def _positive(value: float | Tensor, name: str) -> float:
    v = float(value.detach()) if isinstance(value, Tensor) else value
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return float(v)


def second_order_zoh(natural_frequency: float | Tensor, damping: float | Tensor, dt: float
                     ) -> tuple[Tensor, Tensor]:
    """Zero-order-hold equivalent of ``w_n^2 / (s^2 + 2 zeta w_n s + w_n^2)``.

    Args:
        natural_frequency: ``f_n`` in Hz (``w_n = 2 pi f_n``), > 0; a float or 0-dim tensor.
        damping: damping ratio ``zeta`` > 0; a float or 0-dim tensor.
        dt: sampling step in s, > 0.

    Returns:
        ``(A_d, B_d)``: (2, 2) and (2,), float64, in the scaled state ``(y, y' / w_n)``
        (module docstring); ``C = [1, 0]``, ``D = 0``. Differentiable in tensor arguments.

    Raises:
        ValueError: a non-positive or non-finite argument, or a non-scalar tensor.
    """
    for name, v in (("natural_frequency", natural_frequency), ("damping", damping)):
        if isinstance(v, Tensor) and v.dim() != 0:
            raise ValueError(f"{name} must be a scalar (0-dim tensor), got shape "
                             f"{tuple(v.shape)}")
        _positive(v, name)
    _positive(dt, "dt")
    wn = 2 * math.pi * torch.as_tensor(natural_frequency, dtype=torch.float64)
    zeta = torch.as_tensor(damping, dtype=torch.float64)
    zero, one = torch.zeros((), dtype=torch.float64), torch.ones((), dtype=torch.float64)
    M = torch.stack([torch.stack([zero, one, zero]),
                     torch.stack([-one, -2 * zeta, one]),
                     torch.stack([zero, zero, zero])]) * (wn * dt)
    E = torch.linalg.matrix_exp(M)
    return E[:2, :2], E[:2, 2]


def _step(t: Tensor | None, fs: float | None, n: int) -> float:
    """The sampling step from a uniform time grid ``t`` (time,) or a rate ``fs`` (Hz)."""
    if (t is None) == (fs is None):
        raise ValueError(f"give exactly one of t or fs, got t={'None' if t is None else '...'}"
                         f", fs={fs!r}")
    if fs is not None:
        return 1.0 / _positive(fs, "fs")
    check_tensor(t, "t")
    check_floating(t, "t")
    if t.dim() != 1 or t.shape[0] != n or n < 2:
        raise ValueError(f"t must have shape (time,) with time = {n} >= 2, got shape "
                         f"{tuple(t.shape)}")
    d = torch.diff(t.detach().double())
    dt = float(d.mean())
    if not (dt > 0 and math.isfinite(dt)) or float((d - dt).abs().max()) > 1e-9 * max(
            1.0, float(t.detach().abs().max())):
        raise ValueError("t must be strictly increasing and evenly spaced (a zero-order hold "
                         f"at one rate), got steps from {float(d.min()):.6g} to "
                         f"{float(d.max()):.6g}")
    return dt


class PiezoStage(nn.Module):
    """Hysteresis ``H`` followed by a lightly damped second-order stage (module docstring).

    Args:
        natural_frequency: the stage's ``f_n`` in Hz, > 0.
        damping: its damping ratio ``zeta`` > 0 (a piezo stage: about 0.05 - 0.1).
        hysteresis: a :class:`~torchhys.HysteresisOperator` with one output (e.g.
            :class:`~torchhys.PrandtlIshlinskii`), or a :class:`~torchhys.plants.BoucWen`;
            default :func:`default_stage_hysteresis`.
        learnable: register ``natural_frequency`` and ``damping`` as parameters (else
            buffers); both are float64 0-dim tensors.

    Shapes:
        ``forward(u, t=None, *, fs=None)``: u (time,) or (batch, time) -> y of u's shape.
        Give the sample times ``t`` (time,), evenly spaced, or the sampling rate ``fs`` (Hz).

    Raises:
        ValueError: non-positive ``natural_frequency`` or ``damping``.
        TypeError: a ``hysteresis`` that is neither kind.

    Example::

        stage = PiezoStage(natural_frequency=1000.0, damping=0.07)
        y = stage(u, fs=20_000.0)          # u (batch, time) at 20 kHz
    """

    def __init__(self, natural_frequency: float, damping: float = 0.07, *,
                 hysteresis: nn.Module | None = None, learnable: bool = False) -> None:
        super().__init__()
        values = {"natural_frequency": _positive(natural_frequency, "natural_frequency"),
                  "damping": _positive(damping, "damping")}
        for name, v in values.items():
            tensor = torch.tensor(v, dtype=torch.float64)
            if learnable:
                self.register_parameter(name, nn.Parameter(tensor))
            else:
                self.register_buffer(name, tensor)
        if hysteresis is None:
            hysteresis = default_stage_hysteresis()
        elif not isinstance(hysteresis, BoucWen):
            op = check_operator(hysteresis, "hysteresis")
            if op.n_outputs != 1 or not op.causal:
                raise TypeError(f"hysteresis must be a causal operator with one output, got "
                                f"{type(op).__name__} with n_outputs={op.n_outputs}")
        self.hysteresis = hysteresis

    def hysteresis_output(self, u: Tensor) -> Tensor:
        """``h = H[u]`` from rest: u (time,) or (batch, time) -> h of u's shape (rate-
        independent: it needs no time grid)."""
        ub, squeezed = as_batched_sequence(u, "u")
        if isinstance(self.hysteresis, BoucWen):  # any increasing grid gives the same output
            grid = torch.arange(ub.shape[-1], dtype=torch.float64)
            h = self.hysteresis(ub.double(), grid).to(ub.dtype)
        else:
            h, _ = self.hysteresis(ub)
            h = h.to(ub.dtype)
        return h[0] if squeezed else h

    def matrices(self, dt: float) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The sampled stage ``(A_d, B_d, C, D)``: (2, 2), (2,), (1, 2), (1,), float64."""
        A, B = second_order_zoh(self.natural_frequency, self.damping, dt)
        return A, B, A.new_tensor([[1.0, 0.0]]), A.new_zeros(1)

    def coefficients(self, fs: float) -> tuple[Tensor, Tensor]:
        """The sampled stage as ``(b, a)``, (3,) each, scipy's lfilter convention.

        ``G(z) = (b1 z^-1 + b2 z^-2) / (1 + a1 z^-1 + a2 z^-2)`` (``b[0] = 0``), with
        ``G(1) = 1``; from ``C adj(zI - A_d) B_d / det(zI - A_d)``.
        """
        A, B, _, _ = self.matrices(1.0 / _positive(fs, "fs"))
        a = torch.stack([torch.ones_like(A[0, 0]), -(A[0, 0] + A[1, 1]),
                         A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]])
        b = torch.stack([torch.zeros_like(B[0]), B[0], A[0, 1] * B[1] - A[1, 1] * B[0]])
        return b, a

    def dynamics(self, h: Tensor, t: Tensor | None = None, *, fs: float | None = None
                 ) -> Tensor:
        """The stage alone, from rest: h (time,) or (batch, time) -> y of h's shape."""
        hb, squeezed = as_batched_sequence(h, "h")
        dt = _step(t, fs, hb.shape[-1])
        A, B, C, D = self.matrices(dt)
        y, _ = state_space(hb, *(m.to(hb.dtype) for m in (A, B, C, D)))
        y = y.squeeze(-1)
        return y[0] if squeezed else y

    def forward(self, u: Tensor, t: Tensor | None = None, *, fs: float | None = None
                ) -> Tensor:
        """Stage output ``y`` for the command ``u`` (time,) or (batch, time), from rest."""
        return self.dynamics(self.hysteresis_output(u), t, fs=fs)

    def extra_repr(self) -> str:
        return (f"natural_frequency={float(self.natural_frequency):.6g} Hz, "
                f"damping={float(self.damping):.6g}")
