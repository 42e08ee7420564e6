"""A mass-spring-damper with a Bouc-Wen hysteretic restoring force (a grey-box model).

The single-degree-of-freedom oscillator of the Bouc-Wen benchmark (Noel and Schoukens),
force ``u`` (N) in, displacement ``y`` (m) out::

    m y'' + c y' + k y + z = u(t)
    z'   = alpha y' - beta_gamma |y'| |z|^(nu-1) z - beta_delta y' |z|^nu

Only the products ``beta_gamma = beta gamma`` and ``beta_delta = beta delta`` of the usual
coefficients reach the output (``beta`` scales both), so they are the parameters. The
benchmark's values: ``m = 2``, ``c = 10``, ``k = 5e4``, ``alpha = 5e4``, ``beta_gamma = 800``,
``beta_delta = -1100``, ``nu = 1`` (:data:`BENCHMARK`).

Discretisation. Classic RK4 in time, ``substeps`` steps per sample interval. Between samples
the input is a polynomial through the samples: ``"cubic"`` (default) through
``u[t-2], u[t-1], u[t], u[t+1]`` on the interval ``[t, t+1]``, ``"linear"`` through
``u[t], u[t+1]``. Both are causal: ``y[t+1]`` uses inputs up to ``u[t+1]``. On the benchmark's
band-limited input with the true coefficients, 4 substeps and the cubic give a steady-state
test RMSE of about 1.3e-6 m, the linear one about 7e-6 m (the input's curvature between
samples matters at that level).

State. ``(batch, 6)``: ``y, y', z`` at the last sample and the last three inputs. ``state=None``
means at rest at the first sample (``y[0] = 0``) with the input held at ``u[0]`` before it.

References:
    J. P. Noel, M. Schoukens, "Hysteretic benchmark with a dynamic nonlinearity", Workshop on
    Nonlinear System Identification Benchmarks, 2016; M. Ismail, F. Ikhouane, J. Rodellar,
    "The hysteresis Bouc-Wen model, a survey", Arch. Comput. Methods Eng. 16 (2009).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence, check_choice, check_int, check_state
from torchhys.models._common import check_fs

__all__ = ["BENCHMARK", "BoucWenOscillator"]

BENCHMARK: dict[str, float] = {"m": 2.0, "c": 10.0, "k": 5e4, "alpha": 5e4,
                               "beta_gamma": 800.0, "beta_delta": -1100.0, "nu": 1.0}
"""The coefficients of the Bouc-Wen benchmark (SI units)."""

_POSITIVE = ("m", "c", "k", "alpha")
_SIGNED = ("beta_gamma", "beta_delta")
_NODES = {"cubic": (-2.0, -1.0, 0.0, 1.0), "linear": (0.0, 1.0)}


def _lagrange(nodes: tuple[float, ...], x: float) -> list[float]:
    """Weights of the polynomial through ``nodes`` evaluated at ``x``."""
    out = []
    for i, ni in enumerate(nodes):
        w = 1.0
        for j, nj in enumerate(nodes):
            if j != i:
                w *= (x - nj) / (ni - nj)
        out.append(w)
    return out


class BoucWenOscillator(nn.Module):
    """The Bouc-Wen oscillator (module docstring) with learnable coefficients.

    Positive coefficients are stored as ``log(value / reference)``, the signed ones as
    ``value / scale`` (reference and scale: the initial values, buffers), so every raw
    parameter is of order one. ``nu`` is fixed unless ``learn_exponent`` (then ``nu > 0``
    through a log).

    Args:
        m, c, k, alpha: mass (kg), damping (N s/m), stiffness (N/m), hysteretic stiffness
            (N/m); positive.
        beta_gamma, beta_delta: the Bouc-Wen shape products (1/m for ``nu = 1``).
        nu: the Bouc-Wen exponent (> 0).
        fs: sampling frequency of the data (Hz).
        substeps: RK4 steps per sample interval.
        interpolation: the input between samples, ``"cubic"`` or ``"linear"``.
        learn_exponent: make ``nu`` a parameter.

    Shape:
        - u: (time,) or (batch, time), N
        - state: (6,) or (batch, 6); None: at rest (module docstring)
        - returns ``(y, state)``: y of u's shape (m), the state after the last sample.
    """

    state_size = 6

    def __init__(self, m: float = 1.0, c: float = 10.0, k: float = 1e4, alpha: float = 1e4,
                 beta_gamma: float = 0.0, beta_delta: float = 0.0, nu: float = 1.0, *,
                 fs: float, substeps: int = 4, interpolation: str = "cubic",
                 learn_exponent: bool = False) -> None:
        super().__init__()
        values = {"m": m, "c": c, "k": k, "alpha": alpha, "beta_gamma": beta_gamma,
                  "beta_delta": beta_delta, "nu": nu}
        for name, v in values.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"{name} must be a finite float, got {v!r}")
            if name in _POSITIVE + ("nu",) and v <= 0:
                raise ValueError(f"{name} must be > 0, got {v!r}")
        self.fs = check_fs(fs, "fs")
        self.substeps = check_int(substeps, "substeps", minimum=1)
        self.interpolation = check_choice(interpolation, "interpolation", tuple(_NODES))
        self.learn_exponent = bool(learn_exponent)
        f64 = torch.float64
        for name in _POSITIVE:
            self.register_buffer(f"{name}_ref", torch.tensor(float(values[name]), dtype=f64))
            setattr(self, f"log_{name}", nn.Parameter(torch.zeros((), dtype=f64)))
        for name in _SIGNED:
            scale = abs(values[name]) or 1.0 / 1e-3  # 1/m: |z|-proportional terms for y ~ 1 mm
            self.register_buffer(f"{name}_scale", torch.tensor(scale, dtype=f64))
            setattr(self, name + "_raw",
                    nn.Parameter(torch.tensor(values[name] / scale, dtype=f64)))
        if self.learn_exponent:
            self.log_nu = nn.Parameter(torch.tensor(math.log(nu), dtype=f64))
        else:
            self.register_buffer("log_nu", torch.tensor(math.log(nu), dtype=f64))
        nodes = _NODES[self.interpolation]
        fr = [j / (2 * self.substeps) for j in range(2 * self.substeps + 1)]
        weights = torch.tensor([_lagrange(nodes, x) for x in fr], dtype=f64)
        # weights over the last 4 inputs u[t-2], u[t-1], u[t], u[t+1] (zero-padded for linear)
        self.register_buffer("weights", torch.cat(
            [weights.new_zeros(len(fr), 4 - len(nodes)), weights], dim=1), persistent=False)

    def coefficients(self) -> dict[str, Tensor]:
        """The physical coefficients, 0-dim tensors: m, c, k, alpha, beta_gamma, beta_delta,
        nu."""
        out = {n: getattr(self, f"{n}_ref") * getattr(self, f"log_{n}").exp() for n in _POSITIVE}
        out.update({n: getattr(self, f"{n}_scale") * getattr(self, n + "_raw") for n in _SIGNED})
        out["nu"] = self.log_nu.exp()
        return out

    def config(self) -> dict[str, object]:
        """Constructor arguments that rebuild the module (load the state dict after)."""
        return {"fs": self.fs, "substeps": self.substeps, "interpolation": self.interpolation,
                "learn_exponent": self.learn_exponent}

    def forward(self, u: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        ub, squeezed = as_batched_sequence(u, "u")
        B = ub.shape[0]
        if state is None:
            start = torch.cat([ub.new_zeros(B, 3), ub[:, :1].expand(B, 3)], dim=1)
            first, todo = [ub.new_zeros(B)], ub[:, 1:]
        else:
            start, first, todo = check_state(state, B, self.state_size, ub), [], ub
        seq = torch.cat([start[:, 3:], todo], dim=1)
        # the input at the 2 substeps + 1 points of each interval, (B, T', 2 substeps + 1)
        mech, ys = start[:, :3], first
        if todo.shape[1]:
            points = seq.unfold(1, 4, 1) @ self.weights.to(ub.dtype).mT
            step = self._step_function(ub.dtype)
            for p in points.unbind(1):
                mech = step(mech, p)
                ys.append(mech[:, 0])
        y = torch.stack(ys, dim=1)
        new_state = torch.cat([mech, seq[:, -3:]], dim=1)
        return (y[0], new_state[0]) if squeezed else (y, new_state)

    def _step_function(self, dtype: torch.dtype) -> Callable[[Tensor, Tensor], Tensor]:
        """One sample interval: RK4 ``substeps`` times, (B, 3), (B, 2 substeps + 1) -> (B, 3)."""
        c = {n: v.to(dtype) for n, v in self.coefficients().items()}
        inv_m = 1.0 / c["m"]
        # the linear part of the right-hand side: d/dt (y, v, z) = s @ M^T + u e
        zero = torch.zeros_like(inv_m)
        M = torch.stack([torch.stack([zero, zero + 1, zero]),
                         torch.stack([-c["k"] * inv_m, -c["c"] * inv_m, -inv_m]),
                         torch.stack([zero, c["alpha"], zero])])
        e = torch.stack([zero, inv_m, zero])
        last = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=inv_m.device)
        bg, bd, nu = c["beta_gamma"], c["beta_delta"], c["nu"]
        linear_exponent = not self.learn_exponent and float(self.log_nu) == 0.0  # nu = 1
        tiny = torch.finfo(dtype).tiny

        def rhs(s: Tensor, u: Tensor) -> Tensor:
            v, z = s[:, 1], s[:, 2]
            if linear_exponent:
                nl = bg * v.abs() * z + bd * v * z.abs()
            else:
                p = z.abs().clamp_min(tiny).pow(nu)
                nl = (bg * v.abs() * torch.sign(z) + bd * v) * p
            return torch.addmm(torch.outer(u, e), s, M.mT) - torch.outer(nl, last)

        h = 1.0 / (self.fs * self.substeps)

        def step(s: Tensor, p: Tensor) -> Tensor:
            for j in range(self.substeps):
                a, b, f = p[:, 2 * j], p[:, 2 * j + 1], p[:, 2 * j + 2]
                k1 = rhs(s, a)
                k2 = rhs(torch.add(s, k1, alpha=0.5 * h), b)
                k3 = rhs(torch.add(s, k2, alpha=0.5 * h), b)
                k4 = rhs(torch.add(s, k3, alpha=h), f)
                s = s + (h / 6) * (k1 + k4 + 2 * (k2 + k3))
            return s

        return step

    def extra_repr(self) -> str:
        c = ", ".join(f"{k}={float(v):.6g}" for k, v in self.coefficients().items())
        return f"{c}, fs={self.fs}, substeps={self.substeps}, interpolation={self.interpolation!r}"
