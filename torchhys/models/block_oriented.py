"""A block-oriented model with hysteresis: a linear block with a hysteretic feedback.

:class:`HysteresisFeedback` is a Lur'e-type structure: the output is the sum of a linear
block of the input and a strictly proper linear block of a hysteretic force ``z`` of the
output itself::

    y[t] = G_u(q) u[t] + G_z(q) z[t]          (G_z strictly proper: no algebraic loop)
    z[t] = H[y](t)                            (a hysteretic element, rate-independent)

``G_u`` and ``G_z`` are :class:`torchhys.dynamics.TransferFunction` blocks (stable, poles in
second-order sections); ``H`` is a feedback element
(:class:`~torchhys.operators.feedback_element.FeedbackElement`: a
:class:`~torchhys.operators.duhem.DuhemHysteresis` or a
:class:`~torchhys.operators.play_hysteresis.PlayHysteresis`). Signals
are scaled inside (``u / u_scale``, ``y / y_scale``, so ``H`` sees numbers of order one).

It contains the Bouc-Wen oscillator, ``y = G (u - z)``, ``z = BW[y]``, up to sampling, but
assumes only a linear system with a hysteretic feedback of its output.

Sequence path: ``G_u u`` is one :func:`~torchhys.functional.lfilter` call over the whole
sequence; the loop runs ``H`` and the DF2T step of ``G_z``
(:func:`~torchhys.functional.linear_filter.df2t_step`, the maths of the block's sequence
path), one sample at a time. State ``(batch, n_u + n_z + h)``: the delays of ``G_u``, of
``G_z`` and the element's state. ``None``: at rest.

Identification: start from a linear model with part of its stiffness in the loop
(:func:`torchhys.models.starting_values.init_from_linear`), then minimise the simulation
error by windows (:func:`torchhys.models.windows.fit_windows`).

References:
    M. Schoukens, K. Tiels, "Identification of block-oriented nonlinear systems starting from
    linear approximations: a survey", Automatica 85 (2017).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence, check_int, check_state
from torchhys.dynamics import TransferFunction
from torchhys.functional.linear_filter import df2t_step
from torchhys.models._common import check_fs, scale_buffer
from torchhys.operators.feedback_element import FeedbackElement
from torchhys.registry import make_operator

__all__ = ["HysteresisFeedback"]


class HysteresisFeedback(nn.Module):
    """``y = G_u u + G_z H[y]`` (module docstring).

    Args:
        order: order of ``G_u`` and ``G_z``.
        element: the feedback element, as an operator spec
            (:func:`torchhys.registry.make_operator`), e.g. ``{"name": "duhem", "hidden": 0}``
            (the default) or ``{"name": "play_hysteresis", "widths": [...], "hidden": 16}``,
            or a :class:`~torchhys.operators.feedback_element.FeedbackElement`.
        fs: sampling frequency the model is identified at (Hz).
        u_scale, y_scale: the input and output units (e.g. their standard deviations).
        max_pole_radius: the pole bounds of ``G_u`` and ``G_z`` (:meth:`set_blocks` may
            raise them; :meth:`config` gives them).

    Shape:
        - u: (time,) or (batch, time)
        - state: (state_size,) or (batch, state_size); zeros (rest) if None
        - returns ``(y, state)``: y of u's shape, the state after the last sample.
    """

    def __init__(self, order: int = 2, element: str | dict[str, object] | FeedbackElement |
                 None = None, *,
                 fs: float, u_scale: float = 1.0, y_scale: float = 1.0,
                 max_pole_radius: Sequence[float] = (0.999, 0.999)) -> None:
        super().__init__()
        self.order = check_int(order, "order", minimum=1)
        self.fs = check_fs(fs, "fs")
        r_u, r_z = max_pole_radius
        self.G_u = TransferFunction(self.order, max_pole_radius=r_u)
        self.G_z = TransferFunction(self.order, feedthrough=False, max_pole_radius=r_z)
        self.H = make_operator({"name": "duhem", "hidden": 0} if element is None else element,
                               argument="element")
        if not isinstance(self.H, FeedbackElement):
            raise TypeError(f"element must be a feedback element (an operator with a "
                            f"per-sample step(v, state): 'duhem' or 'play_hysteresis'), got "
                            f"{type(self.H).__name__}")
        self.state_size = 2 * self.order + self.H.state_size
        self.register_buffer("u_scale", scale_buffer(u_scale, "u_scale"))
        self.register_buffer("y_scale", scale_buffer(y_scale, "y_scale"))
        with torch.no_grad():
            self.G_z.numerator.zero_()  # no feedback at first
        self.double()

    def config(self) -> dict[str, object]:
        """Constructor arguments that rebuild the module (load the state dict after)."""
        return {"order": self.order, "element": self.H.config(), "fs": self.fs,
                "max_pole_radius": [self.G_u.max_pole_radius, self.G_z.max_pole_radius]}

    @torch.no_grad()
    def set_blocks(self, b_u: Tensor, b_z: Tensor, a: Tensor) -> None:
        """Set ``G_u = b_u / a`` and ``G_z = b_z / a`` (lfilter's convention, ``b_z[0] = 0``).

        Raises:
            ValueError: an unstable ``a`` (its pole moduli), or a wrong order.
        """
        for name, b, ft in (("G_u", b_u, True), ("G_z", b_z, False)):
            block = TransferFunction.from_coefficients(b, a, feedthrough=ft)
            if block.order != self.order:
                raise ValueError(f"{name} must have order {self.order}, got {block.order}")
            setattr(self, name, block)

    def forward(self, u: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        ub, squeezed = as_batched_sequence(u, "u")
        B, n = ub.shape[0], self.order
        start = (ub.new_zeros(B, self.state_size) if state is None
                 else check_state(state, B, self.state_size, ub))
        y_u, zf_u = self.G_u(ub / self.u_scale.to(ub.dtype), start[:, :n])
        b, a = (c.to(ub.dtype) for c in self.G_z.coefficients())
        a = a[1:]
        s_z, s_h = start[:, n: 2 * n], start[:, 2 * n:]
        outs = []
        for yu_t in y_u.unbind(1):
            y_t = yu_t.unsqueeze(1) + s_z[:, :1]      # G_z is strictly proper
            outs.append(y_t)
            z_t, s_h = self.H.step(y_t, s_h)
            s_z = df2t_step(z_t, s_z, b, a)[1]
        y = torch.cat(outs, dim=1) * self.y_scale.to(ub.dtype)
        new_state = torch.cat([zf_u, s_z, s_h], dim=1)
        return (y[0], new_state[0]) if squeezed else (y, new_state)
