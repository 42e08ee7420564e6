"""Export a compensator's step, or an operator's forward step, as a CasADi ``Function``: the
symbolic, differentiable step that model-predictive control (``casadi.Opti``, ``nlpsol``)
optimizes through, generated from the same exported graph as the C99 step.

* :func:`to_casadi` (:func:`function_and_state` with the fresh state and the layout): the
  compensator of a model, ``(x, state) -> (u, new_state)``, ``(x, conditions, state) ->
  (u, new_state)`` for a model with operating conditions (``docs/conditions.md``).
* :func:`to_casadi_forward` (:func:`forward_function_and_state`): the forward model,
  command -> response, of a hysteresis operator (a :class:`~torchhys.PrandtlIshlinskii`,
  :class:`~torchhys.Backlash`, :class:`~torchhys.Preisach`, ... with known or fitted
  parameters): ``(u, state) -> (y, new_state)``, what an MPC predicts the plant with.
* :func:`save_casadi` / :func:`load_casadi`: a ``NAME.casadi`` file (CasADi's serialized
  function, ``casadi.Function.load`` reads it without torchhys).

How: the compensator is built as :func:`torchhys.deploy.c.to_c` builds it (its ``_build``),
its explicit step exported with ``torch.export`` at batch 1 as the C generator exports it
(:class:`~torchhys.deploy.export._ExplicitStep`), and the graph translated node by node, one
CasADi translation per aten operation (:mod:`torchhys.deploy.casadi`), parameters and
buffers folded to constants. The function is built of ``SX`` scalars: ``casadi.jacobian``,
``Function.jacobian`` and ``Function.generate`` (C code) work on it as on any CasADi
function. An operation without a translation raises ValueError naming it and the module it
came from.

Every number is a float64 (CasADi's only type): the int64 counters and the bool flag of the
state are whole numbers, resp. 0 and 1, in the flat state vector. Needs the ``casadi`` extra
(``pip install "torchhys[casadi]"``).
"""

from __future__ import annotations

import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from torchhys.deploy.adaptive import AdaptiveCompensator
from torchhys.deploy.c._to_c import _build
from torchhys.deploy.casadi._values import Sym, casadi, objects
from torchhys.deploy.casadi._walk import translate
from torchhys.deploy.export import _check_path, _ExplicitStep, write_outputs
from torchhys.step import OperatorStep, check_step

__all__ = ["CasadiStep", "StateSlice", "forward_function_and_state", "function_and_state",
           "load_casadi", "save_casadi", "to_casadi", "to_casadi_forward"]

#: the compensator's state tensors by index (:mod:`torchhys.deploy.streaming`)
_NAMES = ("F", "I", "started", "F64")


@dataclass(frozen=True)
class StateSlice:
    """One state tensor in the flat state vector: ``vector[offset:offset + size]`` is the
    tensor of ``shape`` (batch 1, row-major) and torch ``dtype``."""

    name: str
    offset: int
    shape: tuple[int, ...]
    dtype: torch.dtype

    @property
    def size(self) -> int:
        return math.prod(self.shape)


@dataclass(frozen=True)
class CasadiStep:
    """A CasADi step and its state: ``function`` (a ``casadi.Function``),
    ``initial_state`` (the flat fresh state, float64), ``layout`` (one
    :class:`StateSlice` per state tensor) and ``n_conditions`` (the length of the
    ``conditions`` input, 0: none)."""

    function: Any
    initial_state: np.ndarray
    layout: tuple[StateSlice, ...]
    n_conditions: int = 0

    def unflatten(self, vector: Any) -> list[Tensor]:
        """The state tensors of a flat state vector (a numpy array or a CasADi DM), in
        their torch dtypes and shapes."""
        v = np.asarray(vector, dtype=np.float64).reshape(-1)
        return [torch.from_numpy(v[s.offset:s.offset + s.size].copy()).reshape(s.shape)
                .to(s.dtype) for s in self.layout]


def flatten(state: list[Tensor]) -> np.ndarray:
    """State tensors as one float64 vector (the layout of :class:`CasadiStep`)."""
    if not state:
        return np.zeros(0)
    return np.concatenate([t.detach().to(torch.float64).reshape(-1).numpy() for t in state])


def _layout(state: list[Tensor], names: list[str]) -> tuple[StateSlice, ...]:
    out, at = [], 0
    for name, t in zip(names, state, strict=True):
        out.append(StateSlice(name, at, tuple(t.shape), t.dtype))
        at += t.numel()
    return tuple(out)


def _symbols(vector: Any, tensors: list[Tensor]) -> list[Sym]:
    """The tensors' symbolic stand-ins, slices of the SX column ``vector``."""
    out, at = [], 0
    for t in tensors:
        n = t.numel()
        out.append(Sym(objects([vector[at + i] for i in range(n)], tuple(t.shape)), t.dtype))
        at += n
    return out


def _column(values: list[Any]) -> Any:
    """The outputs' elements (row-major, one after the other) as one SX column."""
    ca = casadi()
    elements = []
    for v in values:
        if isinstance(v, Sym):
            elements += list(v.a.flat)
        else:  # a known tensor (an output that does not depend on the inputs)
            elements += [ca.SX(float(e)) for e in torch.as_tensor(v).reshape(-1).tolist()]
    return ca.vertcat(*elements) if elements else ca.SX(0, 1)


def _check_name(name: object) -> str:
    if not (isinstance(name, str) and name.isidentifier() and name.isascii()):
        raise ValueError(f"name must be an identifier (letters, digits, '_'), got {name!r}")
    return name


def _export(module: nn.Module, args: tuple[Tensor, ...]) -> torch.export.ExportedProgram:
    with torch.no_grad():
        return torch.export.export(module, args, strict=False)


def function_and_state(
    model: nn.Module, *, dtype: torch.dtype = torch.float64,
    limits: tuple[float, float] | None = None, initial_command: float = 0.0,
    input_range: tuple[float, float] | None = None, input_margin: float | None = 0.05,
    direction: str = "auto", name: str = "torchhys_comp",
) -> CasadiStep:
    """The compensator's step as a CasADi function, with its fresh state and layout.

    The function (``name``) maps ``x`` (1x1: the desired output in physical units) and
    ``state`` (n x 1) to ``u`` (1x1: the saturated command) and ``new_state`` (n x 1); a
    model with operating conditions takes ``conditions`` (n_conditions x 1) between them.
    ``state`` is the compensator's state tensors (:mod:`torchhys.deploy.streaming`: ``F``,
    ``I``, ``started`` and, with float64 blocks, ``F64``, each at batch 1) flattened
    row-major one after the other: ``layout`` says where each lies; the fresh state is
    ``initial_state`` (all zeros). It is the TorchScript file's step
    (:func:`~torchhys.deploy.export.to_torchscript`): saturation, a NaN or inf sample held
    and counted, the input clamp and the direction guard.

    Args:
        model: as :func:`torchhys.deploy.c.to_c` (a network, an inverse model, a
            composition, or a built static
            :class:`~torchhys.deploy.streaming.StreamingCompensator`).
        dtype: ``torch.float64`` (default) or ``torch.float32``: the parameters' dtype
            (float32: rounded to float32); CasADi computes in float64 either way.
        limits, initial_command, input_range, input_margin, direction: as
            :func:`torchhys.deploy.export.to_torchscript`.
        name: the function's name (an identifier; the C symbol of ``Function.generate``).

    Raises:
        ImportError: casadi is not installed (the message names the extra).
        ValueError: an operation of the step without a CasADi translation (named, with
            the module and line it came from); an adaptive compensator; see
            :func:`torchhys.deploy.c.to_c` for the other options.
    """
    ca = casadi()
    name = _check_name(name)
    if isinstance(model, AdaptiveCompensator):
        raise ValueError("model: an AdaptiveCompensator has no CasADi export (its update "
                         "is not a step of the command); pass the model")
    comp = _build(model, dtype, limits, initial_command,
                  {"input_range": input_range, "input_margin": input_margin,
                   "direction": direction})
    state = comp.initial_state(1)
    inputs = comp.example_inputs(1)
    ep = _export(_ExplicitStep(comp), (torch.zeros(1, dtype=dtype),
                                        *(t for _, t in inputs), *state))
    n_state = sum(t.numel() for t in state)
    x = ca.SX.sym("x")
    s = ca.SX.sym("state", n_state)
    between = [ca.SX.sym(n, t.numel()) for n, t in inputs]
    syms = [Sym(objects([x], (1,)), dtype),
            *[_symbols(b, [t])[0] for b, (_, t) in zip(between, inputs, strict=True)],
            *_symbols(s, state)]
    outs = translate(ep, syms)
    fn = ca.Function(name, [x, *between, s], [_column(outs[:1]), _column(outs[1:])],
                     ["x", *(n for n, _ in inputs), "state"], ["u", "new_state"])
    return CasadiStep(fn, flatten(state), _layout(state, list(_NAMES[:len(state)])),
                      comp.n_conditions)


def to_casadi(
    model: nn.Module, *, dtype: torch.dtype = torch.float64,
    limits: tuple[float, float] | None = None, initial_command: float = 0.0,
    input_range: tuple[float, float] | None = None, input_margin: float | None = 0.05,
    direction: str = "auto", name: str = "torchhys_comp",
) -> Any:
    """The compensator's step as a ``casadi.Function`` ``(x, state) -> (u, new_state)``
    (``(x, conditions, state)`` with operating conditions); the options, the errors and
    the state's layout: :func:`function_and_state` (whose ``initial_state`` is the fresh
    state: all zeros, of length ``fn.size1_in("state")``)."""
    return function_and_state(model, dtype=dtype, limits=limits,
                              initial_command=initial_command, input_range=input_range,
                              input_margin=input_margin, direction=direction,
                              name=name).function


class _Forward(nn.Module):
    """An operator step as a graph of tensors: ``(u (1, 1), *state) -> (features, *new)``."""

    def __init__(self, step: OperatorStep) -> None:
        super().__init__()
        self.step = step

    def forward(self, u: Tensor, *state: Tensor) -> tuple[Tensor, ...]:
        y, new = self.step(u, list(state))
        return (y, *new)


def _operator_step(operator: nn.Module, dtype: torch.dtype) -> OperatorStep:
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    if isinstance(operator, OperatorStep):
        return check_step(operator, "operator").to(dtype).eval()
    make = getattr(operator, "streaming_step", None)
    if not callable(make):
        raise TypeError("operator must be a hysteresis operator (with streaming_step) or a "
                        f"torchhys.step.OperatorStep, got {type(operator).__name__}")
    return check_step(make(dtype), "operator.streaming_step(dtype)").eval()


def forward_function_and_state(
    operator: nn.Module, *, u0: float = 0.0, dtype: torch.dtype = torch.float64,
    name: str = "torchhys_forward",
) -> CasadiStep:
    """The forward model of a hysteresis operator as a CasADi function, with its state.

    The function (``name``) maps ``u`` (1x1: the command, the operator's input) and
    ``state`` (n x 1: the operator step's blocks, :attr:`~torchhys.step.OperatorStep.
    state_spec`, flattened in order) to ``y`` (n_outputs x 1: the operator's output, the
    response of a plant it models) and ``new_state``. ``initial_state`` is the state at a
    first command ``u0`` (each block at ``start + from_sample * u0``; a play starts at 0),
    ``layout`` names the blocks. It is the operator's own step
    (:meth:`~torchhys.operator.HysteresisOperator.streaming_step`): no saturation or NaN
    guard (the optimizer's commands are its decision variables).

    Args:
        operator: a causal hysteresis operator (its current parameters: a known model, or
            one fitted to the plant, e.g. :func:`~torchhys.identification.fitting.
            fit_prandtl_ishlinskii`), or an :class:`~torchhys.step.OperatorStep`.
        u0: the first command (sets the blocks that start from the sample).
        dtype: the step's dtype (CasADi computes in float64 either way).
        name: the function's name (an identifier).

    Raises:
        ImportError: casadi is not installed. TypeError: not an operator. ValueError: an
            operation without a translation, a bad ``dtype`` or ``name``.
    """
    ca = casadi()
    name = _check_name(name)
    step = _operator_step(operator, dtype)
    n_in = getattr(step, "n_inputs", 1)
    if n_in != 1:
        raise ValueError(f"operator: its step takes {n_in} inputs; the forward model takes one "
                         "command")
    first = step.initial_state(torch.full((1, 1), float(u0), dtype=dtype))
    ep = _export(_Forward(step), (torch.zeros(1, 1, dtype=dtype), *first))
    n_state = sum(t.numel() for t in first)
    u, s = ca.SX.sym("u"), ca.SX.sym("state", n_state)
    outs = translate(ep, [Sym(objects([u], (1, 1)), dtype), *_symbols(s, first)],
                     who="to_casadi_forward")
    fn = ca.Function(name, [u, s], [_column(outs[:1]), _column(outs[1:])],
                     ["u", "state"], ["y", "new_state"])
    names = [b.name for b in step.state_spec]
    return CasadiStep(fn, flatten(first), _layout(first, names))


def to_casadi_forward(operator: nn.Module, *, dtype: torch.dtype = torch.float64,
                      name: str = "torchhys_forward") -> Any:
    """The operator's forward model as a ``casadi.Function`` ``(u, state) -> (y,
    new_state)``; the options, the errors and the state (its start at a first command
    ``u0``): :func:`forward_function_and_state`."""
    return forward_function_and_state(operator, dtype=dtype, name=name).function


def save_casadi(fn: Any, path: str | os.PathLike) -> str:
    """Write the ``casadi.Function`` ``fn`` to ``path`` (conventionally ``NAME.casadi``:
    CasADi's serialized function, what ``Function.save`` writes; ``casadi.Function.load``
    reads it), atomically: an old file there is replaced whole or left as it was."""
    ca = casadi()
    if not isinstance(fn, ca.Function):
        raise TypeError(f"fn must be a casadi.Function, got {type(fn).__name__}")
    path = _check_path(path)
    with tempfile.TemporaryDirectory() as folder:  # Function.save's bytes, then one write
        scratch = os.path.join(folder, "function.casadi")
        fn.save(scratch)
        data = Path(scratch).read_bytes()
    write_outputs([(path, data)])
    return path


def load_casadi(path: str | os.PathLike) -> Any:
    """The ``casadi.Function`` of a file from :func:`save_casadi` (``Function.load``)."""
    return casadi().Function.load(os.fspath(path))
