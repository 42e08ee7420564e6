"""The exact inverse of a Preisach model, as an operator.

A :class:`~torchhys.Preisach` model with hard relays, a non-negative density and a linear
term > 0 rises strictly with its input at every state: given the relays, its output is
``offset + linear * g(x)`` plus a constant between neighbouring thresholds (g the grading,
:func:`~torchhys.functional.preisach.graded_input`; x itself on an even grid), and jumps up
at each threshold where relays switch. So each sample has one solution, found in closed form
on the segment that holds the target, or the threshold itself when the target lies inside a
jump (:func:`~torchhys.functional.preisach.preisach_inverse_step`); the relays then switch
with the solved input. Fitted in the direction where the Preisach model has the right shape
(the flux density of a magnetic core from its field, H -> B), it is the compensator of that
model (B -> H): fed the model's output from the same state, it returns the model's input.

Each sample's relays depend on the inputs solved before it, so the sequence path is
sequential; but the relays change only where a solution reaches a threshold, and it solves
the samples between two switches at once (:func:`~torchhys.functional.preisach.preisach_inverse`).
Still slower than the model's own (a scan) where the relays switch often.
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchhys._checks import check_int
from torchhys.functional.preisach import (
    check_preisach_invertible,
    check_relay_state,
    preisach_inverse,
    preisach_inverse_constants,
    preisach_inverse_step,
)
from torchhys.operator import (
    Example,
    HysteresisOperator,
    OperatorStep,
    StateBlock,
    register_operator,
)
from torchhys.operators.preisach import Preisach, check_saved_grid

__all__ = ["PreisachInverse", "PreisachInverseStep"]


class PreisachInverseStep(OperatorStep):
    """Per-sample step of :class:`PreisachInverse`
    (:func:`~torchhys.functional.preisach.preisach_inverse_step`).

    State: one block ``"relays"`` (batch, K), starting at the model's initial relays.
    Feature: the solved input. Shapes: y (batch, 1) -> features (batch, 1). Written for
    TorchScript and ``torch.export``.
    """

    def __init__(self, alpha: Tensor, beta: Tensor, weights: Tensor, linear: Tensor,
                 offset: Tensor, initial: Tensor, centre: float, scale: float | None) -> None:
        super().__init__()
        linear, offset = linear.detach().reshape(()), offset.detach().reshape(())
        tables = preisach_inverse_constants(alpha, beta, weights.detach(), linear, offset,
                                            centre, scale)
        for name, v in (("alpha", alpha), ("beta", beta), ("linear", linear),
                        *zip(("offs0", "doffs", "lin_g", "cap", "level", "bounds"), tables,
                             strict=True)):
            self.register_buffer(name, v.detach().clone())
        self.centre, self.scale = float(centre), scale
        self.n_outputs = 1
        self.state_spec = [StateBlock("relays", alpha.numel(), start=initial.tolist())]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        u, r = preisach_inverse_step(x, state[0], self.alpha, self.beta, self.offs0,
                                     self.doffs, self.lin_g, self.cap, self.level,
                                     self.bounds, self.linear, self.centre, self.scale)
        return u, [r]


class PreisachInverse(HysteresisOperator):
    """``x = F^-1[y]``, the exact inverse of a hard-relay :class:`~torchhys.Preisach` model F
    (module docstring). Fixed (buffers only): build it with :meth:`from_model` (or
    ``model.inverse()``); the plain constructor gives a placeholder of the right shape for
    ``load_state_dict``.

    Args:
        n: levels per axis of the model's grid (>= 1): K = n (n + 1) / 2 relays.

    Shape:
        - y: (time,) or (batch, time)
        - state: the model's relays before the first sample, (K,) or (batch, K), +-1; None:
          the model's initial relays
        - returns ``(x, state)``: x the shape of y; state the relays at the last sample
          (chunked calls with it equal one call: the same relays, x to the last bit or two
          on a graded grid, whose sinh rounds differently in longer vectors).
    """

    n_outputs: int = 1

    def __init__(self, n: int = 1) -> None:
        super().__init__()
        check_int(n, "n", minimum=1)
        model = Preisach(-1.0, 1.0, n)
        dtype = torch.get_default_dtype()
        for name in ("alpha", "beta", "initial_relays", "grading"):
            self.register_buffer(name, getattr(model, name).detach().to(dtype).clone())
        self.register_buffer("weights", torch.zeros_like(self.alpha))
        self.register_buffer("linear", torch.ones((), dtype=dtype))
        self.register_buffer("offset", torch.zeros((), dtype=dtype))
        self.n = n
        self.centre, self.scale = model.centre, model.scale

    @classmethod
    @torch.no_grad()
    def from_model(cls, model: Preisach) -> PreisachInverse:
        """The inverse of ``model`` (its current parameters, detached), in its dtype.

        Raises:
            TypeError: ``model`` is not a :class:`~torchhys.Preisach`.
            ValueError: smooth relays, or no inverse
                (:func:`~torchhys.functional.preisach.check_preisach_invertible`).
        """
        if not isinstance(model, Preisach):
            raise TypeError(f"model must be a Preisach, got {type(model).__name__}")
        if model.smooth is not None:
            raise ValueError("the inverse is of a model with hard relays (smooth=None), got "
                             f"smooth={model.smooth}")
        check_preisach_invertible(model.weights.detach(), model.linear.detach())
        inverse = cls(model.n).to(model.alpha.dtype)
        for name in ("alpha", "beta", "initial_relays", "grading", "weights", "linear",
                     "offset"):
            getattr(inverse, name).copy_(getattr(model, name).detach())
        Preisach._read_grading(inverse)  # type: ignore[arg-type]
        return inverse.to(model.alpha.device)

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        check_relay_state(state, x, self.alpha.shape[0], "state")
        r0 = self.initial_relays if state is None else state
        return preisach_inverse(x, self.weights, self.alpha, self.beta, offset=self.offset,
                                linear=self.linear, r0=r0, centre=self.centre,
                                scale=self.scale)

    def streaming_step(self, dtype: torch.dtype) -> PreisachInverseStep:
        """The per-sample step with the current buffers, in ``dtype``."""
        alpha, beta, weights, linear, offset, initial = (t.detach().to(dtype) for t in (
            self.alpha, self.beta, self.weights, self.linear, self.offset,
            self.initial_relays))
        return PreisachInverseStep(alpha, beta, weights, linear, offset, initial, self.centre,
                                   self.scale)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:  # noqa: ANN001
        """Checks the model it would hold before anything is copied (all or nothing, also
        for a partial state dict, whose missing keys keep their current values): thresholds
        ``alpha >= beta`` finite, relays +-1, the grading, and an invertible model; each
        error names its key."""
        def saved(name: str) -> Tensor:  # the saved value, or the current one if not given
            v = state_dict.get(prefix + name)
            return v if isinstance(v, Tensor) else getattr(self, name)

        a, b, r, g = saved("alpha"), saved("beta"), saved("initial_relays"), saved("grading")
        if a.shape != b.shape:
            raise ValueError(f"{prefix}alpha and {prefix}beta must be finite thresholds with "
                             "alpha >= beta (a Preisach grid) of one shape")
        if r.shape != a.shape:
            raise ValueError(f"{prefix}initial_relays must hold one relay value +-1 per relay")
        check_saved_grid(prefix, a, b, r, g)
        for name in ("linear", "offset"):
            v = saved(name)
            if v.numel() != 1 or not bool(v.isfinite().all()):
                raise ValueError(f"{prefix}{name} must be one finite number, got "
                                 f"{v.tolist()!r:.80}")
        try:
            check_preisach_invertible(saved("weights"), saved("linear"))
        except ValueError as err:
            raise ValueError(f"{prefix}{err}") from None
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        Preisach._read_grading(self)  # type: ignore[arg-type]

    def extra_repr(self) -> str:
        graded = "" if self.scale is None else f", scale={self.scale:.6g}"
        return f"n={self.n}, relays={self.alpha.numel()}{graded}"


def _example() -> PreisachInverse:
    """The inverse of a hard-relay model on a graded grid over [-1, 1] (10 relays) with a
    linear term."""
    model = Preisach(-1.0, 1.0, 4, scale=0.5).double()
    with torch.no_grad():
        model.weights.copy_(torch.linspace(0.05, 0.2, model.n_relays))
        model.linear.fill_(0.3)
        model.offset.fill_(0.1)
    return model.inverse()


register_operator("preisach_inverse", PreisachInverse, example=Example(
    # the graded map's sinh rounds differently in the step and in the sequence path's windows
    _example, atol=1e-12, bad_values={"linear": 0.0, "initial_relays": 0.0}))
