"""Per-sample steps of the branch operators (EIHO, Zhao-Tan), for export.

The sequence path is :func:`torchhys.functional._branch.branch_operator`; these steps call
the same definitions (:func:`~torchhys.functional.play_step` for the turning-point
detector, :class:`~torchhys.functional._branch.BranchShape` and
:func:`~torchhys.functional._branch.direction_coefficient` for the branches), operation
for operation, so a step-by-step run equals the sequence output bit for bit. Three steps:

* :class:`RecentStep`: the ``"recent"`` rule, any threshold, ``"level"`` or ``"branch"``
  output, fixed or anchored coefficients;
* :class:`DominantStep`: the ``"dominant"`` rule (return-point memory, a fixed-size stack);
* :class:`RebasedStep`: the re-based recent-rule EIHO with threshold 0 and fixed
  coefficients, ``f = a_d sign(v) g(|v|)``, ``v = x - x_a``: with threshold 0 the running
  extremum is the last sample and the tentative term vanishes, so the step keeps only the
  previous sample, the anchor and ``v`` (the deployed configuration; :func:`branch_step`
  picks it).

Use :func:`branch_step` to build the one that fits an operator's settings.
"""

import torch
from torch import Tensor

from torchhys.functional._branch import (
    BranchShape,
    SquareRoot,
    direction_coefficient,
    signed_sqrt,
    sqrt_constants,
)
from torchhys.functional.backlash import play_step
from torchhys.step import OperatorStep, StateBlock

__all__ = ["DominantStep", "RebasedStep", "RecentStep", "branch_step"]


class _BranchStep(OperatorStep):
    """Settings shared by the branch steps (fixed at build; tensors in the step's dtype)."""

    def __init__(self, shape: BranchShape, a: Tensor, slope: Tensor | None, r: Tensor,
                 branch: bool) -> None:
        super().__init__()
        self.n_outputs = 1
        self.shape, self.branch = shape, branch
        self.anchored: bool = slope is not None
        slope = torch.zeros_like(a) if slope is None else slope
        for name, value in (("a0", a[0]), ("a1", a[1]), ("s0", slope[0]), ("s1", slope[1]),
                            ("r", r), ("zero", a.new_zeros(()))):
            self.register_buffer(name, value.detach().clone())

    def g(self, u: Tensor, direction: Tensor, anchor: Tensor) -> Tensor:
        """``g(u)`` of a branch of ``direction`` (-1, 0, +1) that starts at ``anchor``."""
        if self.anchored:
            coef = direction_coefficient(self.a0, self.a1, direction, anchor, self.s0, self.s1)
        else:
            coef = direction_coefficient(self.a0, self.a1, direction)
        return self.shape(u, coef)

    def turn(self, x: Tensor, p_old: Tensor, M: Tensor, d_prev: Tensor
             ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The turning-point detector: ``(p, confirm, d, m)``: the detector's new value, a
        confirmed reversal, the committed direction and the running extremum."""
        p = play_step(x, self.r, p_old)
        move = torch.sign(p - p_old)
        confirm = move * d_prev < self.zero
        d = torch.sign(torch.add(d_prev, move, alpha=2.0))
        m = torch.where(move != self.zero, x, M)
        return p, confirm, d, m

    def tentative(self, x: Tensor, m: Tensor, d: Tensor) -> Tensor:
        """The tentative reversed branch from the running extremum: ``s g(relu(s (x - m)))``
        with ``s = -d`` (or ``sign(x - m)`` before the first direction is set)."""
        xm = x - m
        s = torch.sign(torch.sub(torch.sign(xm), d, alpha=2.0))
        return s * self.g(torch.relu(s * xm), s, m)


class RecentStep(_BranchStep):
    """The ``"recent"`` rule: the anchor is the last confirmed turning point.

    State: ``turning`` = ``[p, M, d, x_a]`` (detector, running extremum, direction, anchor),
    and for the ``"level"`` output ``level`` = the branch value at the anchor in float64
    (the sequence path sums the increments with ``cumsum``, which accumulates in double).
    """

    def __init__(self, shape: BranchShape, a: Tensor, slope: Tensor | None, r: Tensor,
                 branch: bool) -> None:
        super().__init__(shape, a, slope, r, branch)
        self.state_spec = [StateBlock("turning", 4, from_sample=[1.0, 1.0, 0.0, 1.0])]
        if not branch:
            self.state_spec.append(StateBlock("level", 1, kind="float64"))

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        p_old, M, d_prev, xa_prev = state[0].split(1, 1)
        p, confirm, d, m = self.turn(x, p_old, M, d_prev)
        x_a = torch.where(confirm, M, xa_prev)
        g_m = d * self.g((m - x_a).abs(), d, x_a)  # f - f(x_a) at the running extremum
        new = [torch.cat([p, m, d, x_a], 1)]
        if self.branch:
            return g_m + self.tentative(x, m, d), new
        # the branch value at the anchor grows by the closed branch at each turning point
        inc = d_prev * self.g((M - xa_prev).abs(), d_prev, xa_prev)
        level = state[1] + torch.where(confirm, inc, torch.zeros_like(inc)).double()
        new.append(level)
        return (level.to(x.dtype) + g_m) + self.tentative(x, m, d), new


def _tables(D: int) -> dict[str, Tensor]:
    """Lookup tables of the dominant stack (depth ``D``), keyed by ``ti + D * confirm``.

    ``ti`` is the anchor index of the previous sample: a confirmed turning point pops the
    loops it closed, which is exactly the previous sample's anchor lookup, and is pushed at
    ``ti + 1`` (at ``D - 2`` after discarding entries 1 and 2 when the stack is full).
    Stack columns: ``[sx (D), sf (D), 2 scratch]``.
    """
    W = 2 * D + 2
    ident = torch.arange(W)
    shift = [0] + list(range(3, D)) + [D - 2, D - 1]
    full = torch.tensor(shift + [D + i for i in shift] + [2 * D, 2 * D + 1])
    gmap = ident.repeat(2 * D, 1)
    gmap[2 * D - 1] = full
    pos = torch.tensor([t + 1 if t + 1 < D else D - 2 for t in range(D)])
    smap = torch.tensor([[2 * D, 2 * D + 1]] * D + [[int(p), D + int(p)] for p in pos])
    # anchor candidates for a stack of top index t: entries 1 <= i <= t - 1 of the parity
    # of t - 1; passing candidate i moves the anchor to i - 1 (nested loops: the passed
    # candidates are the topmost ones, so the lowest passed one decides)
    ktab = torch.arange(D).unsqueeze(1).repeat(1, D)  # non-candidates: t (no pop)
    for t in range(D):
        for i in range(1, t):
            if (t - 1 - i) % 2 == 0:
                ktab[t, i] = i - 1
    return {"gmap": gmap, "smap": smap, "pos": pos, "ktab": ktab, "off": torch.tensor([0, D])}


class DominantStep(_BranchStep):
    """The ``"dominant"`` rule: return-point memory on a stack of ``D`` turning points.

    State: ``detector`` ``[p]``; ``branch`` ``[M, f_m, d, sx (D), sf (D), 2 scratch]``
    (running extremum, branch value there, direction, the stack's inputs and values);
    ``stack`` (int64) ``[top, ti]`` (top index, anchor index of the last sample). The stack
    is updated by table lookups (:func:`_tables`), no data-dependent control flow.
    """

    def __init__(self, shape: BranchShape, a: Tensor, slope: Tensor | None, r: Tensor,
                 branch: bool, depth: int) -> None:
        super().__init__(shape, a, slope, r, branch)
        self.depth = depth
        width = 3 + 2 * depth + 2
        anchors = [0.0] * width
        anchors[0] = anchors[3] = 1.0  # M and the stack's start sx[0]
        self.state_spec = [StateBlock("detector", 1, from_sample=1.0),
                           StateBlock("branch", width, from_sample=anchors),
                           StateBlock("stack", 2, kind="int64")]
        for name, table in _tables(depth).items():
            self.register_buffer(name, table)

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        D = self.depth
        p_old, blk, idx = state[0], state[1], state[2]
        M, d_prev = blk.narrow(1, 0, 1), blk.narrow(1, 2, 1)
        p, confirm, d, m = self.turn(x, p_old, M, d_prev)
        top, ti_prev = idx.select(1, 0), idx.select(1, 1)
        key = torch.add(ti_prev, confirm.squeeze(1), alpha=D)
        # push the confirmed turning point (M, f_m) of the last sample
        S = blk.narrow(1, 3, 2 * D + 2).gather(1, self.gmap.index_select(0, key))
        S = S.scatter(1, self.smap.index_select(0, key), blk.narrow(1, 0, 2))
        top = torch.where(confirm.squeeze(1), self.pos.index_select(0, ti_prev), top)
        # anchor: pop the nested loops closed by the running extremum m
        passed = (m - S.narrow(1, 0, D)) * d >= self.zero
        ti = torch.where(passed, self.ktab.index_select(0, top), top.unsqueeze(1)).amin(1)
        xf = S.gather(1, ti.unsqueeze(1) + self.off)
        x_a, f_a = xf.narrow(1, 0, 1), xf.narrow(1, 1, 1)
        g_m = d * self.g((m - x_a).abs(), d, x_a)
        f_m = f_a + g_m
        f = (g_m if self.branch else f_m) + self.tentative(x, m, d)
        new = [p, torch.cat([m, f_m, d, S], 1), torch.stack([top, ti], 1)]
        return f, new


class RebasedStep(_BranchStep):
    """The re-based recent-rule EIHO with threshold 0 and fixed coefficients.

    ``f = a_d signed_sqrt(v)``, ``v = x - x_a``: every reversal of the input is a turning
    point (a move against the sign of ``v``; copysign compares sign bits, so a zero move is
    never one), anchored at the previous sample. State: ``[x_prev]``, ``[x_a]``, ``[v]``.
    """

    def __init__(self, a: Tensor, eps: float) -> None:
        super().__init__(SquareRoot(eps), a, None, a.new_zeros(()), True)
        self.symmetric: bool = bool(a[0] == a[1])
        # the square root's eps and eps ** 0.5 as buffers (for the TorchScript interpreter,
        # which would wrap Python numbers into new tensors at every step; same values)
        eps_t, root_eps = sqrt_constants(eps, a)
        self.register_buffer("eps_t", eps_t)
        self.register_buffer("root_eps", root_eps)
        self.state_spec = [StateBlock("previous sample", 1, from_sample=1.0),
                           StateBlock("anchor", 1, from_sample=1.0), StateBlock("v", 1)]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        x_prev, xa_prev, v_prev = state[0], state[1], state[2]
        delta = x - x_prev
        x_a = torch.where(torch.copysign(delta, v_prev) != delta, x_prev, xa_prev)
        v = x - x_a
        coef = self.a0 if self.symmetric else direction_coefficient(self.a0, self.a1, v)
        return coef * signed_sqrt(v, self.eps_t, self.root_eps), [x, x_a, v]


def branch_step(
    shape: BranchShape, rule: str, a: Tensor, slope: Tensor | None, threshold: Tensor, *,
    output: str, max_depth: int, dtype: torch.dtype,
) -> _BranchStep:
    """The step of a branch operator with these settings, in ``dtype``: one step class per
    rule (:class:`DominantStep`, :class:`RecentStep`), and :class:`RebasedStep` for the
    recent rule's deployed case (the square-root shape, threshold 0, fixed coefficients,
    the ``"branch"`` output).

    Args:
        shape: the branch shape (:class:`~torchhys.functional._branch.SquareRoot` of the
            EIHO, :class:`~torchhys.functional._branch.ZhaoTanShape`).
        rule: ``"recent"`` or ``"dominant"``.
        a: (2,) coefficients (ascending, descending); ones for the Zhao-Tan operator.
        slope: (2,) anchor slopes (``a_d exp(slope_d x_e)``), or None.
        threshold: 0-dim reversal threshold (calibrated).
        output: ``"level"`` or ``"branch"``; max_depth: stack size of ``"dominant"``.
    """
    a, r = a.detach().to(dtype).reshape(-1).expand(2), (0.5 * threshold.detach()).to(dtype)
    slope = None if slope is None else slope.detach().to(dtype).reshape(-1).expand(2)
    branch = output == "branch"
    if rule == "dominant":
        return DominantStep(shape, a, slope, r, branch, max_depth)
    if (isinstance(shape, SquareRoot) and branch and slope is None and float(r) == 0.0
            and shape.eps > 0):
        return RebasedStep(a, shape.eps)
    return RecentStep(shape, a, slope, r, branch)
