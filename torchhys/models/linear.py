"""The linear baseline: a transfer function between scaled signals, fitted by output error.

:func:`fit_linear` fits ``B(z) / A(z)`` of a given order: an ARX least-squares fit (equation
error, one linear solve) gives the start, then L-BFGS minimises the simulation (output)
error over the whole record with :class:`torchhys.dynamics.TransferFunction` (stable
parametrization, the compiled lfilter). An unstable ARX start falls back to the block's
default (poles of modulus 0.5).

References:
    L. Ljung, System Identification: Theory for the User, 2nd ed., 1999, Secs. 4.2 and 7.3
    (ARX and output-error models).
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence, check_int, check_state
from torchhys.dynamics import TransferFunction
from torchhys.models._common import check_fs, scale_buffer

__all__ = ["LinearModel", "fit_linear"]


class LinearModel(nn.Module):
    """``y = y_scale G(z) (u / u_scale)`` with a :class:`~torchhys.dynamics.TransferFunction`
    G of the given order (with feedthrough).

    Shape:
        - u: (time,) or (batch, time)
        - state: the DF2T delays, (order,) or (batch, order); zeros if None
        - returns ``(y, state)``.
    """

    def __init__(self, order: int = 2, *, fs: float, u_scale: float = 1.0,
                 y_scale: float = 1.0, max_pole_radius: float = 0.999) -> None:
        super().__init__()
        self.order = check_int(order, "order", minimum=1)
        self.fs = check_fs(fs, "fs")
        self.state_size = self.order
        self.G = TransferFunction(self.order, max_pole_radius=max_pole_radius).double()
        self.register_buffer("u_scale", scale_buffer(u_scale, "u_scale"))
        self.register_buffer("y_scale", scale_buffer(y_scale, "y_scale"))

    def config(self) -> dict[str, object]:
        """Constructor arguments that rebuild the module (load the state dict after)."""
        return {"order": self.order, "fs": self.fs, "max_pole_radius": self.G.max_pole_radius}

    def forward(self, u: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        ub, squeezed = as_batched_sequence(u, "u")
        start = None if state is None else check_state(state, ub.shape[0], self.order, ub)
        y, s = self.G(ub / self.u_scale.to(ub.dtype), start)
        y = y * self.y_scale.to(ub.dtype)
        return (y[0], s[0]) if squeezed else (y, s)


def fit_linear(u: Tensor, y: Tensor, *, order: int, fs: float, iterations: int = 200
               ) -> LinearModel:
    """Fit a :class:`LinearModel` to one record by ARX, then output error (L-BFGS).

    Args:
        u, y: input and output, (time,), float64, finite.
        order: number of poles.
        fs: the record's sampling frequency (Hz).
        iterations: L-BFGS iterations on the simulation error.

    Returns:
        The fitted model (scales: the standard deviations of u and y).
    """
    ub, _ = as_batched_sequence(u, "u")
    yb, _ = as_batched_sequence(y, "y")
    u1, y1 = ub[0].double(), yb[0].double()
    model = LinearModel(order, fs=fs, u_scale=float(u1.std()), y_scale=float(y1.std()))
    un, yn = u1 / model.u_scale, y1 / model.y_scale
    n, T = order, u1.shape[0]
    if T <= 3 * n + 1:
        raise ValueError(f"the record must be longer than 3 order + 1 = {3 * n + 1} samples, "
                         f"got {T}")
    regressors = [-yn[n - k: T - k] for k in range(1, n + 1)]
    regressors += [un[n - k: T - k] for k in range(0, n + 1)]
    theta = torch.linalg.lstsq(torch.stack(regressors, 1), yn[n:].unsqueeze(1)).solution[:, 0]
    try:
        G = TransferFunction.from_coefficients(theta[n:], torch.cat([theta.new_ones(1),
                                                                     theta[:n]]))
        model.G = G  # its pole bound too (not part of the state dict)
    except ValueError:  # an unstable ARX fit: start from the default block
        pass
    opt = torch.optim.LBFGS(model.G.parameters(), max_iter=iterations, history_size=50,
                            line_search_fn="strong_wolfe", tolerance_grad=1e-12,
                            tolerance_change=1e-15)

    def closure() -> Tensor:
        opt.zero_grad()
        loss = (model.G(un)[0] - yn).square().mean()
        loss.backward()
        return loss

    opt.step(closure)
    return model
