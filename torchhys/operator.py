"""The operator protocol: what every hysteresis operator of torchhys implements.

Networks (:class:`~torchhys.InverseHysteresisNet`), the streaming compensator
(:mod:`torchhys.deploy.streaming`), export (:mod:`torchhys.deploy.export`) and the training registry
compose operators through this protocol only. An operator is one file: a subclass of
:class:`HysteresisOperator` with its sequence path, and a subclass of :class:`OperatorStep`
beside it with its per-sample step; both call the same maths. One line registers it by name
(:func:`register_operator`), with a small :class:`Example` that ``tests/test_conformance.py``
runs through the checks every operator must pass. See ``docs/adding-an-operator.md`` for a
worked example.

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
import warnings
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence
from torchhys.constraints import check_constraint
from torchhys.step import (
    OperatorStep,
    StateBlock,
    _check_step_state,
    custom_start,
)

__all__ = [
    "BROKEN_ENTRY_POINTS",
    "ENTRY_POINT_GROUP",
    "EXAMPLES",
    "OPERATORS",
    "AtomicLoad",
    "Example",
    "HysteresisOperator",
    "OperatorStep",
    "StateBlock",
    "check_operator",
    "custom_start",
    "example_of",
    "load_entry_points",
    "make_operator",
    "register_operator",
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


OPERATORS: dict[str, Callable[..., HysteresisOperator]] = {}
"""Operators by name: ``OPERATORS[name](**options)`` builds one (see :func:`make_operator`)."""


@dataclass(frozen=True)
class Example:
    """A small instance of a registered operator and what the conformance tests
    (``tests/test_conformance.py``) may expect of it.

    Args:
        build: returns a new instance: a few widths or levels, for inputs in about
            ``[-1, 1]``; the tests run it in float64.
        atol: float64 tolerance between the paths that compute the same output (chunked
            calls and one call, the step and ``forward``, the exported compensator and the
            eager one), relative to the output's scale (at least 1); 0: bit for bit.
        no_gradcheck: why ``torch.autograd.gradcheck`` of ``forward`` with respect to the
            input does not apply (e.g. an output piecewise constant in it), or None.
        bad_values: state-dict keys, each with a value that breaks a constraint that
            ``load_state_dict`` checks (the whole tensor filled with it), e.g.
            ``{"weights": -1.0}`` for a non-negative density; empty where none is checked.
    """

    build: Callable[[], HysteresisOperator]
    atol: float = 0.0
    no_gradcheck: str | None = None
    bad_values: Mapping[str, float] = dataclass_field(default_factory=dict)


EXAMPLES: dict[str, Example] = {}
"""The examples given to :func:`register_operator`, by name (see :func:`example_of`)."""


def register_operator(name: str, factory: Callable[..., HysteresisOperator], *,
                      example: Example | Callable[[], HysteresisOperator] | None = None
                      ) -> None:
    """Register an operator class (or factory) under ``name``, for specs by name.

    Registering the same factory under the same name again is a no-op (it keeps the example
    given before, unless a new one is given); so is registering a new definition of the same
    class (the same module and qualified name, as when a notebook cell that defines and
    registers it runs again), which then replaces the old one.

    Args:
        name: the name in specs and configs.
        factory: the class (or a function) that builds the operator from keyword options.
        example: a small instance for the conformance tests: an :class:`Example`, or a
            function that builds the instance (an ``Example`` with the default settings);
            None: ``factory()`` (the default options).

    Raises:
        ValueError: ``name`` is taken by another factory.
    """
    if not isinstance(name, str) or not name:
        raise ValueError(f"name must be a non-empty str, got {name!r}")
    if example is not None and not isinstance(example, Example):
        if not callable(example):
            raise TypeError(f"example must be an Example or a function that builds the "
                            f"operator, got {type(example).__name__}")
        example = Example(example)
    old = OPERATORS.get(name, factory)
    if old is not factory and _qualified(old) != _qualified(factory):
        raise ValueError(f"operator name {name!r} is registered already ({OPERATORS[name]})")
    OPERATORS[name] = factory
    if example is not None:
        EXAMPLES[name] = example
    elif old is not factory:  # a new definition: the old example built the old class
        EXAMPLES.pop(name, None)


def example_of(name: str) -> Example:
    """The :class:`Example` of the operator registered as ``name``: the one given to
    :func:`register_operator`, else ``Example(OPERATORS[name])`` (its default options).

    Raises:
        KeyError: an unknown name.
    """
    if name not in OPERATORS:
        raise KeyError(f"no operator is registered as {name!r}")
    return EXAMPLES.get(name) or Example(OPERATORS[name])


def _qualified(factory: object) -> tuple[str, str] | None:
    """``(module, qualified name)`` of a class or function, None for other callables."""
    module, qualname = getattr(factory, "__module__", None), getattr(factory, "__qualname__", None)
    if module is None or qualname is None or "<locals>" in qualname:
        return None
    return module, qualname


ENTRY_POINT_GROUP = "torchhys.operators"
"""The entry-point group of operators that other packages provide: the entry's name is the
operator's registered name, its value ``module:Class``."""
_entry_points_loaded = False
BROKEN_ENTRY_POINTS: dict[str, str] = {}
"""The entry points that could not be loaded or registered, by name: why (the message of
the warning :func:`load_entry_points` gave, and of the error when the name is used)."""


def load_entry_points() -> list[str]:
    """Register the operators of the installed packages' ``torchhys.operators`` entry points
    (once per process: later calls return ``[]``); called by :func:`make_operator` and by the
    training side before a name is looked up.

    A package declares one in its ``pyproject.toml``::

        [project.entry-points."torchhys.operators"]
        my_operator = "my_package.operators:MyOperator"

    An entry point that cannot be loaded (its import fails) or registered (its name is taken
    by another class) is skipped with one warning that names it and the error; the others
    are registered. Its name stays unknown: :func:`make_operator` raises a ``ValueError``
    with the same message where a spec names it (:data:`BROKEN_ENTRY_POINTS`).

    Returns:
        The names registered by this call.
    """
    global _entry_points_loaded
    if _entry_points_loaded:
        return []
    _entry_points_loaded = True
    from importlib.metadata import entry_points

    names = []
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            register_operator(ep.name, ep.load())
        except Exception as exc:  # noqa: BLE001 (whatever importing another package raises)
            text = " ".join(f"{type(exc).__name__}: {exc}".split())
            why = (f"entry point {ep.name!r} = {ep.value!r} of group {ENTRY_POINT_GROUP!r} "
                   f"cannot be loaded: {text}")
            BROKEN_ENTRY_POINTS[ep.name] = why
            warnings.warn(f"{why}; skipped (the other operators are registered)",
                          stacklevel=2)
            continue
        names.append(ep.name)
    return names


def make_operator(spec: Any, /, *, argument: str = "operator", **options: Any
                  ) -> HysteresisOperator:
    """The operator of a spec: the one resolver of networks, cascades and configs.

    A spec is one of:

    - a registered name, ``"eiho"``: ``OPERATORS["eiho"](**options)``;
    - a dict ``{"name": "eiho", **kwargs}``: ``OPERATORS["eiho"](**kwargs, **options)``
      (options of an operator may be specs themselves, e.g. a cascade's parts);
    - an operator (a :class:`HysteresisOperator`): itself, checked (no ``options``).

    The installed packages' entry points are registered first (:func:`load_entry_points`).

    Args:
        spec: the spec.
        argument: what the spec is called in error messages (``"operator"``,
            ``"operator[1]"``, ...).
        **options: keyword options of the operator given by name (or added to a dict's).

    Raises:
        ValueError: an unknown name (the message lists the registered ones; for the name of
            an entry point that could not be loaded, why), a dict without
            a ``name`` or with an option given twice, options the operator does not take
            (the operator's own checks name the option).
        TypeError: a spec of another type, an object outside the operator protocol, options
            given with an operator.
    """
    load_entry_points()
    if isinstance(spec, Mapping):
        if "name" not in spec:
            hint = (" ({'fit': ...} is a model family that `torchhys fit` identifies on the "
                    "training data, not an operator)" if "fit" in spec else "")
            raise ValueError(f"{argument}: a spec dict needs a 'name' (a registered operator), "
                             f"got {dict(spec)!r}{hint}")
        twice = sorted(set(spec) & set(options))
        if twice:
            raise ValueError(f"{argument}: option(s) {twice} given in the spec and as "
                             "keywords")
        name, options = spec["name"], {**{k: v for k, v in spec.items() if k != "name"},
                                       **options}
    elif isinstance(spec, str):
        name = spec
    elif isinstance(spec, nn.Module):
        if options:
            raise TypeError(f"{argument}: options {sorted(options)} apply to an operator "
                            f"given by name, not to a {type(spec).__name__} instance")
        return check_operator(spec, argument)
    else:
        raise TypeError(f"{argument} must be a registered operator name, a dict "
                        f"{{'name': NAME, **options}} or a HysteresisOperator, got "
                        f"{type(spec).__name__} {spec!r}")
    if isinstance(name, str) and name not in OPERATORS and name in BROKEN_ENTRY_POINTS:
        raise ValueError(f"{argument}: {BROKEN_ENTRY_POINTS[name]}")
    if not isinstance(name, str) or name not in OPERATORS:
        raise ValueError(f"{argument}: no operator is registered as {name!r}; registered "
                         f"names: {sorted(OPERATORS)}")
    try:
        op = OPERATORS[name](**options)
    except TypeError as e:
        raise ValueError(f"{argument} {name!r}: {e}") from e
    return check_operator(op, f"{argument} {name!r}")
