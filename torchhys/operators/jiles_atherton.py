"""The Jiles-Atherton model as an operator (flux density in, field out).

:class:`JilesAtherton` is the inverse Jiles-Atherton model of a magnetic core: the field H
(the current that drives it) for a wanted flux density B, the compensator of a magnetic
actuator. Its maths is :func:`torchhys.functional.jiles_atherton`. Five physical parameters
describe the whole family of loops, so a model fitted on one or two loop amplitudes
predicts loops of other amplitudes, which models with many free weights do not (see
docs/real-data.md). :func:`~torchhys.identification.jiles_atherton.fit_jiles_atherton`
identifies the parameters by least squares (Levenberg-Marquardt from several starts).
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
    check_tensor,
)
from torchhys.functional.jiles_atherton import MU0, jiles_atherton, jiles_atherton_step
from torchhys.operator import HysteresisOperator
from torchhys.registry import register_operator
from torchhys.step import OperatorStep, StateBlock
from torchhys.testing import Example

__all__ = ["JilesAtherton", "JilesAthertonStep"]

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
        """Euler steps per sample (an int; kept in the ``saved_substeps`` buffer, read as a
        Python int when set or loaded: the forward reads no buffer's value, so it traces)."""
        return self._substeps

    @substeps.setter
    def substeps(self, value: int) -> None:
        self.saved_substeps.fill_(check_int(value, "substeps", minimum=1))
        self._substeps = value

    constraints = {"raw": "finite", "saved_mu0": "positive",
                   "saved_substeps": "positive_integer"}

    def after_load(self) -> None:
        self.mu0 = float(self.saved_mu0)
        self._substeps = int(self.saved_substeps)

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


