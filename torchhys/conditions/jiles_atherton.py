"""The inverse Jiles-Atherton model with parameters that move with measured operating
conditions (a core's temperature): :class:`ConditionedJilesAtherton`, its step
:class:`ConditionedJilesAthertonStep` and :func:`conditioned_ja_parameters`.

The model is :func:`torchhys.functional.jiles_atherton` (flux density B in, field H out) with
each sample's five parameters

    (ms, a, k, alpha) = exp(raw[:4] + theta[:4] . b(c~)),   c = sigmoid(raw[4] + theta[4] . b(c~)),

``b`` the tensor-product Legendre basis of total degree ``degree`` without its constant
(:func:`~torchhys.conditions.basis.legendre_basis`) of the conditions scaled to [-1, 1] over
their calibrated range. Every theta gives valid parameters (positive, ``0 < c < 1``).
``theta`` starts at 0: the operator starts as :class:`~torchhys.JilesAtherton` of the same
parameters.
"""

# no `from __future__ import annotations`: TorchScript reads the step's class annotations
import math

import torch
from torch import Tensor, nn

from torchhys._checks import check_finite, check_int, check_positive, check_tensor
from torchhys.conditions._base import ConditionedOperator, schedule
from torchhys.conditions.basis import total_degree
from torchhys.functional.jiles_atherton import MU0, jiles_atherton_step
from torchhys.step import OperatorStep, StateBlock

__all__ = ["ConditionedJilesAtherton", "ConditionedJilesAthertonStep",
           "conditioned_ja_parameters"]

_NAMES = ("ms", "a", "k", "alpha", "c")


def conditioned_ja_parameters(c: Tensor, raw: Tensor, theta: Tensor, scale: Tensor,
                              shift: Tensor, exponents: list[list[int]], degree: int) -> Tensor:
    """``(ms, a, k, alpha, c)`` (..., 5) of conditions c (..., n): ``raw`` (5,) the logarithms
    of ``ms, a, k, alpha`` and the logit of ``c``, plus ``theta . b(c * scale + shift)``
    (``theta`` (5, len(exponents))). Without exponents (no conditions): ``raw``'s values for
    every sample."""
    if len(exponents) == 0:
        z = raw.expand(list(c.shape[:-1]) + [raw.shape[0]])
    else:
        z = raw + schedule(c, theta, scale, shift, exponents, degree)
    return torch.cat([torch.exp(z[..., :4]), torch.sigmoid(z[..., 4:])], -1)


class ConditionedJilesAthertonStep(OperatorStep):
    """Per-sample step: :func:`conditioned_ja_parameters` of the sample's conditions, then
    :func:`~torchhys.functional.jiles_atherton_step`.

    State: ``flux`` (the last sample's B) and ``field`` (its H), both 0 at the first sample
    (a demagnetised core), as :class:`~torchhys.JilesAtherton`'s step. Input: x (batch, 1 +
    n): B, then the n conditions. Features: H (batch, 1).
    """

    exponents: list[list[int]]
    degree: int
    mu0: float
    substeps: int

    def __init__(self, raw: Tensor, theta: Tensor, scale: Tensor, shift: Tensor,
                 exponents: list[list[int]], degree: int, mu0: float, substeps: int) -> None:
        super().__init__()
        for name, value in (("raw", raw), ("theta", theta), ("scale", scale),
                            ("shift", shift)):
            self.register_buffer(name, value.detach().clone())
        self.exponents, self.degree = exponents, int(degree)
        self.mu0, self.substeps = float(mu0), int(substeps)
        self.n_inputs = 1 + int(scale.numel())
        self.n_outputs = 1
        self.state_spec = [StateBlock("flux", 1), StateBlock("field", 1)]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        p = conditioned_ja_parameters(x[:, 1:], self.raw, self.theta, self.scale, self.shift,
                                      self.exponents, self.degree)
        b = x[:, :1]
        h = jiles_atherton_step(b, state[0], state[1], p[:, 0:1], p[:, 1:2], p[:, 2:3],
                                p[:, 3:4], p[:, 4:5], self.mu0, self.substeps)
        return h, [b, h]


class ConditionedJilesAtherton(ConditionedOperator):
    """Inverse Jiles-Atherton model (B in, H out) whose parameters are log-linear (``c``:
    logit-linear) in a Legendre basis of the conditions (the module docstring).

    It assumes that the conditions (a temperature) move the material's parameters, while the
    physics of one loop stays Jiles-Atherton's: the saturation, the anhysteretic shape, the
    pinning, the coupling and the reversible share each scale smoothly with the condition.
    ``raw`` (5,) and ``theta`` (5, K) are parameters; ``theta`` starts at 0. The sequence
    path loops over the samples (as :class:`~torchhys.JilesAtherton`'s); its step is the
    same maths.

    Args:
        n_conditions: conditions per sample (>= 0; 0: :class:`~torchhys.JilesAtherton`).
        degree: total degree of the basis in the conditions (>= 1).
        ms, a, k, alpha, c: the parameters at ``theta = 0`` (as :class:`JilesAtherton`'s:
            positive, ``0 < c < 1``).
        mu0: input units per output unit of free space (4 pi 1e-7 for B in T, H in A/m).
        substeps: Euler steps per sample, >= 1. ``mu0`` and ``substeps`` are saved in the
            state dict (``saved_mu0``, ``saved_substeps``) and read back on load.

    Shape:
        - x: (batch, time, 1 + n_conditions) or (time, 1 + n_conditions): column 0 B, the
          others the conditions ((batch, time) or (time,) without conditions)
        - state: ``(batch, 2)`` or ``(2,)``: the last sample's B and H; None: ``(0, 0)``
        - returns ``(H, state)``: H (batch, time) (or (time,)), the state at the last sample.

    Raises:
        ValueError: a bad argument (named); x of another shape, or with NaN or inf; not
            calibrated (with conditions).
    """

    n_outputs: int = 1
    constraints = {"raw": "finite", "theta": "finite", "saved_mu0": "positive",
                   "saved_substeps": "positive_integer"}
    _scales = "the parameters"

    def __init__(self, n_conditions: int = 1, *, degree: int = 1, ms: float = 1e6,
                 a: float = 50.0, k: float = 50.0, alpha: float = 1e-4, c: float = 0.2,
                 mu0: float = MU0, substeps: int = 2) -> None:
        super().__init__()
        values = [check_positive(v, n) for v, n in zip((ms, a, k, alpha, c), _NAMES, strict=True)]
        if not values[4] < 1:
            raise ValueError(f"c must be in (0, 1), got {c!r}")
        self.mu0 = check_positive(mu0, "mu0")
        # the fixed settings travel in the state dict (read back on load), as JilesAtherton's
        self.register_buffer("saved_mu0", torch.tensor(self.mu0, dtype=torch.float64))
        self.register_buffer("saved_substeps", torch.tensor(0))
        self.substeps = substeps
        n = check_int(n_conditions, "n_conditions", minimum=0)
        k_basis = max(len(total_degree(n, check_int(degree, "degree", minimum=1))) - 1, 0)
        raw = [math.log(v) for v in values[:4]] + [math.log(values[4] / (1 - values[4]))]
        self.raw = nn.Parameter(torch.tensor(raw, dtype=torch.float64))
        self.theta = nn.Parameter(torch.zeros(5, k_basis, dtype=torch.float64))
        self._init_conditions(n, degree, torch.float64)

    @property
    def substeps(self) -> int:
        """Euler steps per sample (kept in the ``saved_substeps`` buffer, read as a Python
        int when set or loaded)."""
        return self._substeps

    @substeps.setter
    def substeps(self, value: int) -> None:
        self.saved_substeps.fill_(check_int(value, "substeps", minimum=1))
        self._substeps = value

    def after_load(self) -> None:
        self.mu0 = float(self.saved_mu0)
        self._substeps = int(self.saved_substeps)

    def parameters_at(self, conditions: Tensor) -> Tensor:
        """``(ms, a, k, alpha, c)`` (..., 5) at conditions (..., n_conditions)
        (differentiable)."""
        scale, shift = self._scaling(conditions.dtype)
        return conditioned_ja_parameters(conditions, self.raw.to(conditions.dtype),
                                         self.theta.to(conditions.dtype), scale, shift,
                                         self.exponents, self.degree)

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        xb, squeezed = self._inputs(x)
        n = self.n_conditions
        b = xb if n == 0 else xb[..., 0]
        batch = b.shape[0]
        if state is None:
            b_prev, h_prev = b.new_zeros(batch), b.new_zeros(batch)
        else:
            check_tensor(state, "state")
            s = state.unsqueeze(0) if state.dim() == 1 else state
            if tuple(s.shape) != (batch, 2):
                raise ValueError(f"state must have shape ({batch}, 2) (B and H), got "
                                 f"{tuple(state.shape)}")
            check_finite(s, "state")
            b_prev, h_prev = s[:, 0].to(b.dtype), s[:, 1].to(b.dtype)
        c = xb[..., 1:] if n else b.new_zeros(batch, b.shape[1], 0)
        p = self.parameters_at(c)  # (batch, time, 5)
        out = []
        for t in range(b.shape[1]):
            pt = p[:, t]
            h_prev = jiles_atherton_step(b[:, t], b_prev, h_prev, pt[:, 0], pt[:, 1], pt[:, 2],
                                         pt[:, 3], pt[:, 4], self.mu0, self.substeps)
            b_prev = b[:, t]
            out.append(h_prev)
        h = torch.stack(out, 1)
        last = torch.stack([b_prev, h_prev], 1)
        return (h[0], last[0]) if squeezed else (h, last)

    def streaming_step(self, dtype: torch.dtype) -> ConditionedJilesAthertonStep:
        """The per-sample step with the current parameters and range (detached), in
        ``dtype``."""
        scale, shift = self._scaling(dtype)
        return ConditionedJilesAthertonStep(self.raw.detach().to(dtype),
                                            self.theta.detach().to(dtype), scale, shift,
                                            self.exponents, self.degree, self.mu0,
                                            self.substeps)
