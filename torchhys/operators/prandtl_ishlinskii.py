"""Prandtl-Ishlinskii hysteresis model and its analytic inverse (the classical compensator)."""

from collections.abc import Mapping

import torch
from torch import Tensor, nn

from torchhys._checks import (
    as_batched_sequence,
    check_bool,
    check_finite,
    check_floating,
    check_nonnegative_weights,
    check_tensor,
)
from torchhys.functional.backlash import backlash, check_play_state, play_step
from torchhys.functional.prandtl_ishlinskii import (
    _check_weights,
    pi_output,
    prandtl_ishlinskii_inverse_parameters,
)
from torchhys.operator import HysteresisOperator
from torchhys.operators.backlash import PlayStep, _Widths
from torchhys.protocols import Deployable
from torchhys.registry import register_operator
from torchhys.step import OperatorStep, StateBlock
from torchhys.testing import Example

__all__ = ["PIStep", "PrandtlIshlinskii", "PrandtlIshlinskiiInverse"]


def _check_nonnegative(w: Tensor, name: str) -> None:
    """Raise ``ValueError`` naming ``name`` unless the weights ``w`` of a ``nonnegative``
    model are finite and >= 0."""
    check_nonnegative_weights(w, name, ">= 0 (a nonnegative Prandtl-Ishlinskii model)")


class PIStep(OperatorStep):
    """A Prandtl-Ishlinskii model, one sample at a time: N plays and :func:`pi_output`.

    State: ``plays`` (N columns, 0 at the first sample). Feature: ``w0 x + sum_i w_i y_i``.

    Args:
        widths, weights: (N,) each; linear_weight: 0-dim; all in the step's dtype.
    """

    def __init__(self, widths: Tensor, weights: Tensor, linear_weight: Tensor) -> None:
        super().__init__()
        self.register_buffer("r", 0.5 * widths.detach().clone())
        self.register_buffer("weights", weights.detach().clone())
        self.register_buffer("linear_weight", linear_weight.detach().clone().reshape(()))
        self.n_outputs = 1
        self.state_spec = [StateBlock("plays", int(widths.shape[0]))]

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        y = play_step(x, self.r, state[0])
        return pi_output(x, y.unsqueeze(1), self.weights, self.linear_weight), [y]


class PrandtlIshlinskii(_Widths, HysteresisOperator):
    """Prandtl-Ishlinskii model ``H[x] = w0 * x + sum_i w_i * y_i`` of N play operators.

    The paper's simulated plant (Section 5.2) is
    ``PrandtlIshlinskii(torch.linspace(1/6, 15/6, 15))``: unit weights, no linear
    term, zero initial state.

    Args:
        widths: full dead-band widths d_i >= 0, shape (N,).
        weights: weights w_i, shape (N,); ones if None.
        linear_weight: weight w0 of the linear term.
        learnable: make widths, weights and linear weight trainable (widths stay
            non-negative through softplus).
        nonnegative: a constrained model (``w_i >= 0``, ``w0 >= 0``: monotone, and with
            ``w0 > 0`` or a positive weight at width 0, invertible), as
            :func:`~torchhys.identification.fitting.fit_prandtl_ishlinskii` fits it with
            ``nonnegative=True``: negative weights are refused here and by
            ``load_state_dict``; :meth:`project_` restores the constraint after an optimizer
            step.

    Shape:
        - x: (time,) or (batch, time)
        - state: play-operator outputs before the first sample, (N,) or (batch, N);
          zeros if None
        - returns ``(H, final_state)``: H has the shape of x; final_state holds the
          play-operator outputs at the last sample, (N,) or (batch, N), to pass to the
          next call on the continuation of the sequence.

    Usable as an operator of :class:`~torchhys.InverseHysteresisNet` (one output feature),
    e.g. a least-squares inverse from
    :func:`torchhys.identification.fitting.fit_prandtl_ishlinskii`.
    """

    #: Number of output features when used as an operator of an InverseHysteresisNet.
    n_outputs: int = 1

    def __init__(
        self,
        widths: Tensor | list[float],
        weights: Tensor | list[float] | None = None,
        *,
        linear_weight: float = 0.0,
        learnable: bool = False,
        nonnegative: bool = False,
    ) -> None:
        super().__init__(widths, learnable=learnable)
        self.nonnegative = check_bool(nonnegative, "nonnegative")
        n = self.n_operators
        dtype = self.get_widths().dtype
        w = torch.ones(n, dtype=dtype) if weights is None else torch.as_tensor(weights).to(dtype)
        _check_weights(w, n)
        w0 = torch.tensor(float(linear_weight), dtype=dtype)
        if not torch.isfinite(w0):
            raise ValueError(f"linear_weight must be finite, got {linear_weight}")
        if self.nonnegative:
            _check_nonnegative(w, "weights")
            _check_nonnegative(w0, "linear_weight")
        if learnable:
            self.weights = nn.Parameter(w.clone())
            self.linear_weight = nn.Parameter(w0)
        else:
            self.register_buffer("weights", w.clone())
            self.register_buffer("linear_weight", w0)

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        widths = self.get_widths()
        check_play_state(state, x, widths.shape[0], "state")
        y = backlash(x, widths, state=state)
        h = pi_output(x, y, self.weights.to(y.dtype), self.linear_weight.to(y.dtype))
        return h, y[..., -1, :]

    def streaming_step(self, dtype: torch.dtype) -> PIStep:
        """The per-sample step with the current parameters, in ``dtype``."""
        return PIStep(*(t.detach().to(dtype) for t in (
            self.get_widths(), self.weights, self.linear_weight)))

    @torch.no_grad()
    def project_(self) -> "PrandtlIshlinskii":
        """Clamp the weights and the linear weight at 0 (after an optimizer step of a
        ``nonnegative`` model); returns self."""
        self.weights.clamp_(min=0.0)
        self.linear_weight.clamp_(min=0.0)
        return self

    def extra_repr(self) -> str:
        return f"n={self.n_operators}" + (", nonnegative=True" if self.nonnegative else "")

    constraints = {"fixed_widths": "nonnegative", "raw_widths": "finite", "weights": "finite",
                   "linear_weight": "finite"}

    def check_loaded(self, values: Mapping[str, Tensor], prefix: str) -> None:
        """Non-negative weights where the model is built with ``nonnegative=True``."""
        if self.nonnegative:
            for name in ("weights", "linear_weight"):
                _check_nonnegative(values[name], prefix + name)

    def inverse(self) -> "PrandtlIshlinskiiInverse":
        """The exact inverse model, built from the current parameters (detached).

        Raises:
            ValueError: when the initial loading curve is not strictly increasing.
        """
        return PrandtlIshlinskiiInverse(self)

    def inverse_state(self, state: Tensor) -> Tensor:
        """Map this model's play-operator state to the inverse model's initial state.

        With zero state (the default) the inverse state is zero too.

        Args:
            state: play-operator outputs, (N,) or (batch, N).

        Returns:
            The inverse model's play-operator state, (M,) or (batch, M), M the
            number of operators with positive width.

        Raises:
            TypeError, ValueError: a state that is not a finite floating-point (N,) or
                (batch, N) tensor.
        """
        check_tensor(state, "state")
        check_floating(state, "state")
        n = self.n_operators
        if state.dim() not in (1, 2) or state.shape[-1] != n:
            raise ValueError(f"state must have shape ({n},) or (batch, {n}), got shape "
                             f"{tuple(state.shape)}")
        check_finite(state, "state")
        p = prandtl_ishlinskii_inverse_parameters(
            self.get_widths().detach(), self.weights.detach(), self.linear_weight.detach()
        )
        z = state[..., p.order]
        w = self.weights.detach()[p.order].to(z.dtype)
        # z'_j = s_j z_j + sum_{i>j} w_i z_i
        tail = torch.flip(torch.cumsum(torch.flip(w * z, [-1]), -1), [-1]) - w * z
        return p.cumulative[1:].to(z.dtype) * z + tail


class PrandtlIshlinskiiInverse(HysteresisOperator, Deployable):
    """The analytic inverse of a :class:`PrandtlIshlinskii` model, as an operator: a
    compensator.

    The inverse is itself a Prandtl-Ishlinskii model of the *output*, with the
    play thresholds and weights of the classical inversion rule (see
    :func:`torchhys.functional.prandtl_ishlinskii_inverse_parameters`). Feeding a
    desired output y_d through it gives the command u with ``H[u] = y_d``. Fixed (buffers
    only); with no ``model``, the identity (one play of width 0 and weight 0, linear weight
    1) of the right kind for ``load_state_dict``.

    Args:
        model: the Prandtl-Ishlinskii model to invert (its parameters are copied).

    Raises:
        ValueError: when the model's initial loading curve is not strictly increasing
            (e.g. the paper's plant, which has no linear term).

    Shape:
        - x: the desired output, (time,) or (batch, time)
        - state: inverse play state, (M,) or (batch, M); zeros if None (matching a
          forward model at zero state); see :meth:`PrandtlIshlinskii.inverse_state`
        - returns ``(u, final_state)``, u the shape of x.
    """

    n_outputs: int = 1
    constraints = {"widths": "nonnegative", "weights": "finite", "linear_weight": "finite"}

    def __init__(self, model: PrandtlIshlinskii | None = None) -> None:
        super().__init__()
        if model is None:
            dtype = torch.get_default_dtype()
            widths, weights, w0 = (torch.zeros(1, dtype=dtype), torch.zeros(1, dtype=dtype),
                                   torch.ones((), dtype=dtype))
        else:
            if not isinstance(model, PrandtlIshlinskii):
                raise TypeError(f"model must be a PrandtlIshlinskii, got "
                                f"{type(model).__name__}")
            p = prandtl_ishlinskii_inverse_parameters(
                model.get_widths().detach(), model.weights.detach(),
                model.linear_weight.detach())
            widths, weights, w0 = p.widths, p.weights, p.linear_weight
        self.register_buffer("widths", widths.clone())
        self.register_buffer("weights", weights.clone())
        self.register_buffer("linear_weight", w0.clone())

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        as_batched_sequence(x, "x")
        check_play_state(state, x, self.widths.shape[0], "state")
        if self.widths.numel() == 0:  # purely linear model
            return self.linear_weight.to(x.dtype) * x, x.new_zeros(x.shape[:-1] + (0,))
        z = backlash(x, self.widths.to(x.dtype), state=state)
        u = pi_output(x, z, self.weights.to(z.dtype), self.linear_weight.to(z.dtype))
        return u, z[..., -1, :]

    def streaming_step(self, dtype: torch.dtype) -> PIStep:
        """The per-sample step: one Prandtl-Ishlinskii step of the desired output.

        Raises:
            ValueError: a purely linear inverse (no play operator) needs no compensator.
        """
        if self.widths.numel() == 0:
            raise ValueError("a purely linear PrandtlIshlinskiiInverse needs no compensator")
        return PIStep(self.widths.to(dtype), self.weights.to(dtype),
                      self.linear_weight.to(dtype))

    def streaming_steps(self, dtype: torch.dtype) -> list[OperatorStep]:
        """The compensator's steps, used as a model on its own: its one step."""
        return [self.streaming_step(dtype)]

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        """The command is the step's feature (column 1 after the input's column 0)."""
        return FeatureColumn(1)

    def affine_form(self, dtype: torch.dtype) -> tuple[list[OperatorStep], nn.Module]:
        """The same compensator as the plays' outputs and a readout of them
        (:class:`~torchhys.protocols.AffineForm`): ``[PlayStep(widths)]`` and
        :class:`PIReadout` ``w0 x + sum_i w_i y_i``, the weights the adaptive compensator
        updates (with a bias, 0 offline).

        Raises:
            ValueError: a purely linear inverse (no play operator).
        """
        if self.widths.numel() == 0:
            raise ValueError("a purely linear PrandtlIshlinskiiInverse needs no compensator")
        w = torch.cat([self.linear_weight.reshape(1), self.weights]).to(dtype)
        return [PlayStep(self.widths.to(dtype))], PIReadout(w)


class PIReadout(nn.Module):
    """The readout ``[x, y_1..y_N] @ w`` of a Prandtl-Ishlinskii model's plays: a compensator
    head with an affine readout (:class:`~torchhys.protocols.AffineReadout`; basis ``[x,
    y.., 1]``, the bias's weight 0).

    Shapes: ``forward(features)``: (batch, 1 + N) -> (batch, 1).
    """

    def __init__(self, weight: Tensor) -> None:
        super().__init__()
        self.register_buffer("weight", weight.detach().clone())

    def forward(self, features: Tensor) -> Tensor:
        return torch.mv(features, self.weight).unsqueeze(1)

    def readout_basis(self, features: Tensor) -> Tensor:
        """``[features, 1]`` (batch, N + 2)."""
        return torch.cat([features, torch.ones_like(features[:, :1])], 1)

    def readout_weights(self) -> Tensor:
        """``[w0, w_1..w_N, 0]`` (N + 2,)."""
        return torch.cat([self.weight, self.weight.new_zeros(1)])


class FeatureColumn(nn.Module):
    """A compensator head that returns one feature column: (batch, n) -> (batch, 1)."""

    def __init__(self, index: int) -> None:
        super().__init__()
        self.index = index

    def forward(self, features: Tensor) -> Tensor:
        return features.narrow(1, self.index, 1)


register_operator("prandtl_ishlinskii", PrandtlIshlinskii, example=Example(
    lambda: PrandtlIshlinskii(torch.tensor([0.0, 0.3, 0.8], dtype=torch.float64),
                              torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64),
                              linear_weight=0.4, nonnegative=True),
    bad_values={"weights": -1.0, "fixed_widths": -1.0}))


def _inverse_example() -> PrandtlIshlinskiiInverse:
    """The inverse of the forward example (three plays, one of width 0)."""
    return PrandtlIshlinskiiInverse(PrandtlIshlinskii(
        torch.tensor([0.0, 0.3, 0.8], dtype=torch.float64),
        torch.tensor([0.5, 0.3, 0.2], dtype=torch.float64), linear_weight=0.4,
        nonnegative=True))


register_operator("prandtl_ishlinskii_inverse", PrandtlIshlinskiiInverse, example=Example(
    _inverse_example, bad_values={"widths": -1.0, "weights": float("nan")}))
