"""Bouc-Wen hysteresis plant driven by a sampled input.

Model (the form of the survey by Ismail, Ikhouane and Rodellar, 2009)::

    y(t)  = k_x u(t) + k_w w(t)
    dw/dt = A du/dt - beta |du/dt| |w|^(n-1) w - gamma du/dt |w|^n

Between samples the input is interpolated linearly, so ``du/dt`` is constant on each
sample interval and the right-hand side has kinks at the samples. On such an interval
``dw/dt = (du/dt) g(w)`` with ``g`` fixed, so ``w`` only depends on the input *path*:
the sampled response is rate-independent and does not depend on ``t`` (any strictly
increasing ``t`` gives the same output). The default solver exploits this: one classic
Runge-Kutta-4 step (or ``substeps`` of them) in the input variable per sample interval,
which equals RK4 in time on the sample grid. The adaptive solvers of ``torchdiffeq``
(``method="dopri5"`` etc.) are available too and are told about the kinks through
``jump_t``; they are several times slower (every sample restarts the step) and serve as
a cross-check. Cost is one Python-level step per sample; with autograd the backward pass
dominates.

The piezo form of Low and Guo (1995), ``y = d_p u - h`` with
``dh/dt = alpha d_p du/dt - beta |du/dt| h |h|^(n-1) - gamma du/dt |h|^n``, is the case
``k_x = d_p``, ``k_w = -1``, ``A = alpha d_p``.

References:
    M. Ismail, F. Ikhouane, J. Rodellar, "The hysteresis Bouc-Wen model, a survey",
    Archives of Computational Methods in Engineering 16 (2009) 161-188.
    M. Low, N. Guo, "Modeling of a piezoelectric actuator using the Bouc-Wen model",
    1995 (piezo form above).
"""

from __future__ import annotations

import bisect
import math

import torch
from torch import Tensor, nn

from torchhys._checks import check_choice, check_int

__all__ = ["BoucWen", "bouc_wen", "bouc_wen_state", "DEFAULTS"]

DEFAULTS: dict[str, float] = {
    "A": 0.5, "beta": 0.3, "gamma": 0.1, "n": 1.0, "k_x": 1.0, "k_w": -1.0,
}
"""Default coefficients: Low and Guo's piezo form with ``d_p = 1``, ``alpha = 0.5``.

``w`` alone traverses clockwise loops (the restoring-force loops of structural mechanics);
``k_w = -1`` makes ``y`` lag ``u`` in a counter-clockwise, piezo-like loop whose branches
stay monotone because ``k_x > A + (beta - gamma) A / (beta + gamma)``. ``|w|`` stays below
``A / (beta + gamma) = 1.25``. For ``u = 6 sin(t)`` the output spans about +-4.77 and the
loop is about 2.0 wide at ``u = 0`` (21 % of the output range); on the paper's input
``4 sin(0.5 t) + 2 sin(3 t)`` (+-5.87) from ``w0 = 0`` it spans about -4.97 .. 4.83.
"""

_ADAPTIVE = ("dopri5", "dopri8", "bosh3", "fehlberg2", "adaptive_heun")
_METHODS = ("rk4",) + _ADAPTIVE


def _scalar(name: str, value: float | Tensor, like: Tensor) -> Tensor:
    if isinstance(value, Tensor):
        if value.dim() != 0:
            raise ValueError(f"{name} must be a scalar (0-dim tensor), got shape "
                             f"{tuple(value.shape)}")
        out = value.to(dtype=like.dtype, device=like.device)
    elif isinstance(value, (int, float)) and not isinstance(value, bool):
        out = torch.tensor(float(value), dtype=like.dtype, device=like.device)
    else:
        raise TypeError(f"{name} must be a float or a 0-dim tensor, got {type(value).__name__}")
    if not math.isfinite(float(out.detach())):
        raise ValueError(f"{name} must be finite, got {float(out.detach())}")
    return out


def _check_options(method: str, substeps: int, rtol: float, atol: float) -> None:
    check_choice(method, "method", _METHODS)
    check_int(substeps, "substeps", minimum=1)
    if not (rtol > 0 and atol > 0):
        raise ValueError(f"rtol and atol must be > 0, got rtol={rtol}, atol={atol}")


def _check_inputs(
    u: Tensor, t: Tensor, w0: float | Tensor | None, method: str, substeps: int,
    rtol: float, atol: float,
) -> tuple[Tensor, Tensor]:
    for name, x in (("u", u), ("t", t)):
        if not isinstance(x, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        if not x.is_floating_point():
            raise TypeError(f"{name} must have a floating dtype, got {x.dtype}")
        if not bool(torch.isfinite(x).all()):
            raise ValueError(f"{name} must be finite, got NaN or inf values")
    if t.dim() != 1 or t.numel() == 0:
        raise ValueError(f"t must have shape (time,), got shape {tuple(t.shape)}")
    if u.dim() < 1 or u.shape[-1] != t.shape[0]:
        raise ValueError(f"u must have shape (..., time) with time = len(t) = {t.shape[0]}, "
                         f"got shape {tuple(u.shape)}")
    if t.numel() > 1 and not bool((t[1:] > t[:-1]).all()):
        raise ValueError("t must be strictly increasing")
    _check_options(method, substeps, rtol, atol)
    batch = u.shape[:-1]
    if w0 is None:
        w0 = u.new_zeros(batch)
    elif isinstance(w0, Tensor):
        try:
            w0 = torch.broadcast_to(w0.to(u.dtype), batch)
        except RuntimeError:
            raise ValueError(f"w0 must broadcast to u.shape[:-1] = {tuple(batch)}, got shape "
                             f"{tuple(w0.shape)}") from None
        if not bool(torch.isfinite(w0).all()):
            raise ValueError("w0 must be finite, got NaN or inf values")
    elif isinstance(w0, bool) or not isinstance(w0, (int, float)) or not math.isfinite(w0):
        raise ValueError(f"w0 must be a finite float or a tensor, got {w0!r}")
    else:
        w0 = u.new_full(batch, float(w0))
    return w0, t.to(u.dtype)


def _rk4(u: Tensor, w0: Tensor, A: Tensor, beta: Tensor, gamma: Tensor, n: Tensor,
         substeps: int) -> Tensor:
    """Classic RK4 in the input variable, ``substeps`` steps per sample interval."""
    tiny = torch.finfo(u.dtype).tiny
    du = (u[..., 1:] - u[..., :-1]) / substeps
    b_signed = beta * torch.sign(du)

    def g(w: Tensor, b: Tensor) -> Tensor:
        return A - (b * torch.sign(w) + gamma) * w.abs().clamp_min(tiny).pow(n)

    w, out = w0, [w0]
    for h, b in zip(du.unbind(-1), b_signed.unbind(-1), strict=True):
        for _ in range(substeps):
            k1 = g(w, b)
            k2 = g(w + 0.5 * h * k1, b)
            k3 = g(w + 0.5 * h * k2, b)
            k4 = g(w + h * k3, b)
            w = w + h / 6 * (k1 + 2 * (k2 + k3) + k4)
        out.append(w)
    return torch.stack(out, -1)


def _adaptive(u: Tensor, t: Tensor, w0: Tensor, A: Tensor, beta: Tensor, gamma: Tensor,
              n: Tensor, method: str, rtol: float, atol: float) -> Tensor:
    """torchdiffeq's adaptive solver in time, restarted at every sample (``jump_t``)."""
    tiny = torch.finfo(u.dtype).tiny
    rate = (u[..., 1:] - u[..., :-1]) / (t[1:] - t[:-1])
    rates, b_signed = rate.unbind(-1), (beta * torch.sign(rate)).unbind(-1)
    times, last = t.tolist(), t.shape[0] - 2

    def rhs(s: Tensor, w: Tensor) -> Tensor:
        k = min(max(bisect.bisect_right(times, float(s.detach())) - 1, 0), last)
        p = w.abs().clamp_min(tiny).pow(n)
        return rates[k] * (A - (b_signed[k] * torch.sign(w) + gamma) * p)

    from torchdiffeq import odeint  # on first use: it imports SciPy's integrate

    w = odeint(rhs, w0, t, method=method, rtol=rtol, atol=atol,
               options={"jump_t": t[1:-1]})
    return w.movedim(0, -1)


def bouc_wen_state(
    u: Tensor,
    t: Tensor,
    *,
    A: float | Tensor = DEFAULTS["A"],
    beta: float | Tensor = DEFAULTS["beta"],
    gamma: float | Tensor = DEFAULTS["gamma"],
    n: float | Tensor = DEFAULTS["n"],
    w0: float | Tensor | None = None,
    method: str = "rk4",
    substeps: int = 1,
    rtol: float = 1e-7,
    atol: float = 1e-9,
) -> Tensor:
    """Hysteretic state ``w`` of the Bouc-Wen model (see the module docstring).

    Args:
        u: Input samples ``(..., time)``.
        t: Sample times ``(time,)``, strictly increasing.
        A, beta, gamma: Shape coefficients (floats or 0-dim tensors). ``w`` stays bounded
            by ``(A / (beta + gamma))^(1/n)`` when ``A > 0``, ``beta + gamma > 0`` and
            ``beta >= gamma`` (survey, class of bounded, dissipative models).
        n: Sharpness exponent, ``n >= 1``.
        w0: Initial state, float or tensor broadcastable to ``(...)`` (default 0).
        method: ``"rk4"`` (fixed step per sample interval, default) or a torchdiffeq
            adaptive solver: ``"dopri5"``, ``"dopri8"``, ``"bosh3"``, ``"fehlberg2"``,
            ``"adaptive_heun"``.
        substeps: RK4 steps per sample interval (``method="rk4"`` only).
        rtol, atol: Tolerances of the adaptive solvers.

    Returns:
        w: ``(..., time)`` with ``w[..., 0] = w0``; differentiable in ``u``, ``w0`` and
        the coefficients.

    Raises:
        ValueError: NaN/inf, non-increasing ``t``, mismatched lengths, ``n < 1``, an
            unknown ``method``, bad solver options.
        TypeError: Non-tensor or non-floating ``u``/``t``, non-scalar coefficients.
    """
    w0, t = _check_inputs(u, t, w0, method, substeps, rtol, atol)
    A_, beta_, gamma_, n_ = (_scalar(k, v, u) for k, v in
                             (("A", A), ("beta", beta), ("gamma", gamma), ("n", n)))
    if float(n_.detach()) < 1:
        raise ValueError(f"n must be >= 1, got {float(n_.detach())}")
    if u.shape[-1] == 1:
        return w0.unsqueeze(-1)
    if method == "rk4":
        return _rk4(u, w0, A_, beta_, gamma_, n_, substeps)
    return _adaptive(u, t, w0, A_, beta_, gamma_, n_, method, rtol, atol)


def bouc_wen(
    u: Tensor,
    t: Tensor,
    *,
    A: float | Tensor = DEFAULTS["A"],
    beta: float | Tensor = DEFAULTS["beta"],
    gamma: float | Tensor = DEFAULTS["gamma"],
    n: float | Tensor = DEFAULTS["n"],
    k_x: float | Tensor = DEFAULTS["k_x"],
    k_w: float | Tensor = DEFAULTS["k_w"],
    w0: float | Tensor | None = None,
    method: str = "rk4",
    substeps: int = 1,
    rtol: float = 1e-7,
    atol: float = 1e-9,
) -> Tensor:
    """Output ``y = k_x u + k_w w`` of the Bouc-Wen plant; ``w`` from :func:`bouc_wen_state`.

    Args:
        u: Input samples ``(..., time)``.
        t: Sample times ``(time,)``, strictly increasing.
        A, beta, gamma, n, w0, method, substeps, rtol, atol: As in :func:`bouc_wen_state`.
        k_x: Gain of the input (elastic) part.
        k_w: Gain of the hysteretic part.

    Returns:
        y: ``(..., time)``. Supports autograd in ``u``, ``w0`` and all coefficients.

    Raises:
        ValueError, TypeError: As :func:`bouc_wen_state`; non-scalar or non-finite gains.
    """
    if not isinstance(u, Tensor):
        raise TypeError(f"u must be a torch.Tensor, got {type(u).__name__}")
    k_x_, k_w_ = _scalar("k_x", k_x, u), _scalar("k_w", k_w, u)
    w = bouc_wen_state(u, t, A=A, beta=beta, gamma=gamma, n=n, w0=w0, method=method,
                       substeps=substeps, rtol=rtol, atol=atol)
    return k_x_ * u + k_w_ * w


class BoucWen(nn.Module):
    """Bouc-Wen plant with its coefficients as parameters (``learnable=True``) or buffers.

    ``A``, ``beta``, ``gamma``, ``k_x``, ``k_w`` are stored as they are. The exponent is
    stored as ``n_root`` with ``n = 1 + n_root**2``, so ``n >= 1`` holds during training.
    ``n = 1`` (the default, as in Low and Guo's piezo model) is a stationary point of that
    map: a model built with ``n = 1`` keeps it; build it with ``n > 1`` to identify ``n``.

    Identification: the coefficients are redundant, ``(A, beta, gamma, k_w)`` and
    ``(c A, c^(1-n) beta, c^(1-n) gamma, k_w / c)`` give the same output for any ``c > 0``,
    so hold one of them fixed, e.g. ``model.k_w.requires_grad_(False)``.

    Args:
        A, beta, gamma, n, k_x, k_w: Initial coefficients (defaults :data:`DEFAULTS`).
        learnable: Register the coefficients as ``nn.Parameter`` (else as buffers).
        method, substeps, rtol, atol: Solver options of :func:`bouc_wen_state`.

    Shapes:
        ``u: (..., time)``, ``t: (time,)``, ``w0: (...)`` -> ``y: (..., time)``.
    """

    def __init__(
        self,
        A: float = DEFAULTS["A"],
        beta: float = DEFAULTS["beta"],
        gamma: float = DEFAULTS["gamma"],
        n: float = DEFAULTS["n"],
        k_x: float = DEFAULTS["k_x"],
        k_w: float = DEFAULTS["k_w"],
        *,
        learnable: bool = True,
        method: str = "rk4",
        substeps: int = 1,
        rtol: float = 1e-7,
        atol: float = 1e-9,
    ) -> None:
        super().__init__()
        values = {"A": A, "beta": beta, "gamma": gamma, "n": n, "k_x": k_x, "k_w": k_w}
        for name, value in values.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite float, got {value!r}")
        if n < 1:
            raise ValueError(f"n must be >= 1, got {n}")
        _check_options(method, substeps, rtol, atol)
        values["n_root"] = math.sqrt(n - 1.0)
        del values["n"]
        for name, value in values.items():
            tensor = torch.tensor(float(value))
            if learnable:
                self.register_parameter(name, nn.Parameter(tensor))
            else:
                self.register_buffer(name, tensor)
        self.method, self.substeps, self.rtol, self.atol = method, substeps, rtol, atol

    def coefficients(self) -> dict[str, Tensor]:
        """The model coefficients ``A, beta, gamma, n, k_x, k_w`` as 0-dim tensors."""
        return {"A": self.A, "beta": self.beta, "gamma": self.gamma,
                "n": 1 + self.n_root.square(), "k_x": self.k_x, "k_w": self.k_w}

    def state(self, u: Tensor, t: Tensor, w0: Tensor | None = None) -> Tensor:
        """Hysteretic state ``w: (..., time)``; ``w[..., -1]`` continues a stream as ``w0``."""
        c = self.coefficients()
        return bouc_wen_state(u, t, A=c["A"], beta=c["beta"], gamma=c["gamma"], n=c["n"],
                              w0=w0, method=self.method, substeps=self.substeps,
                              rtol=self.rtol, atol=self.atol)

    def forward(self, u: Tensor, t: Tensor, w0: Tensor | None = None) -> Tensor:
        """Output ``y = k_x u + k_w w: (..., time)`` for input ``u: (..., time)`` at ``t``."""
        return self.k_x * u + self.k_w * self.state(u, t, w0)

    def extra_repr(self) -> str:
        c = {k: round(float(v.detach()), 4) for k, v in self.coefficients().items()}
        return ", ".join(f"{k}={v}" for k, v in c.items()) + f", method={self.method!r}"
