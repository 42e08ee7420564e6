"""The operator protocol: what every hysteresis operator of torchhys implements.

Networks (:class:`~torchhys.InverseHysteresisNet`), the streaming compensator
(:mod:`torchhys.deploy.streaming`), export (:mod:`torchhys.deploy.export`) and the training registry
compose operators through this protocol only. An operator is one file: a subclass of
:class:`HysteresisOperator` with its sequence path, and a subclass of :class:`OperatorStep`
beside it with its per-sample step; both call the same maths. One line registers it by name
(:func:`torchhys.registry.register_operator`), with a small
:class:`~torchhys.testing.Example` that ``tests/test_conformance.py`` runs through the checks
every operator must pass. See ``docs/adding-an-operator.md`` for a worked example.

``HysteresisOperator`` (an ``nn.Module``)::

    n_outputs: int                       features per sample (>= 1)
    causal: bool = True                  False: forward needs the target (not deployable)
    forward(x, state=None) -> (features, state)
        x (batch, time); features (batch, time) or (batch, time, n_outputs); the state
        continues the sequence: chunked calls equal one call
    calibrate(x) -> None                 data-dependent settings from the training input,
                                         called before normalization is fitted (default: none)
    predictor(x) -> () -> features       the output on a fixed input as a closure of the
                                         parameters, for full-batch fits (default: forward)
    constraints: {name: kind}            what a loaded parameter or buffer must be (checked
                                         by load_state_dict; default: none); check_loaded()
                                         and after_load() for the rest
    streaming_step(dtype) -> OperatorStep
                                         its per-sample step, with the current parameters
                                         (detached) in ``dtype``; raises ValueError where the
                                         operator cannot be deployed

``OperatorStep`` (an ``nn.Module`` written for TorchScript and ``torch.export``)::

    state_spec: list[StateBlock]         the step's state, one (batch, size) tensor a block
    n_outputs: int                       features per sample
    forward(x, state) -> (features, state)
        x (batch, 1) in the compensator's dtype; state: one tensor per block, in the order
        of state_spec; features (batch, n_outputs); the new state in the same layout

A :class:`StateBlock` says how its columns start: at a row's first finite sample ``x0`` the
compensator sets them to ``start + from_sample * x0`` (a play starts at 0, an anchor at the
sample itself) before the step runs, so the step needs no "fresh" flag. A step whose start
is not of that form overrides ``initial_state(x0)`` (a cascade builds its start from its
parts'). Blocks of kind
``"float"`` are in the compensator's dtype, ``"float64"`` keep a float64 accumulator,
``"int64"`` hold counters and indices (``from_sample`` must be 0). The step's maths must not
branch in Python on tensor values (use ``torch.where``); its Python ints, floats and bools are
fixed when it is built.
"""

import abc
import copy
from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence
from torchhys.constraints import check_constraint
from torchhys.step import OperatorStep, _check_step_state

__all__ = [
    "AtomicLoad",
    "HysteresisOperator",
    "check_operator",
]


class AtomicLoad:
    """Mixin of ``nn.Module`` subclasses: ``load_state_dict`` loads all or nothing.

    ``nn.Module.load_state_dict`` copies module by module, so a state dict that one
    submodule rejects (a shape mismatch, a negative Preisach density) leaves the submodules
    before it loaded. Here the state dict is first loaded into a copy of the module; only if
    that succeeds is it loaded into the module itself. On error the module is as it was
    (a module that cannot be deep-copied loads directly, module by module). Load hooks run
    on the copy too.
    """

    def load_state_dict(self, state_dict: Any, strict: bool = True, assign: bool = False) -> Any:
        try:
            trial = copy.deepcopy(self)
        except Exception:  # an attribute that cannot be copied (a non-leaf tensor, a lock)
            trial = None
        if trial is not None:
            nn.Module.load_state_dict(trial, state_dict, strict=strict, assign=assign)
        return super().load_state_dict(state_dict, strict=strict, assign=assign)  # type: ignore[misc]


class HysteresisOperator(AtomicLoad, nn.Module, abc.ABC):
    """Base class of the operators that networks, streaming and export compose.

    Subclasses implement :meth:`streaming_step` and set ``n_outputs``; they override
    :meth:`forward` with a sequence path (the default steps through the samples).
    """

    n_outputs: int = 1
    causal: bool = True

    def forward(self, x: Tensor, state: Any = None) -> tuple[Tensor, Any]:
        """x (time,) or (batch, time) -> features ``x.shape`` or ``x.shape + (n_outputs,)``,
        and the state at the last sample.

        Default: the per-sample step (:meth:`streaming_step` in ``x``'s dtype) run over the
        samples in a Python loop, from its first-sample state (:meth:`OperatorStep.initial_state`)
        or from ``state`` (the step's list of tensors, as returned). Correct but slow, and
        the step holds the parameters detached (gradients flow to ``x`` only): an operator
        that trains its parameters, or runs on long records, overrides it with a sequence
        path that calls the same maths.
        """
        xb, added = as_batched_sequence(x, "x")
        step = self.streaming_step(xb.dtype)
        if state is None:
            state = step.initial_state(xb[:, :1])
        else:
            _check_step_state(state, step.state_spec, xb.shape[0])
        outs = []
        for xt in xb.unbind(1):
            f, state = step(xt.unsqueeze(1), state)
            outs.append(f)
        out = torch.stack(outs, 1)
        if self.n_outputs == 1:
            out = out.squeeze(-1)
        return (out.squeeze(0) if added else out), state

    @abc.abstractmethod
    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        """The per-sample step with the current parameters (detached), in ``dtype``."""

    constraints: ClassVar[Mapping[str, str]] = {}
    """What a loaded value must be: the name of one of this module's own parameters or
    buffers -> a constraint kind of :data:`torchhys.constraints.CONSTRAINTS`, e.g.
    ``{"weights": "nonnegative"}``. ``load_state_dict`` checks every entry it is given (of
    the module's shape) before anything is copied; the error names the key."""

    def calibrate(self, x: Tensor) -> None:  # noqa: B027 (optional hook, empty by default)
        """Set data-dependent settings from the training input x (batch, time); default:
        nothing."""

    def predictor(self, x: Tensor) -> Callable[[], Tensor]:
        """The output on a fixed input x (batch, time), from the zero (fresh) state, as a
        closure of the parameters: full-batch fitting calls it at every step. Default:
        ``lambda: self(x)[0]``; an operator overrides it where work that does not depend on
        the trained parameters can be done once (e.g. plays of fixed widths)."""
        return lambda: self(x)[0]

    def mse_closure(self, x: Tensor, y: Tensor, samples: Tensor) -> Callable[[], Tensor]:
        """The mean squared error of the output on a fixed input x (batch, time), from the
        zero state, against y (batch, time) over ``samples`` (bool, (batch, time)), as a
        closure of the parameters: what full-batch fitting minimizes. Default: from
        :meth:`predictor`; an operator overrides it where the loss and its gradient have a
        faster form (e.g. :class:`~torchhys.GeneralizedPrandtlIshlinskii`)."""
        predict = type(self).predictor(self, x)
        return lambda: (predict() - y)[samples].square().mean()

    def check_loaded(self, values: Mapping[str, Tensor], prefix: str) -> None:  # noqa: B027
        """Constraints between the values about to be loaded (``alpha >= beta``, an
        invertible model), after the declared :attr:`constraints` hold. ``values``: each of
        the module's own parameters and buffers by name, the given value or else the current
        one (a partial state dict). Raise ``ValueError`` naming ``prefix + key``; default:
        nothing."""

    def after_load(self) -> None:  # noqa: B027 (optional hook, empty by default)
        """Update Python-level settings from the loaded buffers; default: nothing."""

    def _load_from_state_dict(self, state_dict: Mapping[str, Any], prefix: str,
                              *args: Any, **kwargs: Any) -> None:
        """The declared :attr:`constraints` and :meth:`check_loaded`, then the copy, then
        :meth:`after_load` (all or nothing across modules: :class:`AtomicLoad`)."""
        own = dict(self._parameters)
        own.update((k, v) for k, v in self._buffers.items()
                   if k not in self._non_persistent_buffers_set)
        values = {}
        for name, current in own.items():
            given = state_dict.get(prefix + name)
            usable = isinstance(given, Tensor) and (current is None or given.shape == current.shape)
            if usable and name in self.constraints:
                check_constraint(given, self.constraints[name], prefix + name)
            if isinstance(current, Tensor) or usable:
                values[name] = given if usable else current
        self.check_loaded(values, prefix)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
        self.after_load()


_REQUIRED = ("forward", "streaming_step", "calibrate", "n_outputs", "causal")


def check_operator(op: object, name: str = "operator") -> HysteresisOperator:
    """Raise ``TypeError`` unless ``op`` implements the operator protocol."""
    if not isinstance(op, HysteresisOperator):
        kind = type(op).__name__
        missing = [m for m in _REQUIRED if not hasattr(op, m)]
        hint = f" (it has no {', '.join(missing)})" if missing else ""
        raise TypeError(
            f"{name} must be a torchhys.HysteresisOperator (an nn.Module that implements "
            f"forward(x, state) -> (features, state), n_outputs and streaming_step(dtype); "
            f"see docs/adding-an-operator.md), got {kind}{hint}"
        )
    n = op.n_outputs
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise TypeError(f"{name} {type(op).__name__}: n_outputs must be an int >= 1, got {n!r}")
    m = getattr(op, "n_inputs", 1)  # a multi-input block (torchhys.dynamics) is no operator
    if m != 1:
        raise TypeError(f"{name} {type(op).__name__} has n_inputs = {m}: an operator takes one "
                        "input column (x (batch, time)); use a block with n_inputs=1 here")
    return op
