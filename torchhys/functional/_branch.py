"""Shared machinery of the branch operators anchored at turning points (EIHO, Zhao-Tan).

Both operators follow ``f(x) = f(x_e) +/- g(|x - x_e|)`` on the branch that starts at the
anchor ``x_e`` (a turning point), with ``g(u) = a sqrt(u)`` (EIHO) or
``g(u) = (1 - exp(-u)) u`` (Zhao-Tan). They share the turning-point machinery here.

Between a turning point and its confirmation (when ``threshold > 0``) the output follows
the *tentative* reversed branch from the running extremum ``M``:
``f = f(M) - d g(|x - M|)``. If the reversal is confirmed, that is the new branch anyway;
if the input returns past ``M`` instead, it retraces that branch back to ``f(M)`` and the
old branch continues (a sub-threshold excursion leaves no memory). So the output is a
causal function of the input history, continuous where the input is, and with
``threshold=0`` it is exactly Eq. (2) with every reversal starting a new branch.

Rules for the anchor ``x_e``:
    * ``"recent"``: the last turning point (Eq. (2) as printed). Branch values at turning
      points are cumulative sums: no loop at all.
    * ``"dominant"``: return-point memory. Turning points are kept on a stack
      ``[start, tp_1, tp_2, ...]`` (alternating maxima/minima). When the running extremum
      reaches the turning point that opened the current minor loop (the entry below the
      top), the loop's two entries are popped and the branch continues from the enclosing
      anchor. The stack is a fixed-size tensor of ``max_depth`` entries plus a depth counter;
      when a push would overflow it, the two oldest entries above the start are discarded
      (the outermost loop is forgotten). The stack is updated in a loop over *turning
      points* (not samples); per-sample anchors are then gathers.

Coefficients: fixed per direction, per segment (the paper's non-causal ``a_i``), or, with
``anchor_slope``, a function of the branch's anchor ``a_d exp(k_d x_e)`` (the tentative
reversed branch is anchored at the running extremum).

Outputs: ``"level"`` (default) is ``f`` itself; ``"branch"`` is the branch-local value
``f - f(x_e)`` with ``x_e`` the committed anchor (``+/- g(|x - x_e|)`` on a committed
branch, plus the tentative reversed branch before a confirmation). It depends only on the
input's excursion from the anchor and the direction, not on the anchor's level, so it does
not drift along the history (the level of ``f`` accumulates from 0 at the first sample).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_choice,
    check_finite,
    check_floating,
    check_tensor,
    concrete,
)
from torchhys.functional.turning_points import resolve_threshold, zigzag

_RULES = ("recent", "dominant")


class BranchState(NamedTuple):
    """Streaming state of a branch operator (batch ``B``, stack depth ``D``)."""

    play: Tensor
    """(B,) detector (play operator) state."""
    direction: Tensor
    """(B,) long: direction of the committed branch, +1, -1 or 0 (not yet set)."""
    extremum: Tensor
    """(B,) running extremum of the input since the current anchor."""
    stack_x: Tensor
    """(B, D) input values of the anchors (entry 0: the start)."""
    stack_f: Tensor
    """(B, D) operator outputs at the anchors."""
    stack_seg: Tensor
    """(B, D) long: segment number of the branch that starts at each anchor."""
    depth: Tensor
    """(B,) long: number of valid stack entries (>= 1)."""
    segment: Tensor
    """(B,) long: number of turning points confirmed so far."""


def initial_branch_state(x0: Tensor, depth: int, f0: Tensor | None = None) -> BranchState:
    """Fresh state anchored at the first samples ``x0`` (B,), with ``f = f0`` (default 0)."""
    B = x0.shape[0]
    f0 = x0.new_zeros(B) if f0 is None else f0
    stack_x = torch.cat([x0[:, None], x0.new_zeros(B, depth - 1)], dim=1)
    stack_f = torch.cat([f0[:, None], f0.new_zeros(B, depth - 1)], dim=1)
    zeros = torch.zeros(B, dtype=torch.long, device=x0.device)
    return BranchState(
        x0.detach(), zeros, x0, stack_x, stack_f, torch.zeros_like(stack_x, dtype=torch.long),
        torch.ones_like(zeros), zeros,
    )


def safe_sqrt(u: Tensor, eps: float, differentiable: bool = True) -> Tensor:
    """``sqrt(u)`` for ``u >= eps``, ``u / sqrt(eps)`` below: zero at 0, slope <= 1/sqrt(eps).

    Keeps gradients finite at ``x = x_e``: the inner ``where`` keeps ``sqrt``'s infinite slope
    at 0 out of the backward; with ``differentiable=False`` it is left out, the values are the
    same (that form is :func:`linear_zone_sqrt`, with the constants as tensors). The value
    differs from ``sqrt(u)`` by less than ``sqrt(eps) / 4`` and only for ``0 < u < eps``.
    Scriptable. (``u * rsqrt(max(u, eps))`` is the same function in fewer operations, but its
    rounding, in value and gradient, moves long full-batch fits: the paper's 2000 Adam + 10000
    L-BFGS protocol ends at 2.0e-3 with it, 1.3e-3 with this.)
    """
    if not differentiable:
        eps_t, root_eps = sqrt_constants(eps, u)
        return linear_zone_sqrt(u, eps_t, root_eps)
    big = u >= eps
    root = torch.sqrt(torch.where(big, u, torch.ones_like(u)))
    return torch.where(big, root, u / eps**0.5)


def sqrt_constants(eps: float, like: Tensor) -> tuple[Tensor, Tensor]:
    """The constants of :func:`safe_sqrt`, ``eps`` and ``eps ** 0.5``, as 0-dim tensors in
    ``like``'s dtype and device (each Python number rounded to the dtype, as an operation
    with a Python number rounds it)."""
    return (torch.tensor(eps, dtype=like.dtype, device=like.device),
            torch.tensor(eps**0.5, dtype=like.dtype, device=like.device))


def linear_zone_sqrt(u: Tensor, eps: Tensor, root_eps: Tensor) -> Tensor:
    """:func:`safe_sqrt` without the gradient guard, its constants given as 0-dim tensors
    in ``u``'s dtype (:func:`sqrt_constants`): the same values, bit for bit. For the
    streaming steps (no gradient), which keep the constants as buffers: the TorchScript
    interpreter would wrap a Python ``eps`` into a new tensor twice per call."""
    # (TorchScript only: its executor turns ``u / root_eps`` with a constant 0-dim tensor back
    # into a division by a Python number, wrapped at every call; the rounding_mode overload,
    # the same true division, keeps the tensor)
    return torch.where(u >= eps, torch.sqrt(u), torch.div(u, root_eps, rounding_mode=None))


def signed_sqrt(v: Tensor, eps: Tensor, root_eps: Tensor) -> Tensor:
    """``sign(v) * safe_sqrt(|v|, eps)``, exactly (``copysign`` moves the sign bit), with
    ``eps`` and ``eps ** 0.5`` as 0-dim tensors (:func:`sqrt_constants`); for the streaming
    steps (no gradient)."""
    return torch.copysign(linear_zone_sqrt(v.abs(), eps, root_eps), v)


class BranchShape(nn.Module):
    """The shape ``g(u)`` of a branch operator's branches, ``u = |x - x_e| >= 0`` from the
    branch's anchor ``x_e``, times the branch's coefficient where the shape has one: one
    small object per shape (:class:`SquareRoot`, :class:`ZhaoTanShape`), scriptable, called
    by the sequence path and by the steps."""

    def forward(self, u: Tensor, coef: Tensor) -> Tensor:  # pragma: no cover (abstract)
        raise NotImplementedError


class SquareRoot(BranchShape):
    """``g(u) = coef * safe_sqrt(u, eps)``: the EIHO's branch (Eq. (2)), linear below ``eps``
    (:func:`safe_sqrt`)."""

    def __init__(self, eps: float) -> None:
        super().__init__()
        self.eps = float(eps)

    def forward(self, u: Tensor, coef: Tensor) -> Tensor:
        return coef * safe_sqrt(u, self.eps)


class ZhaoTanShape(BranchShape):
    """``g(u) = (1 - exp(-u / scale)) u``: the Zhao-Tan operator's branch (no coefficient)."""

    def __init__(self, scale: float) -> None:
        super().__init__()
        self.scale = float(scale)

    def forward(self, u: Tensor, coef: Tensor) -> Tensor:
        return (1.0 - torch.exp(-u / self.scale)) * u


def direction_coefficient(
    a0: Tensor, a1: Tensor, direction: Tensor, anchor: Tensor | None = None,
    s0: Tensor | None = None, s1: Tensor | None = None,
) -> Tensor:
    """Coefficient of a branch of ``direction`` (ascending where >= 0): ``a0`` or ``a1``;
    with anchor slopes ``s0, s1``: ``a_d exp(s_d * anchor)``, ``anchor`` its start point."""
    up = direction >= 0
    base = torch.where(up, a0, a1)
    if anchor is None or s0 is None or s1 is None:
        return base
    return base * torch.exp(torch.where(up, s0, s1) * anchor)


def _coef(
    a: Tensor, direction: Tensor, seg: Tensor, per_segment: bool,
    anchor: Tensor | None = None, slope: Tensor | None = None,
) -> Tensor:
    """Branch coefficient: a (2,) = (ascending, descending) or a (B, K) per segment.

    With ``slope`` (2,), the coefficient of a branch depends on its anchor (start point):
    ``a_d exp(slope_d * anchor)``.
    """
    if per_segment:
        return a.gather(1, seg.clamp(min=0, max=a.shape[1] - 1).reshape(a.shape[0], -1)).reshape(
            seg.shape
        )
    if slope is None:
        return direction_coefficient(a[0], a[1], direction)
    return direction_coefficient(a[0], a[1], direction, anchor, slope[0], slope[1])


def _pops(stack_x: Tensor, depth: Tensor, m: Tensor, d: Tensor) -> Tensor:
    """Number of nested minor loops closed by the running extremum ``m`` (shapes (..., D))."""
    i = torch.arange(stack_x.shape[-1], device=stack_x.device)
    top = (depth - 1).unsqueeze(-1)
    cand = (i <= top - 1) & (i >= 1) & ((top - 1 - i) % 2 == 0) & (d != 0).unsqueeze(-1)
    passed = (d.unsqueeze(-1) * (m.unsqueeze(-1) - stack_x)) >= 0
    failed = torch.where(cand & ~passed, i, -1).amax(dim=-1, keepdim=True)
    return (cand & (i > failed)).sum(dim=-1)


def _dominant_stacks(
    state: BranchState, v: Tensor, d_prev: Tensor, confirm: Tensor, a: Tensor,
    shape: BranchShape, per_segment: bool, slope: Tensor | None = None,
) -> tuple[BranchState, list[Tensor]]:
    """Update the stack at every confirmed turning point; return per-segment snapshots."""
    B, T = v.shape
    D = state.stack_x.shape[1]
    sx, sf, ss, depth = state.stack_x, state.stack_f, state.stack_seg, state.depth
    n_conf = confirm.sum(dim=1)
    # the most turning points a row confirms; where it cannot be read (traced, batched, meta
    # or fake tensors) every sample may be one: T steps, the rows past their own count masked
    K = 0 if T == 0 else int(n_conf.max()) if concrete(n_conf) else T
    order = torch.where(confirm, torch.arange(T, device=v.device), T).sort(dim=1).values[:, :K]
    snaps = [[sx, sf, ss, depth]]
    rows = torch.arange(B, device=v.device)
    for j in range(K):
        c = order[:, j].clamp(max=T - 1)
        valid = order[:, j] < T
        vj, dj = v[rows, c], d_prev[rows, c]
        top = depth - 1 - 2 * _pops(sx, depth, vj.detach(), dj)
        ax, af, aseg = sx[rows, top], sf[rows, top], ss[rows, top]
        coef = _coef(a, dj, aseg, per_segment, ax, slope)
        fv = af + dj * shape((vj - ax).abs(), coef)
        pos = top + 1
        full = pos >= D
        pos = torch.where(full, pos - 2, pos)
        hot = torch.nn.functional.one_hot(pos, D).bool()
        new = []
        for t, val in ((sx, vj), (sf, fv), (ss, state.segment + j + 1)):
            shifted = torch.where(full[:, None], torch.cat([t[:, :1], t[:, 3:], t[:, -2:]], 1), t)
            new.append(torch.where(valid[:, None], torch.where(hot, val[:, None], shifted), t))
        sx, sf, ss = new
        depth = torch.where(valid, pos + 1, depth)
        snaps.append([sx, sf, ss, depth])
    stacked = [torch.stack([s[k] for s in snaps], dim=1) for k in range(4)]
    return state._replace(stack_x=sx, stack_f=sf, stack_seg=ss, depth=depth), stacked


def branch_operator(
    x: Tensor, a: Tensor, shape: BranchShape, rule: str, threshold: float | str | Tensor,
    state: BranchState | None, per_segment: bool, max_depth: int,
    anchor_slope: Tensor | None = None, branch: bool = False,
) -> tuple[Tensor, BranchState]:
    xb, squeezed = as_batched_sequence(x, "x")
    check_choice(rule, "rule", _RULES)
    B, T = xb.shape
    depth = max_depth if rule == "dominant" else 1
    if state is None:
        state = initial_branch_state(xb[:, 0], depth)
    elif state.stack_x.shape != (B, depth):
        raise ValueError(
            f"state must come from the same operator and batch: stack shape {(B, depth)} "
            f"expected, got {tuple(state.stack_x.shape)}"
        )
    th = resolve_threshold(threshold, xb)
    z = zigzag(xb, th, state.play, state.direction)
    d = z.direction
    # the previous sample's values: shifted in and cut to T (a slice of size T - 1 makes
    # torch.export with a dynamic time dimension guard on T != 2)
    d_prev = torch.cat([state.direction[:, None], d], dim=1)[:, :T]
    last = z.extremum
    last_prev = torch.cat([last.new_full((B, 1), -1), last], dim=1)[:, :T]
    M = torch.where(last >= 0, xb.gather(1, last.clamp(min=0)), state.extremum[:, None])
    v = torch.where(last_prev >= 0, xb.gather(1, last_prev.clamp(min=0)), state.extremum[:, None])
    seg_local = z.confirm.long().cumsum(dim=1)
    segment = state.segment[:, None] + seg_local
    if rule == "recent":
        idx = torch.arange(T, device=xb.device).expand(B, T)
        lc = torch.where(z.confirm, idx, -1).cummax(dim=1).values
        x_a = torch.where(lc >= 0, v.gather(1, lc.clamp(min=0)), state.stack_x[:, :1])
        x_a_prev = torch.cat([state.stack_x[:, :1], x_a], dim=1)[:, :T]
        coef = _coef(a, d_prev, segment - 1, per_segment, x_a_prev, anchor_slope)
        g = shape((v - x_a_prev).abs(), coef)
        inc = torch.where(z.confirm, d_prev * g, 0.0)
        f_a = state.stack_f[:, :1] + inc.cumsum(dim=1)
        seg_a = segment
        new_state = state._replace(
            stack_x=x_a[:, -1:], stack_f=f_a[:, -1:], stack_seg=segment[:, -1:]
        )
    else:
        new_state, (sx, sf, ss, sdepth) = _dominant_stacks(
            state, v, d_prev, z.confirm, a, shape, per_segment, anchor_slope
        )
        D = sx.shape[-1]
        g_idx = seg_local[..., None].expand(B, T, D)
        sx_t, sf_t, ss_t = (s.gather(1, g_idx) for s in (sx, sf, ss))
        depth_t = sdepth.gather(1, seg_local)
        top = (depth_t - 1 - 2 * _pops(sx_t, depth_t, M.detach(), d))[..., None]
        x_a, f_a, seg_a = (s.gather(2, top)[..., 0] for s in (sx_t, sf_t, ss_t))
    coef_a = _coef(a, d, seg_a, per_segment, x_a, anchor_slope)
    base = torch.zeros_like(f_a) if branch else f_a  # "branch" output: f - f(x_e)
    f_m = base + d * shape((M - x_a).abs(), coef_a)
    s = torch.where(d != 0, -d, torch.sign(xb.detach() - M.detach()).long())
    u = torch.relu(s * (xb - M))
    seg_rev = torch.where(d != 0, segment + 1, segment)
    coef_s = _coef(a, s, seg_rev, per_segment, M, anchor_slope)
    f = f_m + s * shape(u, coef_s)
    new_state = new_state._replace(
        play=z.play, direction=d[:, -1], extremum=M[:, -1], segment=segment[:, -1]
    )
    return (f[0] if squeezed else f), new_state


def check_a(a: Tensor, per_segment: bool, batch: int) -> Tensor:
    check_tensor(a, "a")
    check_floating(a, "a")
    check_finite(a, "a")
    if per_segment:
        if a.dim() == 1:
            a = a.unsqueeze(0)
        if a.dim() != 2 or a.shape[0] != batch or a.shape[1] == 0:
            raise ValueError(
                f"per-segment a must have shape (batch={batch}, segments), got {tuple(a.shape)}"
            )
    else:
        if a.numel() not in (1, 2) or a.dim() > 1:
            raise ValueError(f"a must be a scalar or (ascending, descending), got {tuple(a.shape)}")
        a = a.reshape(-1).expand(2)
    if concrete(a) and bool((a <= 0).any()):
        raise ValueError(f"a must be positive, got minimum {a.min().item():.6g}")
    return a
