"""The Preisach operator and its per-sample step (identification:
:mod:`torchhys.identification.preisach`).

The maths (relays, tie rule, smooth relays, the chunked sequence path) is in
:mod:`torchhys.functional.preisach`; the module holds the grid, the density and the state,
and the step calls the same :func:`~torchhys.functional.preisach.relay_update` and
:func:`~torchhys.functional.preisach.relay_output` as the sequence path.

References:
    I. D. Mayergoyz, Mathematical Models of Hysteresis, Springer, 1991.

**The exact inverse of a Preisach model, as an operator.**

A :class:`~torchhys.Preisach` model with hard relays, a non-negative density and a linear
term > 0 rises strictly with its input at every state: given the relays, its output is
``offset + linear * g(x)`` plus a constant between neighbouring thresholds (g the grading,
:func:`~torchhys.functional.preisach.graded_input`; x itself on an even grid), and jumps up
at each threshold where relays switch. So each sample has one solution, found in closed form
on the segment that holds the target, or the threshold itself when the target lies inside a
jump (:func:`~torchhys.functional.preisach_inverse.preisach_inverse_step`); the relays then
switch with the solved input. Fitted in the direction where the Preisach model has the right
shape (the flux density of a magnetic core from its field, H -> B), it is the compensator of
that model (B -> H): fed the model's output from the same state, it returns the model's input.

Each sample's relays depend on the inputs solved before it, so the sequence path is
sequential; but the relays change only where a solution reaches a threshold, and it solves
the samples between two switches at once
(:func:`~torchhys.functional.preisach_inverse.preisach_inverse`).
Still slower than the model's own (a scan) where the relays switch often.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import Tensor, nn

from torchhys._checks import (
    check_bool,
    check_int,
)
from torchhys.functional.preisach import (
    _check_smooth,
    check_relay_state,
    check_scale,
    demagnetized_state,
    graded_input,
    graded_input_inverse,
    preisach_grid,
    preisach_with_state,
    relay_output,
    relay_update,
)
from torchhys.functional.preisach_inverse import (
    check_preisach_invertible,
    preisach_inverse,
    preisach_inverse_constants,
    preisach_inverse_step,
)
from torchhys.operator import HysteresisOperator
from torchhys.registry import register_operator
from torchhys.step import OperatorStep, StateBlock
from torchhys.testing import Example

__all__ = ["Preisach", "PreisachInverse", "PreisachInverseStep", "PreisachStep"]


class Preisach(HysteresisOperator):
    """Discretised Preisach model ``offset + linear * x + sum_k w_k r_k[x]`` of the
    K = n (n + 1) / 2 relays of :func:`~torchhys.functional.preisach_grid` on [lo, hi].

    The density ``weights`` (K,) is stored as is, non-negative: the constructor,
    :func:`fit_preisach` and ``load_state_dict`` keep it so (loading negative weights raises
    ``ValueError``). A gradient step may take it below zero: forward uses ``max(w, 0)``, whose
    gradient passes at 0, and :meth:`project_` clamps the stored values (call it after each
    optimizer step: projected gradient). Stored rather than behind a softplus so that the
    exact zeros of a non-negative least-squares fit are representable. Initial density:
    uniform, ``1 / K`` (a major loop from -1 to 1).

    Args:
        lo, hi: input range of the grid; beyond it the relays saturate.
        n: levels per axis (>= 1).
        linear: learn a linear term ``linear * x`` (else fixed at 0).
        offset: learn an offset (else fixed at 0).
        smooth: temperature of smooth relays (gradients in x), or None for hard relays.
        initial: relays before the first sample: ``"demagnetized"`` (+1 below the line
            ``alpha + beta = lo + hi``, -1 on and above it), ``"negative"`` or ``"positive"``
            (after saturation: all -1 or all +1), or a (K,) tensor of +-1.
        scale: None (an even grid), or s > 0: a graded grid
            (:func:`~torchhys.functional.preisach_grid`), whose levels are equal steps of
            ``g(x) = c + s asinh((x - c) / s)``, c = (lo + hi) / 2: dense within about s of
            the center, sparse beyond. The linear term then reads g(x), a reversible part
            that saturates. For a magnetic core modelled from its field (H -> B; invert it
            with :meth:`inverse` for the compensator B -> H), s about a tenth of the largest
            field puts thresholds where the small loops turn. Saved in the state dict
            (buffer ``grading``: center, then scale or 0).

    Shape:
        - x: (time,) or (batch, time)
        - state: the relays at the last sample, (K,) or (batch, K), +-1; None: ``initial``
        - returns ``(y, state)``: y the shape of x; chunked calls equal one call.

    References:
        I. D. Mayergoyz, Mathematical Models of Hysteresis, Springer, 1991.
    """

    n_outputs: int = 1

    def __init__(
        self,
        lo: float,
        hi: float,
        n: int = 20,
        *,
        linear: bool = True,
        offset: bool = True,
        smooth: float | None = None,
        initial: str | Tensor = "demagnetized",
        scale: float | None = None,
    ) -> None:
        super().__init__()
        check_bool(linear, "linear")
        check_bool(offset, "offset")
        alpha, beta = preisach_grid(lo, hi, n, scale=scale, dtype=torch.float64)
        self.lo, self.hi, self.n, self.n_relays = float(lo), float(hi), n, alpha.numel()
        self.smooth = _check_smooth(smooth)
        self.center, self.scale = 0.5 * (self.lo + self.hi), check_scale(scale)
        dtype = torch.get_default_dtype()
        # (center, scale) of the grading, scale 0 for none: saved with the model
        self.register_buffer("grading", torch.tensor(
            [self.center, 0.0 if self.scale is None else self.scale], dtype=dtype))
        self._read_grading()
        self.register_buffer("initial_relays", self._initial(initial, alpha, beta).to(dtype))
        self.register_buffer("alpha", alpha.to(dtype))
        self.register_buffer("beta", beta.to(dtype))
        self.weights = nn.Parameter(torch.full_like(self.alpha, 1.0 / self.n_relays))
        for name, learn in (("linear", linear), ("offset", offset)):
            if learn:
                setattr(self, name, nn.Parameter(torch.zeros(())))
            else:
                self.register_buffer(name, torch.zeros(()))

    def _initial(self, initial: str | Tensor, alpha: Tensor, beta: Tensor) -> Tensor:
        choices = ("demagnetized", "negative", "positive")
        if isinstance(initial, Tensor):
            if initial.shape != alpha.shape:
                raise ValueError(f"initial must be one of {choices} or a tensor of shape "
                                 f"({alpha.numel()},) of +-1, got shape {tuple(initial.shape)}")
            if not bool(((initial == 1) | (initial == -1)).all()):
                raise ValueError("initial must hold relay values +-1, got values "
                                 f"{sorted(set(initial.tolist()))[:5]}")
            return initial.to(alpha.dtype).clone()
        if initial == "demagnetized":
            return demagnetized_state(alpha, beta, 0.5 * (self.lo + self.hi))
        if initial in ("negative", "positive"):
            return torch.full_like(alpha, -1.0 if initial == "negative" else 1.0)
        raise ValueError(f"initial must be one of {choices} or a tensor, got {initial!r}")

    def _read_grading(self) -> None:
        """The grading as Python numbers, from the saved buffer (in its dtype's rounding, so
        that a loaded copy computes the same)."""
        self.center = float(self.grading[0])
        self.scale = float(self.grading[1]) if float(self.grading[1]) > 0 else None

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        check_relay_state(state, x, self.alpha.shape[0], "state")
        r0 = self.initial_relays if state is None else state
        return preisach_with_state(
            x, self.weights.clamp_min(0.0), self.alpha, self.beta, offset=self.offset,
            linear=self.linear, state=r0, smooth=self.smooth, center=self.center,
            scale=self.scale,
        )

    @torch.no_grad()
    def project_(self) -> Preisach:
        """Clamp the stored density at 0 (after an optimizer step); returns self."""
        self.weights.clamp_(min=0.0)
        return self

    def streaming_step(self, dtype: torch.dtype) -> PreisachStep:
        """The per-sample step with the current parameters (detached), in ``dtype``."""
        return PreisachStep(self.alpha, self.beta, self.weights.clamp_min(0.0), self.linear,
                            self.offset, self.initial_relays, self.smooth, dtype,
                            self.center, self.scale)

    def inverse(self) -> PreisachInverse:
        """The exact inverse ``x = F^-1[y]`` as an operator (:class:`~torchhys.PreisachInverse`,
        detached parameters; see :class:`PreisachInverse`): the compensator of
        this
        model. It shares the model's state (the relays).

        Raises:
            ValueError: smooth relays, or an output that does not rise strictly with the
                input (``linear`` not > 0).
        """

        return PreisachInverse.from_model(self)

    def extra_repr(self) -> str:
        graded = "" if self.scale is None else f", scale={self.scale:.6g}"
        return f"lo={self.lo}, hi={self.hi}, n={self.n}, smooth={self.smooth}{graded}"

    constraints = {"weights": "nonnegative", "alpha": "finite", "beta": "finite",
                   "initial_relays": "relay"}

    def check_loaded(self, values: Mapping[str, Tensor], prefix: str) -> None:
        """Thresholds ``alpha >= beta`` and the grading (:func:`check_saved_grid`)."""
        check_saved_grid(prefix, values["alpha"], values["beta"], None, values["grading"])

    def after_load(self) -> None:
        """The grading and the grid range from the loaded buffers."""
        self._read_grading()
        a = self.alpha.detach()
        if self.n > 1:
            # the grid range of the loaded thresholds (cell centers, module docstring),
            # in the graded variable where the cells are equal
            c, s = self.center, self.scale
            gl, gh = (graded_input(torch.stack([a.min(), a.max()]).double().cpu(), c, s)
                      .tolist())
            half = 0.5 * (gh - gl) / (self.n - 1)
            self.lo, self.hi = graded_input_inverse(
                torch.tensor([gl - half, gh + half], dtype=torch.float64), c, s).tolist()


def check_saved_grid(prefix: str, alpha: Tensor | None, beta: Tensor | None,
                     initial: Tensor | None, grading: Tensor | None) -> None:
    """The values of a Preisach grid about to be loaded (each None where not given): finite
    thresholds ``alpha >= beta`` (when both are given, of one shape), initial relays of +-1,
    and a grading ``(center, scale)``, finite, scale >= 0.

    Raises:
        ValueError: naming the key (after ``prefix``).
    """
    if alpha is not None and beta is not None and alpha.shape == beta.shape and not bool(
            (alpha.isfinite() & beta.isfinite() & (alpha >= beta)).all()):
        raise ValueError(f"{prefix}alpha and {prefix}beta must be finite thresholds with "
                         "alpha >= beta (a Preisach grid)")
    if initial is not None and not bool(((initial == 1) | (initial == -1)).all()):
        raise ValueError(f"{prefix}initial_relays must hold relay values +-1")
    if grading is not None and (grading.shape != (2,) or not bool(grading.isfinite().all())
                                or float(grading[1]) < 0):
        raise ValueError(f"{prefix}grading must be (center, scale), finite, scale >= 0 "
                         f"(0: an even grid), got {grading.tolist()!r:.80}")


class PreisachStep(OperatorStep):
    """Per-sample step of :class:`Preisach`: ``r = relay_update(x, alpha, beta, r_prev)``,
    features ``offset + linear * x + relay_output(x, ..., r) @ w``.

    State: one block ``"relays"`` (batch, K), starting at the initial relays. Shapes: x
    (batch, 1) -> features (batch, 1). Written for TorchScript and ``torch.export``.
    """

    def __init__(self, alpha: Tensor, beta: Tensor, weights: Tensor, linear: Tensor,
                 offset: Tensor, initial: Tensor, smooth: float | None,
                 dtype: torch.dtype, center: float = 0.0, scale: float | None = None) -> None:
        super().__init__()
        self.n_outputs = 1
        self.state_spec = [StateBlock("relays", alpha.numel(), start=initial.tolist())]
        self.smooth = smooth
        self.center, self.scale = float(center), scale
        for name, v in (("alpha", alpha), ("beta", beta), ("weights", weights[:, None]),
                        ("linear", linear), ("offset", offset)):
            self.register_buffer(name, v.detach().to(dtype).clone())

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        r = relay_update(x, self.alpha, self.beta, state[0])
        out = relay_output(x, self.alpha, self.beta, r, self.smooth)
        lin = self.linear * graded_input(x, self.center, self.scale)
        return self.offset + lin + out @ self.weights, [r]


def _example() -> Preisach:
    """Hard relays on [-1, 1] (10 relays), an uneven density and a linear term."""
    model = Preisach(-1.0, 1.0, 4).double()
    with torch.no_grad():
        model.weights.copy_(torch.linspace(0.05, 0.2, model.n_relays))
        model.linear.fill_(0.3)
        model.offset.fill_(0.1)
    return model


register_operator("preisach", Preisach, example=Example(
    # the step sums the relays in another order than the sequence path
    _example, atol=1e-13, bad_values={"weights": -1.0, "initial_relays": 0.0}))


class PreisachInverseStep(OperatorStep):
    """Per-sample step of :class:`PreisachInverse`
    (:func:`~torchhys.functional.preisach_inverse.preisach_inverse_step`).

    State: one block ``"relays"`` (batch, K), starting at the model's initial relays.
    Feature: the solved input. Shapes: y (batch, 1) -> features (batch, 1). Written for
    TorchScript and ``torch.export``.
    """

    def __init__(self, alpha: Tensor, beta: Tensor, weights: Tensor, linear: Tensor,
                 offset: Tensor, initial: Tensor, center: float, scale: float | None) -> None:
        super().__init__()
        linear, offset = linear.detach().reshape(()), offset.detach().reshape(())
        tables = preisach_inverse_constants(alpha, beta, weights.detach(), linear, offset,
                                            center, scale)
        for name, v in (("alpha", alpha), ("beta", beta), ("linear", linear),
                        *zip(("offs0", "doffs", "lin_g", "cap", "level", "bounds"), tables,
                             strict=True)):
            self.register_buffer(name, v.detach().clone())
        self.center, self.scale = float(center), scale
        self.n_outputs = 1
        self.state_spec = [StateBlock("relays", alpha.numel(), start=initial.tolist())]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        u, r = preisach_inverse_step(x, state[0], self.alpha, self.beta, self.offs0,
                                     self.doffs, self.lin_g, self.cap, self.level,
                                     self.bounds, self.linear, self.center, self.scale)
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
        self.center, self.scale = model.center, model.scale

    @classmethod
    @torch.no_grad()
    def from_model(cls, model: Preisach) -> PreisachInverse:
        """The inverse of ``model`` (its current parameters, detached), in its dtype.

        Raises:
            TypeError: ``model`` is not a :class:`~torchhys.Preisach`.
            ValueError: smooth relays, or no inverse
                (:func:`~torchhys.functional.preisach_inverse.check_preisach_invertible`).
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
                                linear=self.linear, state=r0, center=self.center,
                                scale=self.scale)

    def streaming_step(self, dtype: torch.dtype) -> PreisachInverseStep:
        """The per-sample step with the current buffers, in ``dtype``."""
        alpha, beta, weights, linear, offset, initial = (t.detach().to(dtype) for t in (
            self.alpha, self.beta, self.weights, self.linear, self.offset,
            self.initial_relays))
        return PreisachInverseStep(alpha, beta, weights, linear, offset, initial, self.center,
                                   self.scale)

    constraints = {"alpha": "finite", "beta": "finite", "initial_relays": "relay",
                   "linear": "finite", "offset": "finite"}

    def check_loaded(self, values: Mapping[str, Tensor], prefix: str) -> None:
        """The model it would hold (also for a partial state dict, whose missing keys keep
        their current values): thresholds ``alpha >= beta`` of one shape, one relay each,
        the grading, scalars, and an invertible model; each error names its key."""
        a, b, r = values["alpha"], values["beta"], values["initial_relays"]
        if a.shape != b.shape:
            raise ValueError(f"{prefix}alpha and {prefix}beta must be finite thresholds with "
                             "alpha >= beta (a Preisach grid) of one shape")
        if r.shape != a.shape:
            raise ValueError(f"{prefix}initial_relays must hold one relay value +-1 per relay")
        check_saved_grid(prefix, a, b, None, values["grading"])
        for name in ("linear", "offset"):
            if values[name].numel() != 1:
                raise ValueError(f"{prefix}{name} must be one finite number, got "
                                 f"{values[name].tolist()!r:.80}")
        try:
            check_preisach_invertible(values["weights"], values["linear"])
        except ValueError as err:
            raise ValueError(f"{prefix}{err}") from None

    def after_load(self) -> None:
        Preisach._read_grading(self)  # type: ignore[arg-type]

    def extra_repr(self) -> str:
        graded = "" if self.scale is None else f", scale={self.scale:.6g}"
        return f"n={self.n}, relays={self.alpha.numel()}{graded}"


def _inverse_example() -> PreisachInverse:
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
    _inverse_example, atol=1e-12, bad_values={"linear": 0.0, "initial_relays": 0.0}))
