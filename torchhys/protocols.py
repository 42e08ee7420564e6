"""The roles a model plays besides its operators': a network, a sequence model and a
deployable.

The operator protocol (:mod:`torchhys.operator`, :mod:`torchhys.step`) is what an operator
implements. A model built of operators plays more roles, declared here:

* :class:`Network`: what the training side fits (:class:`~torchhys.training.module.
  InverseHysteresisModule`, the full-batch fits): its operators, the features of an input,
  the head on them and the normalization fitted to the training data.
* :class:`Deployable`: what the streaming compensator runs
  (:class:`~torchhys.deploy.streaming.StreamingCompensator`, and through it every export):
  its per-sample steps and the head on their features.
* :class:`SequenceModel`: the training side's other kind, a model of x -> y trained end to
  end on its output that records its training data's ranges (no features nor head to
  fit apart).

:class:`~torchhys.InverseHysteresisNet` plays the first two; a
:class:`~torchhys.PrandtlIshlinskiiInverse` is deployable on its own; a
:class:`~torchhys.compose.Composed` is a sequence model and deployable. A model of another
class plays a role by being an ``nn.Module`` with the members of its protocol (each is a
``typing.Protocol``, checkable with ``isinstance``); :func:`check_network`,
:func:`check_sequence_model` and :func:`check_deployable` are the one check of each, a
``TypeError`` naming the argument and every member it lacks.

Besides its members, a model may record its training data's ranges as buffers (``in_min``,
``in_max``, ``out_min``, ``out_max``, ``trend``: :meth:`InverseHysteresisNet.fit_normalization
<torchhys.InverseHysteresisNet.fit_normalization>`); the compensator's default limits, input
clamp and direction guard read them where present (:mod:`torchhys.deploy.ranges`).
"""

from collections.abc import Sequence
from typing import Any, Protocol, TypeVar, runtime_checkable

import torch
from torch import Tensor, nn

from torchhys.step import OperatorStep

__all__ = [
    "AffineForm", "AffineReadout", "Conditioned", "Deployable", "Network", "SequenceModel",
    "check_deployable", "check_network", "check_readout", "check_sequence_model",
    "missing_members", "n_conditions",
]


@runtime_checkable
class Network(Protocol):
    """What the training side fits: operators, then a head on their features.

    Shapes: x, y (batch, time) in physical units; features (batch, time, n_features), the
    input itself first.
    """

    operators: Sequence[nn.Module]
    """The operators (:class:`~torchhys.HysteresisOperator`), in the order of their
    features; the data-dependent ones (model families) are fitted on the training data
    before :meth:`fit_normalization`."""

    def features(self, x: Tensor, state: list | None = None, *, target: Tensor | None = None,
                 segment_a: Tensor | None = None) -> tuple[Tensor, list]:
        """The input space ``[x, f_1(x), ...]`` of x (batch, time): (batch, time,
        n_features) and the operators' states; ``state`` continues them. ``target`` and
        ``segment_a`` go to a non-causal operator (it needs the target)."""
        ...

    def head(self, features: Tensor) -> Tensor:
        """The output of the features (..., n_features) -> (...), in physical units."""
        ...

    def fit_normalization(self, x: Tensor, y: Tensor, *, mask: Tensor | None = None) -> None:
        """Fit what the head normalizes with to training data x, y (batch, time), over the
        samples of ``mask`` (bool, (batch, time); None: all); calibrate the operators'
        data-dependent settings first."""
        ...


@runtime_checkable
class Deployable(Protocol):
    """What the streaming compensator runs, one sample at a time.

    Shapes: a step takes x (batch, 1) and returns (batch, n_outputs); the head takes the
    features ``[x, step features...]`` (batch, 1 + sum of n_outputs) and returns the command
    (batch, 1).
    """

    def streaming_steps(self, dtype: torch.dtype) -> list[OperatorStep]:
        """The per-sample steps (:class:`~torchhys.step.OperatorStep`) in ``dtype``, with the
        current parameters (detached); raise ``ValueError`` where the model cannot stream
        (a non-causal operator, an uncalibrated setting)."""
        ...

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        """A module of the steps' features (batch, n) -> the command (batch, 1), physical
        units, in ``dtype``; written for TorchScript and ``torch.export``."""
        ...


@runtime_checkable
class AffineReadout(Protocol):
    """A compensator head (:meth:`Deployable.streaming_head`) whose command is affine in
    weights of its own: ``head(f) == readout_basis(f) @ readout_weights()`` up to rounding,
    what the adaptive compensator (:class:`~torchhys.deploy.adaptive.AdaptiveCompensator`)
    updates online. Shapes: ``readout_basis``: the features (batch, n) -> (batch, m);
    ``readout_weights()``: (m,), in the head's dtype.
    """

    def readout_basis(self, features: Tensor) -> Tensor:
        """The readout's regressors of the head's features: (batch, n) -> (batch, m)."""
        ...

    def readout_weights(self) -> Tensor:
        """The readout's weights (m,) of the fitted head."""
        ...


@runtime_checkable
class AffineForm(Protocol):
    """A deployable whose head has no affine readout of its own but which streams, equally,
    as other steps and a head that has (:class:`AffineReadout`): the Prandtl-Ishlinskii
    inverse (its plays and their weights). The adaptive compensator runs this form."""

    def affine_form(self, dtype: torch.dtype) -> tuple[list[OperatorStep], nn.Module]:
        """``(steps, head)``, in ``dtype``, equal to the model's own up to rounding."""
        ...


@runtime_checkable
class Conditioned(Protocol):
    """A deployable whose command also depends on measured operating conditions (a coil
    voltage, a supply pressure, a temperature): ``n_conditions`` further inputs per sample.

    The compensator then takes ``step(x_t, conditions)`` with conditions (batch,
    n_conditions); a step of ``n_inputs == 1 + n_conditions`` gets ``[x, conditions]``
    (batch, 1 + n_conditions), a step of one input gets x alone; the head's features are
    ``[x, conditions..., step features...]``. The model records its training conditions'
    ranges as buffers ``cond_min``, ``cond_max`` (n_conditions,), which the compensator's
    condition clamp reads (:func:`torchhys.deploy.ranges.default_condition_ranges`).
    """

    n_conditions: int
    """Number of condition inputs per sample (>= 1)."""


def n_conditions(model: object) -> int:
    """The model's :attr:`Conditioned.n_conditions` (0 for a model without conditions).

    Raises:
        TypeError: ``n_conditions`` is not an int >= 0.
    """
    if not isinstance(model, Conditioned):
        return 0
    n = model.n_conditions
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise TypeError(f"{type(model).__name__}.n_conditions must be an int >= 0, got {n!r}")
    return n


@runtime_checkable
class SequenceModel(Protocol):
    """What the training side fits besides a :class:`Network`: a sequence model x (batch,
    time) -> y (batch, time), trained end to end on its output, which records its training
    data's ranges (``in_min``, ``in_max``, ``out_min``, ``out_max``, ``trend``) for the
    compensator (a :class:`~torchhys.compose.Composed`: a user's module through
    :func:`~torchhys.compose.compose`)."""

    def forward(self, x: Tensor) -> Tensor:
        """The output y (batch, time) of x (batch, time), in physical units."""
        ...

    def record_ranges(self, x: Tensor, y: Tensor, *, mask: Tensor | None = None) -> None:
        """Record the ranges of training data x, y (batch, time), over the samples of
        ``mask`` (bool, (batch, time); None: all)."""
        ...


P = TypeVar("P")


def missing_members(obj: object, protocol: type) -> list[str]:
    """The members of ``protocol`` (:class:`Network`, :class:`Deployable`) that ``obj``
    lacks, in the order the protocol declares them."""
    declared = [*getattr(protocol, "__annotations__", {}),
                *(k for k, v in vars(protocol).items() if callable(v) and not k.startswith("_"))]
    return [m for m in declared if not hasattr(obj, m)]


def _check(obj: Any, argument: str, protocol: type[P], roles: str) -> P:
    missing = missing_members(obj, protocol)
    if isinstance(obj, nn.Module) and not missing:
        return obj
    why = [] if isinstance(obj, nn.Module) else ["it is no nn.Module"]
    why += [f"it has no {', '.join(missing)}"] if missing else []
    raise TypeError(f"{argument} must be an nn.Module with the members of "
                    f"torchhys.protocols.{protocol.__name__} ({roles}), got "
                    f"{type(obj).__name__}: {'; '.join(why)}")


def check_network(obj: Any, argument: str = "net") -> Network:
    """``obj``, checked to be a :class:`Network` (an ``nn.Module`` with its members).

    Raises:
        TypeError: naming ``argument`` and every member ``obj`` lacks.
    """
    return _check(obj, argument, Network,
                  "operators, features, head and fit_normalization, as an "
                  "InverseHysteresisNet has; a user's module trains through "
                  "torchhys.compose.compose, as a SequenceModel")


def check_sequence_model(obj: Any, argument: str = "model") -> SequenceModel:
    """``obj``, checked to be a :class:`SequenceModel` (an ``nn.Module`` with its members).

    Raises:
        TypeError: naming ``argument`` and every member ``obj`` lacks.
    """
    return _check(obj, argument, SequenceModel,
                  "forward(x) and record_ranges(x, y, mask=), as a torchhys.compose.Composed "
                  "has")


def check_deployable(obj: Any, argument: str = "model") -> Deployable:
    """``obj``, checked to be a :class:`Deployable` (an ``nn.Module`` with its members).

    Raises:
        TypeError: naming ``argument`` and every member ``obj`` lacks.
    """
    return _check(obj, argument, Deployable,
                  "streaming_steps(dtype) and streaming_head(dtype), as an "
                  "InverseHysteresisNet or a PrandtlIshlinskiiInverse has")


def check_readout(head: Any, argument: str = "model") -> AffineReadout:
    """``head``, checked to be an :class:`AffineReadout` (the adaptive compensator's need).

    Raises:
        ValueError: naming ``argument``: its head has no affine readout to adapt.
    """
    if isinstance(head, nn.Module) and not missing_members(head, AffineReadout):
        return head
    raise ValueError(f"{argument}: its compensator head ({type(head).__name__}) has no affine "
                     "readout to adapt (torchhys.protocols.AffineReadout: readout_basis and "
                     "readout_weights); adapt works on an InverseHysteresisNet or a "
                     "ScheduledReadout, use adapt='none' for this model")
