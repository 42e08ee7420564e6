"""The Jiles-Atherton model as an operator (flux density in, field out) and its identification.

:class:`JilesAtherton` is the inverse Jiles-Atherton model of a magnetic core: the field H
(the current that drives it) for a wanted flux density B, the compensator of a magnetic
actuator. Its maths is :func:`torchhys.functional.jiles_atherton`. Five physical parameters
describe the whole family of loops, so a model fitted on one or two loop amplitudes
predicts loops of other amplitudes, which models with many free weights do not (see
docs/real-data.md). :func:`fit_jiles_atherton` identifies the parameters by least squares
(Levenberg-Marquardt from several starts).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_finite,
    check_int,
    check_positive,
    check_same_shape,
    check_tensor,
    check_warmup,
    fitted_samples,
)
from torchhys.functional.jiles_atherton import MU0, jiles_atherton, jiles_atherton_step
from torchhys.operator import (
    Example,
    HysteresisOperator,
    OperatorStep,
    StateBlock,
    register_operator,
)

__all__ = ["JilesAtherton", "JilesAthertonStep", "fit_jiles_atherton", "substeps_for"]

_NAMES = ("ms", "a", "k", "alpha", "c")


class JilesAthertonStep(OperatorStep):
    """Per-sample step of :class:`JilesAtherton`
    (:func:`~torchhys.functional.jiles_atherton_step`).

    State: ``flux`` (the last sample's B) and ``field`` (its H), both 0 at the first sample
    (a demagnetised core: the first step integrates from B = 0). Shapes: x (batch, 1) ->
    features (batch, 1). Args: the effective parameters, 0-dim, in the step's dtype.
    """

    def __init__(self, ms: Tensor, a: Tensor, k: Tensor, alpha: Tensor, c: Tensor,
                 mu0: float, substeps: int) -> None:
        super().__init__()
        for name, value in zip(_NAMES, (ms, a, k, alpha, c), strict=True):
            self.register_buffer(name, value.detach().clone().reshape(()))
        self.mu0 = float(mu0)
        self.substeps = int(substeps)
        self.n_outputs = 1
        self.state_spec = [StateBlock("flux", 1), StateBlock("field", 1)]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        h = jiles_atherton_step(x, state[0], state[1], self.ms, self.a, self.k, self.alpha,
                                self.c, self.mu0, self.substeps)
        return h, [x, h]


class JilesAtherton(HysteresisOperator):
    """Inverse Jiles-Atherton model: flux density B (input) -> field H (output).

    Args:
        ms: saturation magnetization (A/m with the default ``mu0``), > 0.
        a: shape of the anhysteretic curve (A/m), > 0.
        k: pinning, about the coercive field (A/m), > 0.
        alpha: inter-domain coupling (dimensionless), > 0.
        c: reversible share of the magnetization, in (0, 1).
        mu0: input units per output unit of free space: 4 pi 1e-7 for B in T and H in A/m
            (for B in mT and H in A/m, 4 pi 1e-4). Fixed.
        substeps: Euler steps per sample, >= 1: enough that one step moves B by a small part
            of its range (:func:`fit_jiles_atherton` picks it from the data).

    ``mu0`` and ``substeps`` are saved in the state dict (buffers ``saved_mu0``,
    ``saved_substeps``) and read back by ``load_state_dict``.

    The parameters are trainable, stored as logarithms (``ms, a, k, alpha``) and a logit
    (``c``): every value is a valid model. :meth:`parameters_effective` returns them.

    Shape:
        - x: B, (time,) or (batch, time)
        - state: ``(batch, 2)`` or ``(2,)``: the last sample's B and H; None: ``(0, 0)``,
          the demagnetised core
        - returns ``(H, state)``: H the shape of x, the state at the last sample.

    A sequential model (a Python loop over time, vectorized over the batch): meant for
    quasi-static loops of hundreds to thousands of samples.
    """

    n_outputs: int = 1

    def __init__(self, ms: float = 1e6, a: float = 50.0, k: float = 50.0, alpha: float = 1e-4,
                 c: float = 0.2, *, mu0: float = MU0, substeps: int = 2) -> None:
        super().__init__()
        values = [check_positive(v, n) for v, n in zip((ms, a, k, alpha, c), _NAMES, strict=True)]
        if not values[4] < 1:
            raise ValueError(f"c must be in (0, 1), got {c!r}")
        self.mu0 = check_positive(mu0, "mu0")
        raw = [math.log(v) for v in values[:4]] + [math.log(values[4] / (1 - values[4]))]
        self.raw = nn.Parameter(torch.tensor(raw, dtype=torch.float64))
        # the fixed settings travel in the state dict (read back on load): a module built
        # with the defaults and loaded from a saved one runs as the saved one did
        self.register_buffer("saved_mu0", torch.tensor(self.mu0, dtype=torch.float64))
        self.register_buffer("saved_substeps", torch.tensor(0))
        self.substeps = substeps

    @property
    def substeps(self) -> int:
        """Euler steps per sample (an int; kept in the ``saved_substeps`` buffer)."""
        return int(self.saved_substeps)

    @substeps.setter
    def substeps(self, value: int) -> None:
        self.saved_substeps.fill_(check_int(value, "substeps", minimum=1))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # type: ignore[override]
        # checked before anything is copied (a bad value is an error, the module unchanged)
        raw = state_dict.get(prefix + "raw")
        if isinstance(raw, Tensor) and not bool(raw.isfinite().all()):
            raise ValueError(f"{prefix}raw must be finite, got {raw.tolist()}")
        mu0 = state_dict.get(prefix + "saved_mu0")
        if isinstance(mu0, Tensor) and mu0.numel() == 1:
            mu0 = check_positive(float(mu0), f"{prefix}saved_mu0")
        steps = state_dict.get(prefix + "saved_substeps")
        if isinstance(steps, Tensor) and steps.numel() == 1:
            v = float(steps)
            if not (math.isfinite(v) and v == round(v) and v >= 1):
                raise ValueError(f"{prefix}saved_substeps must be an int >= 1, got {v!r}")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        if isinstance(mu0, float):
            self.mu0 = mu0

    def parameters_effective(self) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """``(ms, a, k, alpha, c)``, each 0-dim (differentiable)."""
        ms, a, k, alpha = self.raw[:4].exp().unbind()
        return ms, a, k, alpha, torch.sigmoid(self.raw[4])

    def extra_repr(self) -> str:
        p = ", ".join(f"{n}={float(v.detach()):.4g}" for n, v in
                      zip(_NAMES, self.parameters_effective(), strict=True))
        return f"{p}, mu0={self.mu0:.4g}, substeps={self.substeps}"

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        b, unbatched = as_batched_sequence(x, "x")
        start = None
        if state is not None:
            check_tensor(state, "state")
            s = state.unsqueeze(0) if state.dim() == 1 else state
            if s.shape != (b.shape[0], 2):
                raise ValueError(f"state must have shape ({b.shape[0]}, 2) (B and H), got "
                                 f"{tuple(state.shape)}")
            check_finite(s, "state")
            start = (s[:, 0].to(b.dtype), s[:, 1].to(b.dtype))
        p = [v.to(b.dtype) for v in self.parameters_effective()]
        h, (b_last, h_last) = jiles_atherton(b, *p, mu0=self.mu0, substeps=self.substeps,
                                             state=start)
        last = torch.stack([b_last, h_last], 1)
        return (h[0], last[0]) if unbatched else (h, last)

    def streaming_step(self, dtype: torch.dtype) -> JilesAthertonStep:
        """The per-sample step with the current parameters (detached), in ``dtype``."""
        p = [v.detach().to(dtype) for v in self.parameters_effective()]
        return JilesAthertonStep(*p, self.mu0, self.substeps)


register_operator("jiles_atherton", JilesAtherton, example=Example(
    JilesAtherton, bad_values={"raw": float("nan"), "saved_substeps": 0}))


def substeps_for(x: Tensor, resolution: int = 32, quantile: float = 1.0) -> int:
    """Euler steps per sample so that a sample step of x (rows, time) (its largest, or the
    given quantile of the absolute steps) moves x by at most 1/resolution of its range; at
    most 64."""
    span = float(x.max() - x.min())
    if x.shape[-1] < 2 or not span > 0:
        return 1
    step = float(torch.quantile(x.diff(dim=-1).abs().flatten(), quantile))
    return max(1, min(64, math.ceil(step * resolution / span)))


def fit_jiles_atherton(x: Tensor, y: Tensor, *, warmup: int = 0, mu0: float = MU0,
                       substeps: int | None = None, starts: int = 8, iterations: int = 60,
                       seed: int = 0, mask: Tensor | None = None) -> JilesAtherton:
    """Fit an inverse Jiles-Atherton model ``y = H[x]`` (B -> H) by least squares.

    Levenberg-Marquardt on the logarithms of the parameters (forward-difference Jacobians)
    from ``starts`` random starts scaled to the data (``ms`` from the largest |B|, ``a`` and
    ``k`` from the largest |H|), all starts in one batched run; the start with the least
    training error is returned. Every row runs from the demagnetised state; the first
    ``warmup`` samples of each row run the state but are not fitted.

    Args:
        x: flux density B, (time,) or (rows, time).
        y: field H, the shape of x.
        warmup: leading samples left out of the fit, in [0, time).
        mu0: as for :class:`JilesAtherton` (units).
        substeps: Euler steps per sample; None: enough that one step moves B by at most
            1/32 of its range (at most 64).
        starts, iterations: random starts and Levenberg-Marquardt iterations of each.
        seed: the starts' random generator seed.
        mask: the samples to fit, bool, the shape of ``x`` (False: left out of the fit, the
            state still runs through them, e.g. a held-out block or a shorter row's
            padding); None: every sample (after ``warmup`` in both cases).

    Returns:
        The fitted :class:`JilesAtherton` (float64 parameters).

    Raises:
        ValueError: shapes, non-finite values, a bad warmup, constant x or y, y falling
            with x, or no start with a finite error.
    """
    xb, _ = as_batched_sequence(x, "x")
    yb, _ = as_batched_sequence(y, "y")
    check_same_shape(yb, xb, "y", "x")
    T = xb.shape[1]
    check_warmup(warmup, T)
    mu0 = check_positive(mu0, "mu0")
    starts = check_int(starts, "starts", minimum=1)
    iterations = check_int(iterations, "iterations", minimum=1)
    xb, yb = xb.to(torch.float64), yb.to(torch.float64)
    fitted = fitted_samples(mask, (xb.shape[0], T), warmup).to(xb.device)
    known = fitted_samples(mask, (xb.shape[0], T), 0).to(xb.device)  # the warm-up's too
    bmax, hmax = float(xb.abs().max()), float(yb[known].abs().max())
    xs, ys = xb[fitted], yb[fitted]  # the fitted samples
    if not (float(xb.std()) > 0 and float(ys.std()) > 0):
        raise ValueError("x and y must vary (a constant record has no loop to fit)")
    if float(((xs - xs.mean()) * (ys - ys.mean())).sum()) <= 0:
        raise ValueError("y must rise with x (the field H rises with the flux density B along "
                         "a loop), but it falls: check the sign of y, and that x is B and y H")
    K = substeps_for(xb) if substeps is None else check_int(substeps, "substeps", minimum=1)
    R = xb.shape[0]
    target = ys.reshape(-1)

    def losses(theta: Tensor) -> tuple[Tensor, Tensor]:
        """Residuals (P, n) and mean squared errors (P,) of P parameter rows (P, 5)."""
        P = theta.shape[0]
        p = theta.repeat_interleave(R, 0)
        ms, a, k, alpha = p[:, :4].exp().unbind(1)
        h, _ = jiles_atherton(xb.repeat(P, 1), ms, a, k, alpha, torch.sigmoid(p[:, 4]),
                              mu0=mu0, substeps=K)
        r = h.reshape(P, R, T)[:, fitted] - target
        mse = r.square().mean(1)
        return r, torch.where(torch.isfinite(mse), mse, torch.full_like(mse, math.inf))

    g = torch.Generator().manual_seed(seed)

    def uniform(lo: float, hi: float) -> Tensor:
        return lo + (hi - lo) * torch.rand(starts, generator=g, dtype=torch.float64)

    ms0 = bmax / mu0 * uniform(1.05, 1.6)
    a0, k0 = hmax * uniform(0.02, 0.5), hmax * uniform(0.02, 0.5)
    theta = torch.stack([ms0.log(), a0.log(), k0.log(), (a0 / ms0 * uniform(0.1, 3.0)).log(),
                         uniform(-4.0, 1.0)], 1)
    # log-parameters stay where exp() is a positive float64 and the logit where c is in
    # (0, 1): a degenerate optimum (no coupling, no pinning) is a small positive value
    lo = torch.tensor([-600.0] * 4 + [-30.0], dtype=torch.float64)
    hi = torch.tensor([600.0] * 4 + [30.0], dtype=torch.float64)
    eye, step = torch.eye(5, dtype=torch.float64), 1e-6
    with torch.no_grad():
        _, loss = losses(theta)
        damping = torch.full((starts,), 1e-3, dtype=torch.float64)
        for _ in range(iterations):
            probes = torch.cat([theta.unsqueeze(1) + step * eye, theta.unsqueeze(1)], 1)
            rp, _ = losses(probes.reshape(-1, 5))
            rp = rp.reshape(starts, 6, -1)
            J = ((rp[:, :5] - rp[:, 5:]) / step).transpose(1, 2)  # (starts, n, 5)
            r = rp[:, 5]
            A = J.transpose(1, 2) @ J
            grad = (J.transpose(1, 2) @ r.unsqueeze(2)).squeeze(2)
            scale = torch.diagonal(A, dim1=1, dim2=2).clamp_min(1e-12)
            system = A + damping[:, None, None] * torch.diag_embed(scale)
            delta = -torch.linalg.solve(system, grad.unsqueeze(2)).squeeze(2)
            delta = torch.where(torch.isfinite(delta), delta, torch.zeros_like(delta))
            moved = torch.minimum(torch.maximum(theta + delta, lo), hi)
            _, trial = losses(moved)
            better = trial < loss
            theta = torch.where(better[:, None], moved, theta)
            loss = torch.where(better, trial, loss)
            damping = torch.where(better, damping / 3, damping * 4).clamp(1e-12, 1e12)
            if bool((damping >= 1e12).all()):
                break
    best = int(loss.argmin())
    if not math.isfinite(float(loss[best])):
        raise ValueError("no Jiles-Atherton fit with a finite error: check the units (mu0) "
                         "and that x is the flux density and y the field")
    ms, a, k, alpha = (float(v) for v in theta[best, :4].exp())
    c = float(torch.sigmoid(theta[best, 4]))
    return JilesAtherton(ms, a, k, alpha, min(max(c, 1e-13), 1 - 1e-13), mu0=mu0, substeps=K)
