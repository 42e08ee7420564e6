"""Per-sample steps of the deployable operators, written for TorchScript and ``torch.export``.

Each step module is a pure function of one input sample and an explicit state (a list of
tensors, all zeros when fresh): ``step(x, state, started) -> (out (B, n_out), state)``.
No Python control flow depends on tensor values; branches are ``torch.where`` and the
dominant stack is a fixed-size tensor updated with masks. The arithmetic repeats the
sequence implementations (:mod:`torchhys.functional.backlash`,
:mod:`torchhys.functional._branch`) operation by operation, so a step-by-step run equals
the sequence ``forward`` to float rounding (bit for bit in the tests that allow it).

``started`` (B,) tells whether the row has seen a finite sample before this one: the branch
operators anchor their fresh state at the first sample, so rows that have not started are
re-anchored at the current one.
"""


import torch
from torch import Tensor, nn

__all__ = ["BranchStep", "PIStep", "PlayStep"]


class PlayStep(nn.Module):
    """N play operators: ``y = min(max(y_prev, x - r), x + r)``; state ``[y (B, N)]``.

    Args:
        r: half-widths, shape (N,), in the compensator's dtype (``0.5 * widths``, as the
            sequence path computes them).
    """

    def __init__(self, r: Tensor) -> None:
        super().__init__()
        self.register_buffer("r", r.detach().clone())
        self.n_out: int = int(r.shape[0])

    def state_spec(self) -> list[tuple[list[int], torch.dtype]]:
        return [([self.n_out], self.r.dtype)]

    def step(self, x: Tensor, state: list[Tensor], started: Tensor) -> tuple[Tensor, list[Tensor]]:
        xc = x.unsqueeze(-1)
        y = torch.minimum(torch.maximum(state[0], xc - self.r), xc + self.r)
        return y, [y]


class PIStep(PlayStep):
    """Prandtl-Ishlinskii output ``w0 x + sum_i w_i y_i`` of N plays; state ``[y (B, N)]``."""

    def __init__(self, r: Tensor, weights: Tensor, linear_weight: Tensor) -> None:
        super().__init__(r)
        self.register_buffer("weights", weights.detach().clone())
        self.register_buffer("linear_weight", linear_weight.detach().clone())
        self.n_out = 1

    def state_spec(self) -> list[tuple[list[int], torch.dtype]]:
        return [([int(self.r.shape[0])], self.r.dtype)]

    def step(self, x: Tensor, state: list[Tensor], started: Tensor) -> tuple[Tensor, list[Tensor]]:
        xc = x.unsqueeze(-1)
        y = torch.minimum(torch.maximum(state[0], xc - self.r), xc + self.r)
        return (self.linear_weight * x + y @ self.weights).unsqueeze(-1), [y]


def _safe_sqrt(u: Tensor, eps: float) -> Tensor:
    big = u >= eps
    return torch.where(big, torch.sqrt(torch.where(big, u, torch.ones_like(u))), u / eps**0.5)


class BranchStep(nn.Module):
    """EIHO or Zhao-Tan operator with a turning-point detector, one sample at a time.

    State (batch B, stack size D; D = 1 for ``"recent"``):
    ``[play (B,), direction (B,) long, extremum (B,), stack_x (B, D), stack_f (B, D),
    top (B,) long]``; ``top`` is the index of the top stack entry (depth - 1). With the
    ``"recent"`` rule ``stack_f`` is float64: the sequence path sums the branch increments
    with ``cumsum``, which accumulates in double precision on the CPU; keeping the sum in
    float64 reproduces it exactly.

    Args:
        kind: ``"eiho"`` or ``"zhao_tan"``.
        rule: ``"recent"`` or ``"dominant"``.
        a: (2,) coefficients (ascending, descending), in the compensator's dtype.
        r: 0-dim detector half-width (``threshold / 2``), in the compensator's dtype.
        depth: stack size of the ``"dominant"`` rule.
        eps: linear zone of the EIHO square root.
        scale: input scale (Zhao-Tan): the operator runs on ``x / scale`` and its output
            is multiplied by ``scale``; 1.0 for the EIHO.
    """

    def __init__(
        self, kind: str, rule: str, a: Tensor, r: Tensor, depth: int, eps: float, scale: float
    ) -> None:
        super().__init__()
        self.eiho: bool = kind == "eiho"
        self.dominant: bool = rule == "dominant"
        self.depth: int = depth if self.dominant else 1
        self.eps: float = float(eps)
        self.scale: float = float(scale)
        self.register_buffer("a", a.detach().clone())
        self.register_buffer("r", r.detach().clone())
        self.register_buffer("index", torch.arange(self.depth))
        self.n_out: int = 1

    def state_spec(self) -> list[tuple[list[int], torch.dtype]]:
        dt, long = self.a.dtype, torch.long
        f_dtype = dt if self.dominant else torch.float64
        return [([], dt), ([], long), ([], dt), ([self.depth], dt), ([self.depth], f_dtype),
                ([], long)]

    def _g(self, u: Tensor, coef: Tensor) -> Tensor:
        if self.eiho:
            return coef * _safe_sqrt(u, self.eps)
        return (1.0 - torch.exp(-u)) * u

    def _coef(self, direction: Tensor) -> Tensor:
        return torch.where(direction >= 0, self.a[0], self.a[1])

    def _pops(self, stack_x: Tensor, top: Tensor, m: Tensor, d: Tensor) -> Tensor:
        """Number of nested minor loops closed by the running extremum ``m`` (as the sequence)."""
        i = self.index
        t = top.unsqueeze(-1)
        cand = (i <= t - 1) & (i >= 1) & ((t - 1 - i) % 2 == 0) & (d != 0).unsqueeze(-1)
        passed = (d.unsqueeze(-1) * (m.unsqueeze(-1) - stack_x)) >= 0
        failed = torch.where(cand & ~passed, i, -1).amax(dim=-1, keepdim=True)
        return (cand & (i > failed)).sum(dim=-1)

    def _push(
        self, sx: Tensor, sf: Tensor, top: Tensor, v: Tensor, d_prev: Tensor, confirm: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Dominant rule: pop the loops closed by ``v``, push the turning point ``v``."""
        top0 = top
        top = top - 2 * self._pops(sx, top, v, d_prev)
        ti = top.unsqueeze(-1)
        ax, af = sx.gather(1, ti).squeeze(1), sf.gather(1, ti).squeeze(1)
        fv = af + d_prev * self._g((v - ax).abs(), self._coef(d_prev))
        pos = top + 1
        full = pos >= self.depth
        pos = torch.where(full, pos - 2, pos)
        hot = self.index == pos.unsqueeze(-1)
        c, f = confirm.unsqueeze(-1), full.unsqueeze(-1)
        out: list[Tensor] = []
        for t, val in ((sx, v), (sf, fv)):
            shifted = torch.where(f, torch.cat([t[:, :1], t[:, 3:], t[:, -2:]], 1), t)
            out.append(torch.where(c, torch.where(hot, val.unsqueeze(-1), shifted), t))
        return out[0], out[1], torch.where(confirm, pos, top0)

    def step(self, x: Tensor, state: list[Tensor], started: Tensor) -> tuple[Tensor, list[Tensor]]:
        if self.scale != 1.0:
            x = x / self.scale
        play, d_prev, ext, sx, sf, top = state
        # a row's first finite sample anchors its fresh state
        play = torch.where(started, play, x)
        ext = torch.where(started, ext, x)
        sx = torch.where((self.index == 0) & ~started.unsqueeze(-1), x.unsqueeze(-1), sx)
        # turning-point detector: the play operator of full width `threshold`
        p = torch.minimum(torch.maximum(play, x - self.r), x + self.r)
        move = torch.sign(p - play).to(torch.long)
        moving = move != 0
        d = torch.where(moving, move, d_prev)
        confirm = moving & (d_prev != 0) & (move != d_prev)
        v = ext
        m = torch.where(moving, x, ext)
        if self.dominant:
            sx, sf, top = self._push(sx, sf, top, v, d_prev, confirm)
            ti = (top - 2 * self._pops(sx, top, m, d)).unsqueeze(-1)
            x_a, f_a = sx.gather(1, ti).squeeze(1), sf.gather(1, ti).squeeze(1)
        else:
            xa_prev = sx[:, 0]
            inc = d_prev * self._g((v - xa_prev).abs(), self._coef(d_prev))
            sf = sf + torch.where(confirm, inc, torch.zeros_like(inc)).to(sf.dtype).unsqueeze(-1)
            x_a = torch.where(confirm, v, xa_prev)
            sx = x_a.unsqueeze(-1)
            f_a = sf[:, 0].to(x.dtype)
        f_m = f_a + d * self._g((m - x_a).abs(), self._coef(d))
        s = torch.where(d != 0, -d, torch.sign(x - m).to(torch.long))
        u = torch.relu(s * (x - m))
        f = f_m + s * self._g(u, self._coef(s))
        if self.scale != 1.0:
            f = f * self.scale
        return f.unsqueeze(-1), [p, d, m, sx, sf, top]
