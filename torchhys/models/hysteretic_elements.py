"""Hysteretic elements for feedback loops: one sample at a time, with an explicit state.

A loop needs the element's output at sample t before it can advance the linear block, so an
element here is a per-sample step ``step(v, state) -> (z, state)`` on ``v`` (batch, 1); its
sequence path (:meth:`forward`) loops over that step. Both elements are rate-independent:
they see the path of ``v``, not its timing.

- :class:`DuhemHysteresis`: a Duhem operator, ``dz = g_up(z) dv`` while ``v`` rises and
  ``g_down(z) dv`` while it falls, with slopes ``g = a + b z + c |z|`` (plus a small network
  of z where ``hidden > 0``), integrated along a straight path from ``v[t-1]`` to ``v[t]``
  by one RK4 step in ``v`` (the scheme of :func:`torchhys.plants.bouc_wen_state`). The
  Bouc-Wen operator with exponent 1, ``dz = alpha dv - bg |dv| z - bd dv |z|``, is the case
  ``g_up = alpha - bg z - bd |z|``, ``g_down = alpha + bg z - bd |z|``.
  State ``(batch, 2)``: z and the previous v.
- :class:`PlayHysteresis`: a generalised Prandtl-Ishlinskii operator, a linear combination
  of v and N plays of v (the widths of a :class:`torchhys.Backlash`, the step
  :func:`~torchhys.functional.play_step`) plus a small tanh network of them. State
  ``(batch, N)``: the play outputs. Its minor loops are congruent (a Prandtl-Ishlinskii
  property), which the Bouc-Wen operator's are not.

References:
    P. Duhem (1897); J. W. Macki, P. Nistri, P. Zecca, "Mathematical models for hysteresis",
    SIAM Review 35 (1993) (the Duhem model); Ismail, Ikhouane, Rodellar (2009) (Bouc-Wen as
    a Duhem model); Krejci, Kuhnen (2001) (Prandtl-Ishlinskii).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchhys._checks import check_int
from torchhys.functional.backlash import play_step
from torchhys.operators.backlash import Backlash

__all__ = ["DuhemHysteresis", "PlayHysteresis"]


def _zero_last(net: nn.Sequential) -> nn.Sequential:
    nn.init.zeros_(net[-1].weight)
    nn.init.zeros_(net[-1].bias)
    return net


class _Element(nn.Module):
    state_size: int

    def step(self, v: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        raise NotImplementedError

    def forward(self, v: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """v (batch, time) -> z (batch, time) and the state after the last sample."""
        s = v.new_zeros(v.shape[0], self.state_size) if state is None else state
        zs = []
        for v_t in v.unbind(1):
            z, s = self.step(v_t.unsqueeze(1), s)
            zs.append(z)
        return torch.cat(zs, dim=1), s


class DuhemHysteresis(_Element):
    """The Duhem operator with affine-in-|z| slopes (module docstring).

    Args:
        hidden: tanh units of the slope network (0: the affine slopes only).

    Initialised with slopes 1 (``z = v`` from rest).
    """

    state_size = 2

    def __init__(self, hidden: int = 0) -> None:
        super().__init__()
        self.hidden = check_int(hidden, "hidden", minimum=0)
        # rows: up, down; columns: 1, z, |z|
        self.coef = nn.Parameter(torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]))
        if self.hidden:
            self.net = _zero_last(nn.Sequential(nn.Linear(1, hidden), nn.Tanh(),
                                                nn.Linear(hidden, 2)))

    def config(self) -> dict[str, object]:
        return {"kind": "duhem", "hidden": self.hidden}

    def step(self, v: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        z, v_prev = state[:, :1], state[:, 1:]
        dv = v - v_prev
        up = dv.clamp_min(0.0)
        move = torch.cat([up, dv - up], dim=1)  # (B, 2); at dv = 0 the gradient goes one way
        c = move @ self.coef.to(v.dtype)                                    # (B, 3)
        c0, c1, c2 = c[:, :1], c[:, 1:2], c[:, 2:]
        net = self.net if self.hidden else None

        def slope(z: Tensor) -> Tensor:  # dz over the whole step, at z
            out = torch.addcmul(torch.addcmul(c0, c1, z), c2, z.abs())
            if net is not None:
                out = out + (net(z) * move).sum(1, keepdim=True)
            return out

        k1 = slope(z)
        k2 = slope(z + 0.5 * k1)
        k3 = slope(z + 0.5 * k2)
        k4 = slope(z + k3)
        z = z + (k1 + k4 + 2 * (k2 + k3)) / 6
        return z, torch.cat([z, v], dim=1)


class PlayHysteresis(_Element):
    """A generalised Prandtl-Ishlinskii operator: ``z = w . (v, p) + MLP(v, p)``.

    Args:
        widths: initial full dead-band widths of the N plays (learnable), (N,).
        hidden: tanh units of the network (0: the linear combination only).

    Initialised with ``z = v``.
    """

    def __init__(self, widths: Tensor | list[float], hidden: int = 16) -> None:
        super().__init__()
        self.plays = Backlash(torch.as_tensor(widths, dtype=torch.float64), learnable=True)
        self.state_size = self.plays.n_operators
        self.hidden = check_int(hidden, "hidden", minimum=0)
        k = 1 + self.state_size
        self.w = nn.Parameter(torch.cat([torch.ones(1, 1), torch.zeros(k - 1, 1)]))
        if self.hidden:
            self.net = _zero_last(nn.Sequential(nn.Linear(k, hidden), nn.Tanh(),
                                                nn.Linear(hidden, 1)))

    def config(self) -> dict[str, object]:
        return {"kind": "plays", "widths": [0.0] * self.state_size, "hidden": self.hidden}

    def step(self, v: Tensor, state: Tensor) -> tuple[Tensor, Tensor]:
        p = play_step(v, (0.5 * self.plays.get_widths()).to(v.dtype), state)
        features = torch.cat([v, p], dim=1)
        z = features @ self.w.to(v.dtype)
        if self.hidden:
            z = z + self.net(features)
        return z, p


def make_element(config: dict[str, object]) -> DuhemHysteresis | PlayHysteresis:
    """An element from its ``config()``."""
    options = dict(config)
    kind = options.pop("kind", None)
    if kind == "duhem":
        return DuhemHysteresis(**options)
    if kind == "plays":
        return PlayHysteresis(**options)
    raise ValueError(f"element kind must be 'duhem' or 'plays', got {kind!r}")
