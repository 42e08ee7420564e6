"""Starting values for :class:`~torchhys.models.block_oriented.HysteresisFeedback`.

From a linear model ``G = B / A`` (the best linear approximation, fitted by output error):
part of its stiffness is moved into the feedback. With the element linear, ``z = v = y``
(slopes 1, its initial state), and

    G_u = B / (A - k C),    G_z = -k C / (A - k C),    C = B - b_0    (strictly proper),

the loop ``y = G_u u + G_z z`` has the transfer function ``B / A``: the model starts as the
linear one, exactly. ``k`` is ``fraction / G(1)``, a fraction of the static stiffness
(scaled units); the open loop ``A - k C`` is then the softer plant of which the element
carries the rest. The simulation error then shapes the element away from linear
(:func:`~torchhys.models.windows.fit_windows`); starting from zero feedback instead leaves
the element's parameters without a gradient.
"""

from __future__ import annotations

import numpy as np
import torch

from torchhys.dynamics import TransferFunction
from torchhys.models.block_oriented import HysteresisFeedback

__all__ = ["grey_box_start", "init_from_linear"]


@torch.no_grad()
def init_from_linear(model: HysteresisFeedback, G: TransferFunction, *,
                     fraction: float = 0.5) -> None:
    """Make ``model`` equal to the linear ``G`` (scaled units) with ``fraction`` of its
    static stiffness in the feedback (module docstring).

    Args:
        model: the model (its element must start linear, ``z = v``: its initial state).
        G: a transfer function of the model's order, from ``u / u_scale`` to
            ``y / y_scale``.
        fraction: the part of the static stiffness moved into the loop, in [0, 1).

    Raises:
        ValueError: a wrong order, a fraction out of range, an open loop ``A - k C`` that is
            not stable (lower the fraction).
    """
    if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) \
            or not 0 <= fraction < 1:
        raise ValueError(f"fraction must be a float in [0, 1), got {fraction!r}")
    if G.order != model.order:
        raise ValueError(f"G must have the model's order {model.order}, got {G.order}")
    b, a = (c.detach().double() for c in G.coefficients())
    gain = float(b.sum() / a.sum())
    k = fraction / gain
    c = b.clone()
    c[0] = 0.0
    a_open = a - k * c
    b_z = -k * c if fraction > 0 else c.new_zeros(c.shape)
    try:
        model.set_blocks(b, b_z, a_open)
    except ValueError as e:
        raise ValueError(f"fraction = {fraction} gives an unstable open loop A - k C ({e}); "
                         "use a smaller fraction") from e



def grey_box_start(G: TransferFunction, *, u_scale: float, y_scale: float, fs: float,
                   fraction: float = 0.5) -> dict[str, float]:
    """Starting coefficients of :class:`~torchhys.models.BoucWenOscillator` from a
    second-order linear model ``G`` (scaled units): its pole pair as ``m``, ``c`` and the
    static stiffness ``k + alpha``, split ``1 - fraction`` / ``fraction``; the Bouc-Wen
    shape products 0 (the model starts linear).

    Raises:
        ValueError: G not of order 2, or without a complex pole pair.
    """
    if G.order != 2:
        raise ValueError(f"G must have order 2 (one pole pair), got {G.order}")
    b, a = (c.detach().double() for c in G.coefficients())
    pole = complex(np.roots(a.numpy())[0])
    if pole.imag == 0:
        raise ValueError(f"G must have a complex pole pair (an oscillator), got poles "
                         f"{np.roots(a.numpy())}")
    s = np.log(pole) * fs
    wn, zeta = abs(s), -s.real / abs(s)
    k_total = u_scale / (y_scale * float(b.sum() / a.sum()))
    m = k_total / wn**2
    return {"m": m, "c": 2 * zeta * wn * m, "k": (1 - fraction) * k_total,
            "alpha": fraction * k_total, "beta_gamma": 0.0, "beta_delta": 0.0}
