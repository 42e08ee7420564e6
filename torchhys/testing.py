"""The conformance checks of the operator protocol, for torchhys and its plugins.

:func:`check_conformance` runs one operator through the checks that every registered
operator passes (``tests/test_conformance.py`` runs them over the registry: the suite and this
function are one code). :class:`Example` is a small instance of an operator and what the
checks may expect of it, given to :func:`torchhys.registry.register_operator`. A plugin
author checks an operator with::

    from torchhys.testing import Example, check_conformance

    check_conformance(MyOperator, Example(lambda: MyOperator(0.3), bad_values={"r": -1.0}))

A check that fails raises ``AssertionError`` naming the operator, the check and what differs;
the result says which checks ran and why the others did not apply. The checks compare paths
that compute the same output within the example's ``atol`` relative to the output's scale
(0: bit for bit), on a signal of nested reversals and a walk on a grid with flat stretches
(turning points, ties, repeated samples), with the compiled kernels where they run and with
the scans. The C99 and ONNX steps are checked against the TorchScript compensator by the
suite (they need a C compiler and ONNX Runtime: ``tests/test_conformance.py``).

The checks under torch's own tools (:data:`TORCH_CHECKS`: ``torch.compile(fullgraph=True)``,
``torch.export`` with a dynamic time dimension, ``torch.func.vmap`` over inputs and over
stacked parameters, meta and fake tensors, ``torch.func.grad``, ``gradgradcheck``) are
documented in ``docs/torch_integration.md``; the compiling ones run when asked::

    check_conformance("backlash", checks=["compile", "export"])

:func:`check_composed` runs a composed model (:func:`torchhys.compose.compose` of a user's
module of operators, recurrent layers and elementwise maths) through the checks of
:data:`COMPOSED_CHECKS`, the same code as the operators' where a check is the same::

    from torchhys.testing import check_composed

    check_composed(lambda: MyModel().double())  # every check but AOTInductor's

:func:`check_conditioned` runs a fitted model with operating conditions (``n_conditions >
0``, ``docs/conditions.md``) on the caller's x (batch, time) and conditions (batch, time, n)
through the checks of :data:`CONDITIONED_CHECKS`, the exported steps (TorchScript, C99,
ONNX Runtime, AOTInductor when asked) among them::

    from torchhys.testing import check_conditioned

    check_conditioned(model, x, conditions)  # every check but AOTInductor's
"""

import copy
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from typing import Any

import torch

import torchhys.registry as registry
from torchhys.operator import HysteresisOperator

__all__ = ["CHECKS", "COMPILE_CHECKS", "COMPOSED_ATOL", "COMPOSED_CHECKS",
           "COMPOSED_COMPILE_CHECKS", "CONDITIONED_CHECKS", "CONDITIONED_COMPILE_CHECKS",
           "DEFAULT_CHECKS", "TORCH_CHECKS", "Example", "check_composed", "check_conditioned",
           "check_conformance", "example_of"]

CHECKS: dict[str, str] = {
    "protocol": "the example is an operator of its registered class",
    "chunked": "chunked calls, the state carried, equal one call; a row as (time,) its row "
               "of a batch",
    "step": "the per-sample step equals forward",
    "gradcheck": "gradcheck of forward in the input",
    "torchscript": "the TorchScript compensator equals the eager one and the network",
    "aoti": "the AOTInductor compensator equals the eager one and holds a NaN",
    "nan": "a NaN sample is held, counted, and leaves the state",
    "wrong_shape": "a state dict with a wrong shape loads nothing, naming the entry",
    "bad_value": "a value breaking a declared constraint is refused, naming the entry",
    "bad_input": "bad input (text, integers, 3-d, NaN) is an error naming x",
    "bad_state": "a state of another batch, or with a NaN, is an error naming state",
    "compile": "torch.compile(fullgraph=True): output, state and gradients (input and "
               "parameters) equal eager within 1e-12 (float64)",
    "export": "torch.export.export with a dynamic time dimension (torch.export.Dim): the "
              "program's output and state equal eager at the traced length and at others",
    "vmap": "torch.func.vmap over a batch of inputs equals each input's own call",
    "vmap_params": "torch.func.vmap over stacked parameters and buffers "
                   "(torch.func.stack_module_state + functional_call) equals each model's call",
    "meta": "on the meta device (op.to('meta')) the output and state have eager's shapes "
            "and dtypes",
    "fake": "under FakeTensorMode (fake parameters, buffers and input) the output and state "
            "have eager's shapes and dtypes",
    "func_grad": "torch.func.grad in the input and the parameters equals torch.autograd.grad",
    "gradgradcheck": "gradgradcheck of forward in the input (float64), or the example's "
                     "documented refusal (no_gradgradcheck) raised by double backward",
}
"""The checks by name: what each holds. ``chunked``, ``step``, ``gradcheck``, ``vmap``,
``vmap_params``, ``func_grad`` and ``gradgradcheck`` run with the compiled play and filter
kernels (where they run) and with the scans; ``compile`` and ``export`` with the default
path. ``docs/torch_integration.md`` says what the torch checks cover."""
COMPILE_CHECKS = ("aoti", "compile", "export")
"""The checks that compile or trace a program (tens of seconds each on a CPU)."""
TORCH_CHECKS = ("compile", "export", "vmap", "vmap_params", "meta", "fake", "func_grad",
                "gradgradcheck")
"""The checks of the operator under torch's own tools (``torchhys._conformance_torch``)."""
DEFAULT_CHECKS = tuple(c for c in CHECKS if c not in COMPILE_CHECKS)
"""The checks :func:`check_conformance` runs by default: all but :data:`COMPILE_CHECKS`."""

COMPOSED_CHECKS: dict[str, str] = {
    "protocol": "the model is a Composed of one composed step that passes "
                "torchhys.step.check_step, its state blocks named '<node>.<block>'",
    "chunked": "the composed step, and the compensator's step, in chunks of 1, 1, 2, 27 and "
               "the rest (the state carried) equal one run bit for bit; a row alone its row "
               "of a batch",
    "step": "the composed step sample by sample equals the module on the whole sequence "
            "(within atol), and the compensator's commands the step bit for bit",
    "state": "the compensator's state saved and restored continues as it did, reset() starts "
             "afresh, step_explicit equals step (commands and state, bit for bit), a state "
             "of another layout is an error naming the block",
    "gradcheck": "gradcheck of the composed step over a sequence in the input, and of one "
                 "step in the input and a reached state (float64)",
    "nan": "a NaN sample is held, counted, and leaves the state",
    "torchscript": "the TorchScript compensator equals the eager one and the module within "
                   "1e-12 (float64)",
    "aoti": "the AOTInductor compensator equals the eager one and the module within 1e-12 "
            "(float64) and holds a NaN",
    "float32": "the float32 compensator equals the float64 module within 1e-4 of the "
               "output's scale (docs/composing.md)",
}
"""The checks of a composed model by name (:func:`check_composed`): what each holds. The C99
and ONNX steps of the compositions are checked against the TorchScript compensator by the
suite (``tests/test_conformance.py``)."""
COMPOSED_COMPILE_CHECKS = ("aoti",)
"""The checks of a composed model that compile a program (tens of seconds on a CPU)."""
COMPOSED_ATOL = 1e-12
"""The default tolerance of the composed step against the module (float64, relative to the
output's scale): torch's fused recurrent kernels sum in another order than the step."""

CONDITIONED_CHECKS: dict[str, str] = {
    "protocol": "n_conditions matches the conditions' columns, cond_min < cond_max are "
                "recorded (finite, (n,)), the compensator takes n conditions and clamps them "
                "to that range widened by 5 %",
    "chunked": "the model's forward in chunks of 1, 1, 2, 27 and the rest (the state "
               "carried; where it takes a state) and the compensator's step_explicit in "
               "chunks (bit for bit) equal one call; a row alone its row of a batch",
    "step": "the compensator's step (no clamp, limits that never act) sample by sample "
            "equals the model's sequence output (within atol), step_explicit the step "
            "(commands and state bit for bit)",
    "gradcheck": "gradcheck of the model's output in the conditions, and in x and the "
                 "conditions unless no_gradcheck_x (float64, the first row's first 24 "
                 "samples)",
    "nan": "a NaN or inf condition, or a NaN input, holds the command, is counted and "
           "leaves the state",
    "bad_state": "a compensator state with a tensor too few or of another dtype, a model "
                 "state with a block too many (where the forward takes one): one-line "
                 "errors naming state; a state dict with a wrong-shaped cond_min loads nothing",
    "conditions": "conditions missing, or one column too many, to the compensator's step "
                  "and forward and to the model: one-line errors naming conditions",
    "torchscript": "the TorchScript file's step and forward equal the torch compensator "
                   "within 1e-12 (float64) with a NaN and an out-of-range condition and a "
                   "NaN input, the counters and the state equal, its metadata the "
                   "conditions' clamp",
    "c": "the C99 step (compiled with cc -std=c99 -O2 -Wall -Wextra -Werror -pedantic) "
         "equals the torch compensator within 1e-12 on the same inputs, the counters equal",
    "onnx": "the ONNX file's step in ONNX Runtime equals the torch compensator within 1e-12 "
            "on the same inputs, the counters, the state and the metadata equal; missing "
            "or wrong-shaped conditions are one-line errors",
    "aoti": "the AOTInductor package's step, as the ONNX file's",
}
"""The checks of a conditioned model by name (:func:`check_conditioned`): what each holds."""
CONDITIONED_COMPILE_CHECKS = ("aoti",)
"""The checks of a conditioned model that compile a program (tens of seconds on a CPU)."""


@dataclass(frozen=True)
class Example:
    """A small instance of an operator and what the conformance checks
    (:func:`check_conformance`) may expect of it. Calling it builds the instance.

    Args:
        build: returns a new instance: a few widths or levels, for inputs in about
            ``[-1, 1]``; the checks run it in float64 (or the dtype asked).
        atol: float64 tolerance between the paths that compute the same output (chunked
            calls and one call, the step and ``forward``, the exported compensator and the
            eager one), relative to the output's scale (at least 1); 0: bit for bit.
        no_gradcheck: why ``torch.autograd.gradcheck`` of ``forward`` with respect to the
            input does not apply (e.g. an output piecewise constant in it), or None.
        bad_values: state-dict keys, each with a value that breaks a constraint that
            ``load_state_dict`` checks (the whole tensor filled with it), e.g.
            ``{"weights": -1.0}`` for a non-negative density; empty where none is checked.
        no_gradgradcheck: where the second derivative does not exist, a regular expression
            that the error of double backward matches (the check asserts that it is raised
            instead of running ``gradgradcheck``), or None.
    """

    build: Callable[[], HysteresisOperator]
    atol: float = 0.0
    no_gradcheck: str | None = None
    bad_values: Mapping[str, float] = dataclass_field(default_factory=dict)
    no_gradgradcheck: str | None = None

    def __call__(self) -> HysteresisOperator:
        return self.build()


def example_of(name: str) -> Example:
    """The :class:`Example` of the operator registered as ``name``: the one given to
    :func:`~torchhys.registry.register_operator` (a function given there: an ``Example``
    with the default settings), else ``Example(OPERATORS[name])`` (its default options).

    Raises:
        KeyError: an unknown name.
    """
    if name not in registry.OPERATORS:
        raise KeyError(f"no operator is registered as {name!r}")
    given = registry.EXAMPLES.get(name) or registry.OPERATORS[name]
    return given if isinstance(given, Example) else Example(given)


def check_conformance(operator: str | type | HysteresisOperator, example: Any = None, *,
                      dtype: torch.dtype = torch.float64,
                      checks: Sequence[str] | None = None) -> dict[str, str | None]:
    """Run one operator through the conformance checks of the operator protocol.

    Args:
        operator: a registered name, an operator class (or a function that builds one from
            no options), or an operator (each check builds a fresh copy of it).
        example: its :class:`Example` (or a function that builds the instance); None: the
            registered one for a name (:func:`example_of`), else ``Example(operator)``.
        dtype: ``torch.float64`` (the examples' tolerances) or ``torch.float32`` (at least
            1e-4 relative to the output's scale; no gradcheck).
        checks: names of :data:`CHECKS` to run, in their order; None: :data:`DEFAULT_CHECKS`
            (all but :data:`COMPILE_CHECKS`: AOTInductor, ``torch.compile`` and
            ``torch.export``).

    Returns:
        Each check run -> None where it held, else why it does not apply (a non-causal
        operator's forward takes the target: every check is skipped; an example with
        ``no_gradcheck``; no ``bad_values``; no state).

    Raises:
        AssertionError: a check that fails, naming the operator, the check and what
            differs (an exception raised inside a check is chained to it).
        ValueError: an unknown name or check, a dtype other than float32 or float64.
        TypeError: ``operator`` or ``example`` of another type.
    """
    import torchhys._conformance as conformance  # the exporters, loaded when checks run
    import torchhys._conformance_torch as torch_conformance

    case = _case(operator, example, dtype)
    names = DEFAULT_CHECKS if checks is None else tuple(checks)
    unknown = [c for c in names if c not in CHECKS]
    if isinstance(checks, str) or unknown:
        raise ValueError(f"checks must be names of torchhys.testing.CHECKS {list(CHECKS)}, "
                         f"got {checks!r}")
    if not case.build().causal:
        why = (f"{case.label} is not causal: its forward takes the target, outside the causal "
               "protocol these checks cover")
        return dict.fromkeys(names, why)
    results: dict[str, str | None] = {}
    for name in names:
        runs = torch_conformance.RUNS if name in TORCH_CHECKS else None
        for where, call in conformance.run(case, name, runs):
            try:
                results[name] = call()
            except Exception as e:  # noqa: BLE001 (whatever the operator raises fails the check)
                text = str(e) if isinstance(e, AssertionError) else f"{type(e).__name__}: {e}"
                raise AssertionError(f"{case.label} fails the check {name!r} ({CHECKS[name]})"
                                     f"{where}: {text}") from e
            if results[name] is not None:
                break
    return results


def check_composed(model: Any, *, atol: float = COMPOSED_ATOL, no_gradcheck: str | None = None,
                   dtype: torch.dtype = torch.float64,
                   checks: Sequence[str] | None = None) -> dict[str, str | None]:
    """Run a composed model through the conformance checks of :data:`COMPOSED_CHECKS`.

    Args:
        model: a function that builds it (called after ``torch.manual_seed(0)`` for each
            check: a :class:`~torchhys.compose.Composed`, or a module that
            :func:`~torchhys.compose.compose` takes), an :class:`Example` of one (its
            ``build``, ``atol`` and ``no_gradcheck``), or the module itself (each check
            composes a copy). Inputs in about ``[-1, 1]``, or in the Composed's recorded
            input range.
        atol: the composed step against the module, relative to the output's scale (at
            least 1); 0: bit for bit (an Example's ``atol`` instead).
        no_gradcheck: why gradcheck does not apply, or None.
        dtype: ``torch.float64`` or ``torch.float32`` (at least 1e-4; no gradcheck).
        checks: names of :data:`COMPOSED_CHECKS`, in their order; None: all but
            :data:`COMPOSED_COMPILE_CHECKS`.

    Returns:
        Each check run -> None where it held, else why it does not apply.

    Raises:
        AssertionError: a check that fails, naming the model, the check and what differs.
        ValueError: an unknown check, a dtype other than float32 or float64.
        TypeError: ``model`` of another type.
    """
    import torchhys._conformance_compose as compose_conformance

    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    names = (tuple(c for c in COMPOSED_CHECKS if c not in COMPOSED_COMPILE_CHECKS)
             if checks is None else tuple(checks))
    if isinstance(checks, str) or any(c not in COMPOSED_CHECKS for c in names):
        raise ValueError(f"checks must be names of torchhys.testing.COMPOSED_CHECKS "
                         f"{list(COMPOSED_CHECKS)}, got {checks!r}")
    if isinstance(model, Example):
        build, atol, no_gradcheck = model.build, model.atol, model.no_gradcheck
    elif isinstance(model, torch.nn.Module):
        build = lambda module=model: copy.deepcopy(module)  # noqa: E731
    elif callable(model):
        build = model
    else:
        raise TypeError(f"model must be an nn.Module, an Example or a function that builds "
                        f"one, got {type(model).__name__}")
    label = f"composed model {_name(build)}"
    case = compose_conformance.ComposedCase(label, build, atol, no_gradcheck, dtype)
    return _run_checks(case, names, compose_conformance.RUNS, COMPOSED_CHECKS)


def _run_checks(case: Any, names: Sequence[str], runs: dict, described: dict
                ) -> dict[str, str | None]:
    """Each check of ``names`` run on ``case`` (``runs[name](case)``): None where it held or
    why it does not apply; the first that fails an ``AssertionError`` naming the model, the
    check (``described[name]``) and what differs."""
    results: dict[str, str | None] = {}
    for name in names:
        try:
            results[name] = runs[name](case)
        except Exception as e:  # noqa: BLE001 (whatever the model raises fails the check)
            text = str(e) if isinstance(e, AssertionError) else f"{type(e).__name__}: {e}"
            raise AssertionError(f"{case.label} fails the check {name!r} "
                                 f"({described[name]}): {text}") from e
    return results


def check_conditioned(model: Any, x: torch.Tensor, conditions: torch.Tensor, *,
                      atol: float = COMPOSED_ATOL, no_gradcheck_x: str | None = None,
                      checks: Sequence[str] | None = None) -> dict[str, str | None]:
    """Run a fitted model with operating conditions through :data:`CONDITIONED_CHECKS`.

    Args:
        model: the fitted model (each check uses a copy), or a function that builds one
            (called after ``torch.manual_seed(0)`` for each check), float64: a module with
            ``n_conditions``, ``cond_min``/``cond_max``, streaming steps
            (``docs/conditions.md``) and ``forward(x, conditions=c)`` (``forward(x, state,
            conditions=c)`` where it continues from a state) returning y or ``(y, state)``.
        x: float64 (batch, time), time >= 40, inside the fitted input range.
        conditions: float64 (batch, time, n_conditions), inside the fitted ranges.
        atol: the compensator's step against the model's sequence output, the chunked and
            the row-alone calls, relative to the output's scale (at least 1); 0: bit for bit.
        no_gradcheck_x: why gradcheck in x does not apply (kinks in the samples, e.g. the
            plays' corners), or None; gradcheck in the conditions runs either way.
        checks: names of :data:`CONDITIONED_CHECKS`, in their order; None: all but
            :data:`CONDITIONED_COMPILE_CHECKS`.

    Returns:
        Each check run -> None where it held, else why it does not apply (no C compiler,
        no ONNX Runtime; gradcheck in the conditions only).

    Raises:
        AssertionError: a check that fails, naming the model, the check and what differs.
        ValueError, TypeError: an unknown check; x or conditions not float64, finite, of
            matching shapes; ``model`` of another type.
    """
    import torchhys._conformance_conditions as conditioned

    names = (tuple(c for c in CONDITIONED_CHECKS if c not in CONDITIONED_COMPILE_CHECKS)
             if checks is None else tuple(checks))
    if isinstance(checks, str) or any(c not in CONDITIONED_CHECKS for c in names):
        raise ValueError(f"checks must be names of torchhys.testing.CONDITIONED_CHECKS "
                         f"{list(CONDITIONED_CHECKS)}, got {checks!r}")
    x, conditions = conditioned.check_inputs(x, conditions)
    if isinstance(model, torch.nn.Module):
        build = lambda module=model: copy.deepcopy(module)  # noqa: E731
    elif callable(model):
        build = model
    else:
        raise TypeError(f"model must be an nn.Module or a function that builds one, got "
                        f"{type(model).__name__}")
    label = f"conditioned model {_name(build)}"
    case = conditioned.ConditionedCase(label, build, x, conditions, atol, no_gradcheck_x)
    return _run_checks(case, names, conditioned.RUNS, CONDITIONED_CHECKS)


def _name(build: Callable[[], Any]) -> str:
    """The class of the module ``build`` makes (a Composed's: its module's), else its name."""
    name = getattr(build, "__name__", "<lambda>")
    if name != "<lambda>":
        return name
    torch.manual_seed(0)
    built = build()
    return type(getattr(built, "module", built)).__name__


def _case(operator: Any, example: Any, dtype: torch.dtype) -> Any:
    import torchhys._conformance as conformance

    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    if example is not None and not callable(example):
        raise TypeError(f"example must be an Example or a function that builds the operator, "
                        f"got {type(example).__name__}")
    if isinstance(operator, str):
        registry.load_entry_points()
        if operator not in registry.OPERATORS:
            raise ValueError(f"operator: no operator is registered as {operator!r}; registered "
                             f"names: {sorted(registry.OPERATORS)}")
        given, label, factory = example or example_of(operator), f"operator {operator!r}", \
            registry.OPERATORS[operator]
    elif isinstance(operator, HysteresisOperator):
        label, factory = f"operator {type(operator).__name__}", type(operator)
        given = example or (lambda: copy.deepcopy(operator))
    elif callable(operator):
        label, factory = f"operator {getattr(operator, '__name__', repr(operator))}", operator
        given = example or operator
    else:
        raise TypeError(f"operator must be a registered name, an operator class or an operator, "
                        f"got {type(operator).__name__}")
    example = given if isinstance(given, Example) else Example(given)
    return conformance.Case(label, example, dtype, factory)
