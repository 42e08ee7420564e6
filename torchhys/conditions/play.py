"""A play (backlash) operator whose thresholds move with measured operating conditions:
:class:`ConditionedBacklash`, its step :class:`ConditionedPlayStep` and the pure tensor maths
(:func:`conditioned_thresholds`, :func:`varying_play`).

Each play i follows ``p_i[t] = clamp(p_i[t-1], x[t] - r_i(c[t]), x[t] + r_i(c[t]))`` with

    r_i(c) = r_i * exp(theta_i . b(c~)),

``b`` the tensor-product Legendre basis of total degree ``degree`` without its constant term
(:func:`~torchhys.conditions.basis.legendre_basis`), ``c~`` the conditions scaled to
[-1, 1] over their calibrated range. ``theta`` starts at 0, so the operator starts as the
ordinary play of thresholds ``r`` (:class:`~torchhys.Backlash` of widths ``2 r``).
"""

# no `from __future__ import annotations`: TorchScript reads the step's class annotations
import torch
from torch import Tensor, nn

from torchhys._checks import check_int, check_widths
from torchhys.conditions._base import ConditionedOperator, schedule
from torchhys.conditions.basis import total_degree
from torchhys.functional.backlash import _check_state, _play, play_step
from torchhys.step import OperatorStep, StateBlock

__all__ = ["ConditionedBacklash", "ConditionedPlayStep", "conditioned_thresholds",
           "varying_play"]


def conditioned_thresholds(c: Tensor, thresholds: Tensor, theta: Tensor, scale: Tensor,
                           shift: Tensor, exponents: list[list[int]], degree: int) -> Tensor:
    """``r_i(c) = r_i exp(theta_i . b(c * scale + shift))``: (..., N) of conditions c (...,
    n); ``thresholds`` (N,), ``theta`` (N, len(exponents)), ``scale`` and ``shift`` (n,) map
    the calibrated range to [-1, 1]. Without exponents (no conditions): ``thresholds``."""
    if len(exponents) == 0:
        return thresholds
    return thresholds * torch.exp(schedule(c, theta, scale, shift, exponents, degree))


def varying_play(x: Tensor, r: Tensor, y0: Tensor) -> Tensor:
    """Plays of time-varying half-widths: ``y[t] = min(max(y[t-1], x[t] - r[t]), x[t] +
    r[t])``, ``y[-1] = y0``; x (B, T), r (B, T, N) >= 0, y0 (B, N) -> y (B, T, N).

    The values come from :func:`_clamp_scan` (without a graph). Each output is then the
    bound of the last sample s <= t at which the clamp was active (``y[s-1] < x[s] - r[s]``
    or ``y[s-1] > x[s] + r[s]``, strictly), or ``y0`` where none was: a gather of those
    bounds, through which autograd returns the gradients of x, r and y0. At a tie the
    gradient follows the inactive branch (``y[t] = y[t-1]``), as
    :func:`~torchhys.functional.backlash` does. The second derivative is zero (the active
    samples are piecewise constant in the inputs).
    """
    lo = x.unsqueeze(-1) - r
    hi = x.unsqueeze(-1) + r
    with torch.no_grad():
        y = _clamp_scan(lo.detach(), hi.detach(), y0.detach())
        prev = torch.cat([y0.detach().unsqueeze(1), y[:, :-1]], 1)
        below = prev < lo.detach()
        active = below | (prev > hi.detach())
        t = torch.arange(1, y.shape[1] + 1, device=y.device).view(1, -1, 1)
        last = torch.where(active, t, torch.zeros_like(t)).cummax(1).values  # 0: y0
    bounds = torch.cat([y0.unsqueeze(1), torch.where(below, lo, hi)], 1)  # (B, T + 1, N)
    return bounds.gather(1, last)


def _clamp_scan(lo: Tensor, hi: Tensor, y0: Tensor) -> Tensor:
    """``y[t] = min(max(y[t-1], lo[t]), hi[t])`` for lo <= hi (B, T, N), y0 (B, N).

    Composed clamps are clamps, so the time axis is cut into C chunks of K samples
    (:func:`~torchhys.functional._play_scan._chunking`, K near sqrt(T / 2)): one pass over
    the K positions composes each chunk's clamps, one over the chunks carries the state, a
    last one over the K positions writes the outputs (about ``2 sqrt(2 T)`` vectorized steps
    instead of T). Minima and maxima only: the values are the plain loop's bit for bit.
    """
    from torchhys.functional._play_scan import _chunking

    B, T, N = lo.shape
    K, C = _chunking(T)
    pad = C * K - T
    if pad:  # repeat the last clamp (idempotent); those outputs are dropped
        lo = torch.cat([lo, lo[:, -1:].expand(B, pad, N)], 1)
        hi = torch.cat([hi, hi[:, -1:].expand(B, pad, N)], 1)
    lo, hi = lo.reshape(B, C, K, N), hi.reshape(B, C, K, N)
    if C > 1:
        a, b = lo[:, :, 0], hi[:, :, 0]
        for k in range(1, K):
            a = torch.minimum(torch.maximum(a, lo[:, :, k]), hi[:, :, k])
            b = torch.minimum(torch.maximum(b, lo[:, :, k]), hi[:, :, k])
        carries, s = [y0], y0
        for j in range(C - 1):
            s = torch.minimum(torch.maximum(s, a[:, j]), b[:, j])
            carries.append(s)
        s = torch.stack(carries, 1)  # (B, C, N): the state entering each chunk
    else:
        s = y0.unsqueeze(1)
    outs = []
    for k in range(K):
        s = torch.minimum(torch.maximum(s, lo[:, :, k]), hi[:, :, k])
        outs.append(s)
    return torch.stack(outs, 2).reshape(B, C * K, N)[:, :T]


class ConditionedPlayStep(OperatorStep):
    """The plays one sample at a time: :func:`conditioned_thresholds` of the sample's
    conditions, then :func:`~torchhys.functional.play_step`.

    State: ``plays`` (N columns, 0 at the first sample, as the sequence path starts).
    Features: the N plays. Input: x (batch, 1 + n): the driving input, then the n conditions
    (n = 0: x (batch, 1), the ordinary play).
    """

    exponents: list[list[int]]
    degree: int
    n: int

    def __init__(self, thresholds: Tensor, theta: Tensor, scale: Tensor, shift: Tensor,
                 exponents: list[list[int]], degree: int) -> None:
        super().__init__()
        for name, value in (("r", thresholds), ("theta", theta), ("scale", scale),
                            ("shift", shift)):
            self.register_buffer(name, value.detach().clone())
        self.exponents, self.degree, self.n = exponents, int(degree), int(scale.numel())
        self.n_inputs = 1 + self.n
        self.n_outputs = int(thresholds.shape[0])
        self.state_spec = [StateBlock("plays", self.n_outputs)]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        r = conditioned_thresholds(x[:, 1:], self.r, self.theta, self.scale, self.shift,
                                   self.exponents, self.degree)
        y = play_step(x[:, :1], r, state[0])
        return y, [y]


class ConditionedBacklash(ConditionedOperator):
    """N plays whose thresholds are scaled by a learned positive function of the conditions.

    ``p_i[t] = clamp(p_i[t-1], x[t] - r_i(c[t]), x[t] + r_i(c[t]))``, ``r_i(c) = r_i
    exp(theta_i . b(c~))`` (the module docstring): the loop's width moves with the condition,
    its shape between reversals stays a play's. ``theta`` (N, K), K the basis' size
    (``C(n + degree, degree) - 1``), is a parameter starting at 0; the thresholds ``r`` are
    fixed. :meth:`calibrate` records the conditions' range (``cond_min``, ``cond_max``) that
    scales them to [-1, 1]; forward and the step need it (with conditions). The plays start
    at 0, as :class:`~torchhys.Backlash`'s. With ``n_conditions = 0`` it is the ordinary
    play of thresholds r, an operator of the protocol on x (batch, time); with conditions its
    step takes ``[x, conditions]`` (``n_inputs = 1 + n_conditions``: a conditioned model's
    step, see docs/conditions.md) and it cannot stand where an operator is expected
    (:func:`~torchhys.operator.check_operator` names ``n_inputs``).

    Args:
        thresholds: half-widths r_i >= 0, shape (N,) (``Backlash(2 * thresholds)`` is the
            same play at ``theta = 0``).
        n_conditions: conditions per sample (>= 0).
        degree: total degree of the basis in the conditions (>= 1).

    Shape:
        - x: (batch, time, 1 + n_conditions) or (time, 1 + n_conditions): column 0 the
          driving input, the others the conditions ((batch, time) or (time,) without
          conditions)
        - state: the plays before the first sample, (N,) or (batch, N); zeros if None
        - returns ``(p, final_state)``: p (batch, time, N) (or (time, N)), the plays at the
          last sample.

    Raises:
        ValueError: bad ``thresholds``, ``n_conditions`` or ``degree``; x of another shape,
            or with NaN or inf (the compensator holds a NaN sample instead); not calibrated.
    """

    constraints = {"thresholds": "nonnegative", "theta": "finite"}
    _scales = "the thresholds"

    def __init__(self, thresholds: Tensor | list[float], n_conditions: int = 1, *,
                 degree: int = 1) -> None:
        super().__init__()
        r = torch.as_tensor(thresholds)
        if not r.is_floating_point():
            r = r.to(torch.get_default_dtype())
        check_widths(r, "thresholds")
        n = check_int(n_conditions, "n_conditions", minimum=0)
        k = len(total_degree(n, check_int(degree, "degree", minimum=1))) - 1
        self.theta = nn.Parameter(torch.zeros(r.shape[0], max(k, 0), dtype=r.dtype))
        self.register_buffer("thresholds", r.detach().clone())
        self._init_conditions(n, degree, r.dtype)

    @property
    def n_outputs(self) -> int:
        """One feature per play (N)."""
        return int(self.thresholds.shape[0])

    def radii(self, conditions: Tensor) -> Tensor:
        """``r_i(c)`` (..., N) of conditions (..., n_conditions)."""
        scale, shift = self._scaling(conditions.dtype)
        return conditioned_thresholds(conditions, self.thresholds.to(conditions.dtype),
                                      self.theta.to(conditions.dtype), scale, shift,
                                      self.exponents, self.degree)

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        xb, squeezed = self._inputs(x)
        drive = xb if self.n_conditions == 0 else xb[..., 0]
        y0 = _check_state(state, drive, self.n_outputs, "state")
        if self.n_conditions == 0:  # constant thresholds: the play's own scan
            y = _play(drive, self.thresholds.to(xb.dtype), y0)
        else:
            y = varying_play(drive, self.radii(xb[..., 1:]), y0)
        return (y[0], y[0, -1]) if squeezed else (y, y[:, -1])

    def streaming_step(self, dtype: torch.dtype) -> ConditionedPlayStep:
        """The per-sample step with the current theta and range, in ``dtype``."""
        scale, shift = self._scaling(dtype)
        return ConditionedPlayStep(self.thresholds.detach().to(dtype),
                                   self.theta.detach().to(dtype), scale, shift,
                                   self.exponents, self.degree)

