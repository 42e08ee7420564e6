"""Per-sample steps of the deployable operators, written for TorchScript and ``torch.export``.

The compensator (:mod:`torchhys.streaming`) keeps all state in a few packed tensors:
``F (B, S)`` in the compensator's dtype, ``I (B, K)`` long, ``started (B, 1)`` bool and,
when a ``"recent"``-rule operator needs it, ``F64 (B, n)`` float64. Every play operator of
the input (:class:`PlayStep`, :class:`PIStep` and the turning-point detector of the EIHO) is
one column of a single block ``Y`` of ``F``; the compensator advances all of them, and sets a
fresh row's anchored columns to its first sample, with one ``clamp`` over the whole of ``F``,
and splits the result once (``parts``). Each step module owns columns of these tensors
(offsets set by :meth:`place`, pieces of the split by :meth:`pieces`), appends its (batch, 1)
feature, if any, to a list the network reads (plays are read from ``Yn`` directly), and its
new state columns to lists that the compensator concatenates once.

No Python control flow depends on tensor values; branches are ``torch.where`` and the
dominant stack is a fixed-size block of ``F`` updated by table lookups. The arithmetic
repeats the sequence implementations (:mod:`torchhys.functional.backlash`,
:mod:`torchhys.functional._branch`) value by value, so a step-by-step run equals the
sequence ``forward`` bit for bit (tested in float32 per operator), except the deployed
threshold-0 re-based EIHO, which computes ``v / sqrt(max(|v|, eps))`` (equal to rounding).
"""

import torch
from torch import Tensor, nn

__all__ = ["BranchStep", "PIStep", "PlayStep"]


class _Step(nn.Module):
    """Column bookkeeping shared by the steps (all sizes are Python ints, fixed at build)."""

    def __init__(self, play_r: Tensor, n_float: int, n_int: int, n_f64: int) -> None:
        super().__init__()
        self.register_buffer("play_r", play_r.detach().clone().reshape(-1))
        self.n_play: int = int(self.play_r.shape[0])
        self.n_float, self.n_int, self.n_f64 = n_float, n_int, n_f64
        self.n_out: int = 1
        self.y0: int = 0
        self.f0: int = 0
        self.i0: int = 0
        self.g0: int = 0
        #: index of this step's first piece in the compensator's split of ``F``
        self.p0: int = 0

    def place(self, y0: int, f0: int, i0: int, g0: int) -> None:
        """Offsets of this step's columns in ``Y``, ``F``, ``I`` and ``F64``."""
        self.y0, self.f0, self.i0, self.g0 = y0, f0, i0, g0

    def pieces(self) -> list[int]:
        """Sizes of the pieces its ``F`` block is split into (by the compensator)."""
        return [self.n_float] if self.n_float > 0 else []

    def network_columns(self) -> list[int]:
        """For each of its features: -1 for a ``Y`` column (the network reads all of
        ``Yn``), else 1 (an appended (batch, 1) feature)."""
        return [1] * self.n_out

    def anchors(self) -> tuple[list[bool], list[bool]]:
        """Which of its ``Y`` and ``F`` columns a fresh row anchors at its first sample."""
        return [False] * self.n_play, [False] * self.n_float


class PlayStep(_Step):
    """N play operators ``y = min(max(y_prev, x - r), x + r)``: N columns of ``Y``.

    Args:
        r: half-widths, shape (N,), in the compensator's dtype (``0.5 * widths``, as the
            sequence path computes them).
    """

    def __init__(self, r: Tensor) -> None:
        super().__init__(r, 0, 0, 0)
        self.n_out = self.n_play

    def network_columns(self) -> list[int]:
        return [-1] * self.n_out  # its features are its columns of Yn

    def step(self, x: Tensor, xc: Tensor, Y: Tensor, Yn: Tensor, F: Tensor, I: Tensor,
             F64: Tensor, started: Tensor, parts: list[Tensor], feats: list[Tensor],
             fl: list[Tensor], il: list[Tensor], gl: list[Tensor]) -> None:
        return None  # its columns of Yn are advanced by the compensator's clamp


class PIStep(_Step):
    """Prandtl-Ishlinskii output ``w0 x + sum_i w_i y_i`` of N plays (N columns of ``Y``)."""

    def __init__(self, r: Tensor, weights: Tensor, linear_weight: Tensor) -> None:
        super().__init__(r, 0, 0, 0)
        self.register_buffer("weights", weights.detach().clone())
        self.register_buffer("linear_weight", linear_weight.detach().clone())

    def step(self, x: Tensor, xc: Tensor, Y: Tensor, Yn: Tensor, F: Tensor, I: Tensor,
             F64: Tensor, started: Tensor, parts: list[Tensor], feats: list[Tensor],
             fl: list[Tensor], il: list[Tensor], gl: list[Tensor]) -> None:
        y = Yn.narrow(1, self.y0, self.n_play)
        feats.append((self.linear_weight * x + y @ self.weights).unsqueeze(-1))


def _tables(D: int) -> dict[str, Tensor]:
    """Lookup tables of the dominant stack (depth ``D``), keyed by ``ti + D * confirm``.

    ``ti`` is the anchor index of the previous sample: a confirmed turning point pops the
    loops it closed, which is exactly the previous sample's anchor lookup, and is pushed at
    ``ti + 1`` (at ``D - 2`` after discarding entries 1 and 2 when the stack is full).
    Stack block: ``[sx (D), sf (D), 2 scratch columns]``.
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
    return {"gmap": gmap, "smap": smap, "pos": pos, "ktab": ktab,
            "off": torch.tensor([0, D])}


class BranchStep(_Step):
    """EIHO or Zhao-Tan operator with a turning-point detector, one sample at a time.

    ``F`` columns: ``[M, f_m, d, stack...]``: running extremum, branch value at it, branch
    direction (-1, 0, +1), then with ``"dominant"`` ``[sx (D), sf (D), 2 scratch]`` and
    ``I`` columns ``[top, ti]`` (top stack index, anchor index of the last sample); with
    ``"recent"`` ``[x_a]`` and one ``F64`` column, the branch value at the anchor (the
    sequence path sums the increments with ``cumsum``, which accumulates in double on the
    CPU; keeping the sum in float64 reproduces it exactly). The EIHO's detector is a column
    of ``Y``; the Zhao-Tan operator runs on ``x / scale`` and keeps its detector last in
    ``F``. The re-based (``branch``) recent-rule EIHO has a shorter step of its own: ``F``
    columns ``[M, d, x_a]``, or ``[d, x_a]`` with threshold 0, or ``[x_a, x - x_a]`` with
    threshold 0, one positive coefficient and ``eps > 0`` (the network then applies the
    coefficient: ``feature_scale``), nothing in ``I`` or ``F64``.

    Args:
        kind: ``"eiho"`` or ``"zhao_tan"``.
        rule: ``"recent"`` or ``"dominant"``.
        a: (2,) coefficients (ascending, descending), in the compensator's dtype.
        r: 0-dim detector half-width (``threshold / 2``), in the compensator's dtype.
        depth: stack size of the ``"dominant"`` rule.
        eps: linear zone of the EIHO square root.
        scale: input scale (Zhao-Tan): the operator runs on ``x / scale`` and its output
            is multiplied by ``scale``; 1.0 for the EIHO.
        slope: (2,) anchor slopes of ``EIHO(a="anchored")``: the coefficient of a branch
            anchored at ``x_e`` is ``a_d exp(slope_d x_e)``; None for a fixed ``a``.
        branch: output the re-based value ``f - f(x_e)`` (``output="branch"``).
    """

    def __init__(
        self, kind: str, rule: str, a: Tensor, r: Tensor, depth: int, eps: float, scale: float,
        slope: Tensor | None = None, branch: bool = False,
    ) -> None:
        self.eiho: bool = kind == "eiho"
        dominant = rule == "dominant"
        D = depth if dominant else 1
        n_float = 3 + (2 * D + 2 if dominant else 1) + (0 if kind == "eiho" else 1)
        # the re-based recent-rule EIHO needs neither f_m nor the float64 sum: F = [M, d, x_a],
        # and with threshold 0 the running extremum is the last sample: F = [d, x_a]
        self.fast: bool = self.eiho and not dominant and branch
        self.r_zero: bool = float(r) == 0.0
        if self.fast:
            n_float = 2 if self.r_zero else 3
        # the EIHO's detector is a play of Y, but with threshold 0 in the fast step it is the
        # previous sample: the compensator's anchored "last x" column (piece 0)
        play_r = r.reshape(1) if kind == "eiho" and not (self.fast and self.r_zero) \
            else r.new_zeros(0)
        super().__init__(play_r, n_float, 2 if dominant else 0,
                         0 if dominant or self.fast else 1)
        self.dominant: bool = dominant
        self.depth: int = D
        self.eps: float = float(eps)
        self.eps_sqrt: float = float(eps) ** 0.5
        self.scale: float = float(scale)
        self.symmetric: bool = bool(a[0] == a[1])
        # 0-dim constants in the compensator's dtype: comparing with or dividing by a Python
        # number converts it to a tensor on every call (the same values, one copy less)
        self.register_buffer("zero", a.new_zeros(()))
        self.register_buffer("eps_t", torch.tensor(self.eps, dtype=a.dtype))
        self.register_buffer("eps_sqrt_t", torch.tensor(self.eps_sqrt, dtype=a.dtype))
        self.register_buffer("a", a.detach().clone())
        self.register_buffer("a0", a[0].detach().clone())
        self.register_buffer("a1", a[1].detach().clone())
        self.register_buffer("r", r.detach().clone())
        self.anchored: bool = slope is not None
        self.branch: bool = branch
        slope = torch.zeros_like(a) if slope is None else slope.detach()
        self.register_buffer("s0", slope[0].clone())
        self.register_buffer("s1", slope[1].clone())
        tables = _tables(D) if dominant else {}
        for name in ("gmap", "smap", "pos", "ktab", "off"):
            self.register_buffer(name, tables.get(name, torch.zeros(0, dtype=torch.long)))
        # threshold-0 re-based recent EIHO with one positive coefficient and a linear zone:
        # F columns [x_a, v] (v = x - x_a), feature v / sqrt(max(|v|, eps)), a_0 folded
        # into the network's weight of this feature (``feature_scale``)
        self.a0_f: float = float(a[0])
        self.signed_v: bool = (self.fast and self.r_zero and self.symmetric
                               and not self.anchored and self.a0_f > 0 and self.eps > 0)
        #: factor the network applies to this step's feature (folded into its weights)
        self.feature_scale: float = self.a0_f if self.signed_v else 1.0
        keep = torch.ones(n_float, dtype=torch.bool)
        if not self.fast:
            keep[0] = keep[3] = keep[-1] = False  # M, x_a / sx[0], detector (Zhao-Tan)
        self.register_buffer("keep", keep)

    def pieces(self) -> list[int]:
        return [1, 1] if self.fast and self.r_zero else super().pieces()

    def anchors(self) -> tuple[list[bool], list[bool]]:
        if not self.eiho:  # anchored inside step, in units of x / scale
            return [], [False] * self.n_float
        if self.signed_v:  # [x_a, v]
            return [], [True, False]
        if self.fast:  # [d, x_a] or [M, d, x_a]
            return ([], [False, True]) if self.r_zero else ([True], [True, False, True])
        cols = [False] * self.n_float
        cols[0] = cols[3] = True
        return [True], cols

    def _g(self, u: Tensor, k: Tensor, anchor: Tensor) -> Tensor:
        """``k * g(u)`` with the coefficient of direction ``k`` (-1, 0, +1), elementwise, of a
        branch anchored at ``anchor`` (used by ``a="anchored"`` only)."""
        if self.eiho:
            big = u >= self.eps_t
            sq = torch.where(big, torch.sqrt(u), u / self.eps_sqrt_t)
            if self.anchored:
                up = k >= self.zero
                coef = torch.where(up, self.a0, self.a1) * torch.exp(
                    torch.where(up, self.s0, self.s1) * anchor)
                return k * (coef * sq)
            if self.symmetric:
                return k * (self.a0 * sq)
            return k * (torch.where(k >= self.zero, self.a0, self.a1) * sq)
        return k * ((1.0 - torch.exp(-u)) * u)

    def _step_recent_branch(self, x: Tensor, xc: Tensor, Y: Tensor, Yn: Tensor, F: Tensor,
                            parts: list[Tensor], feats: list[Tensor],
                            fl: list[Tensor]) -> None:
        """The re-based recent-rule EIHO: ``f = g_d(|m - x_a|) + g_s(relu(s (x - m)))``.

        The same arithmetic as the general step without the branch value at the anchor. With
        threshold 0 the detector follows the input, so the running extremum ``M`` is the
        previous sample (the detector's old value), ``m == x`` and the second term is
        ``g(0) = 0``: ``f = d * a_d g(|x - x_a|)`` (equal values; only the sign of a zero
        may differ).
        """
        if self.signed_v:  # threshold 0, one positive coefficient
            # columns (B, 1) throughout, pieces of the compensator's split of F: the
            # detector's old value (the previous sample, anchored), x_a and v = x_prev - x_a.
            # The branch direction is the sign of v (v is 0 only before the first move): a
            # move against it is a confirmed turning point, anchored at the previous sample.
            # copysign compares sign bits without a product (no underflow); a zero move is
            # never a turn.
            p_old, xa_prev, v_prev = parts[0], parts[self.p0], parts[self.p0 + 1]
            delta = xc - p_old
            x_a = torch.where(torch.copysign(delta, v_prev) != delta, p_old, xa_prev)
            v = xc - x_a
            # sign(v) g(|v|) = v / sqrt(max(|v|, eps)) (the coefficient a_0 is in the head)
            feats.append(v * torch.rsqrt(torch.clamp_min(v.abs(), self.eps)))
            fl.append(x_a)
            fl.append(v)
            return
        if self.r_zero:
            # columns (B, 1) throughout: no select, stack or unsqueeze; the detector's old
            # value (the previous sample), d and x_a are pieces of the compensator's split
            p_old, d_prev, xa_prev = parts[0], parts[self.p0], parts[self.p0 + 1]
            move = torch.sign(xc - p_old)
            d = torch.sign(torch.add(d_prev, move, alpha=2.0))
            # a confirmed turning point is a change of d from -d_prev; the only other change,
            # the first move (d_prev = 0), finds p_old == x_a (both anchored at the first
            # sample, no move since), so anchoring there at p_old gives the same value
            x_a = torch.where(d != d_prev, p_old, xa_prev)
            feats.append(self._g((xc - x_a).abs(), d, x_a))
            fl.append(d)
            fl.append(x_a)
            return
        p_old = Y.select(1, self.y0)
        blk = F.narrow(1, self.f0, self.n_float)
        M, d_prev, xa_prev = blk.select(1, 0), blk.select(1, 1), blk.select(1, 2)
        move = torch.sign(Yn.select(1, self.y0) - p_old)
        confirm = move * d_prev < self.zero
        d = torch.sign(torch.add(d_prev, move, alpha=2.0))
        m = torch.where(move != self.zero, x, M)
        x_a = torch.where(confirm, M, xa_prev)
        xm = x - m
        s = torch.sign(torch.sub(torch.sign(xm), d, alpha=2.0))
        u = torch.stack([(m - x_a).abs(), torch.relu(s * xm)], 1)
        anchor = torch.stack([x_a, m], 1) if self.anchored else u
        gg = self._g(u, torch.stack([d, s], 1), anchor)
        f = gg.select(1, 0) + gg.select(1, 1)
        fl.append(torch.stack([m, d, x_a], 1))
        feats.append(f.unsqueeze(1))

    def step(self, x: Tensor, xc: Tensor, Y: Tensor, Yn: Tensor, F: Tensor, I: Tensor,
             F64: Tensor, started: Tensor, parts: list[Tensor], feats: list[Tensor],
             fl: list[Tensor], il: list[Tensor], gl: list[Tensor]) -> None:
        if self.fast:
            self._step_recent_branch(x, xc, Y, Yn, F, parts, feats, fl)
            return
        blk = F.narrow(1, self.f0, self.n_float)
        if self.eiho:
            p_old, p_new = Y.select(1, self.y0), Yn.select(1, self.y0)
        else:
            x = x / self.scale
            # a row's first finite sample anchors its fresh state
            blk = torch.where(started | self.keep, blk, x.unsqueeze(1))
            p_old = blk.select(1, self.n_float - 1)
            p_new = torch.clamp(p_old, x - self.r, x + self.r)
        M, d_prev = blk.select(1, 0), blk.select(1, 2)
        move = torch.sign(p_new - p_old)
        confirm = move * d_prev < self.zero
        d = torch.sign(torch.add(d_prev, move, alpha=2.0))
        m = torch.where(move != self.zero, x, M)
        if self.dominant:
            D = self.depth
            top, ti_prev = I.select(1, self.i0), I.select(1, self.i0 + 1)
            key = torch.add(ti_prev, confirm, alpha=D)
            # push the confirmed turning point (v, f(v)) = (M, f_m) of the last sample
            S = blk.narrow(1, 3, 2 * D + 2).gather(1, self.gmap.index_select(0, key))
            S = S.scatter(1, self.smap.index_select(0, key), blk.narrow(1, 0, 2))
            top = torch.where(confirm, self.pos.index_select(0, ti_prev), top)
            # anchor: pop the nested loops closed by the running extremum m
            passed = (m.unsqueeze(1) - S.narrow(1, 0, D)) * d.unsqueeze(1) >= self.zero
            ti = torch.where(passed, self.ktab.index_select(0, top), top.unsqueeze(1)).amin(1)
            xf = S.gather(1, ti.unsqueeze(1) + self.off)
            x_a, f_a = xf.select(1, 0), xf.select(1, 1)
            il.append(top.unsqueeze(1))
            il.append(ti.unsqueeze(1))
        else:
            xa_prev = blk.select(1, 3)
            inc = self._g((M - xa_prev).abs(), d_prev, xa_prev)
            sf = F64.narrow(1, self.g0, 1) + torch.where(
                confirm, inc, torch.zeros_like(inc)).to(torch.float64).unsqueeze(1)
            x_a = torch.where(confirm, M, xa_prev)
            f_a = sf.select(1, 0).to(x.dtype)
            S = x_a.unsqueeze(1)
            gl.append(sf)
        xm = x - m
        s = torch.sign(torch.sub(torch.sign(xm), d, alpha=2.0))  # -d, or sign(x - m) if d = 0
        gg = self._g(torch.stack([(m - x_a).abs(), torch.relu(s * xm)], 1),
                     torch.stack([d, s], 1), torch.stack([x_a, m], 1))
        f_m = f_a + gg.select(1, 0)
        f = (gg.select(1, 0) if self.branch else f_m) + gg.select(1, 1)  # branch: f - f(x_e)
        fl.append(torch.stack([m, f_m, d], 1))
        fl.append(S)
        if not self.eiho:
            fl.append(p_new.unsqueeze(1))
            f = f * self.scale
        feats.append(f.unsqueeze(1))
