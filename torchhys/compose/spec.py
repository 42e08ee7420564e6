"""A :class:`~torchhys.compose.Composed` rebuilt from its spec in a checkpoint:
:func:`build_composed`.

``torchhys fit`` given the model as ``model.net: {class_path: torchhys.compose.Composed,
init_args: {module: {class_path: mypkg.MyModel, init_args: {...}}}}`` saves that spec in the
checkpoint's ``hyper_parameters`` (``net``) and the weights and ranges in its ``state_dict``
(``net.*``). :func:`build_composed` builds the user's module from the spec, composes it and
loads the state, for ``torchhys export``. It imports nothing the checkpoint names: each
class must be an ``nn.Module`` of a module imported already (``--import mypkg``), so a
checkpoint cannot make the export import or call code of its choosing.
"""

from __future__ import annotations

import sys
from typing import Any

import torch
from torch import Tensor, nn

from torchhys.compose.composed import Composed

__all__ = ["COMPOSED", "build_composed", "is_composed_spec"]

COMPOSED = ("torchhys.compose.Composed", "torchhys.compose.composed.Composed")
"""The class paths of :class:`Composed` in a spec."""


def is_composed_spec(spec: object) -> bool:
    """Whether ``spec`` (a checkpoint's ``hyper_parameters["net"]``) is a Composed's spec."""
    return isinstance(spec, dict) and spec.get("class_path") in COMPOSED


def _arguments(spec: dict, where: str) -> dict[str, Any]:
    args = {**(spec.get("init_args") or {}), **(spec.get("dict_kwargs") or {})}
    if not all(isinstance(k, str) for k in args):
        raise ValueError(f"{where}: its init_args must be a mapping of names to values")
    return args


def _class(path: object, where: str) -> type[nn.Module]:
    if not isinstance(path, str) or "." not in path:
        raise ValueError(f"{where}: class_path must be 'module.Class', got {path!r}")
    module_name, _, name = path.rpartition(".")
    module = sys.modules.get(module_name)
    if module is None:
        top = module_name.split(".")[0]
        raise ValueError(f"{where} is {path}: give --import {module_name} (and --import-path "
                         f"for the folder of {top}); the export imports no module a "
                         "checkpoint names")
    cls = getattr(module, name, None)
    if not (isinstance(cls, type) and issubclass(cls, nn.Module)):
        raise ValueError(f"{where} is {path}: expected an nn.Module class of the imported "
                         f"module {module_name}, found {type(cls).__name__}")
    return cls


def _value(value: Any, where: str) -> Any:
    """A spec's value: a nested ``{class_path, init_args}`` is built, lists element-wise."""
    if isinstance(value, dict) and "class_path" in value:
        cls = _class(value["class_path"], where)
        args = {k: _value(v, f"{where}.{k}") for k, v in _arguments(value, where).items()}
        try:
            return cls(**args)
        except TypeError as err:
            raise ValueError(f"{where} ({value['class_path']}) cannot be built from its "
                             f"init_args {sorted(args)}: {err}") from None
    if isinstance(value, list):
        return [_value(v, f"{where}[{i}]") for i, v in enumerate(value)]
    return value


def build_composed(spec: dict, state: dict[str, Tensor], where: str = "net") -> Composed:
    """The :class:`Composed` of ``spec`` (``{"class_path": "torchhys.compose.Composed",
    "init_args": {"module": {"class_path": ..., "init_args": {...}}}}``) with the weights
    and ranges of ``state`` (the Composed's state dict: ``module.*``, ``in_min``, ...), in
    the state's dtype.

    Raises:
        ValueError: not a Composed's spec, a class of a module not imported (naming the
            ``--import`` to give), not an ``nn.Module`` class, init_args it does not take,
            weights that do not fit the module.
    """
    if not is_composed_spec(spec):
        got = spec.get("class_path") if isinstance(spec, dict) else type(spec).__name__
        raise ValueError(f"{where}: expected the spec of torchhys.compose.Composed, got {got!r}")
    args = _arguments(spec, where)
    if not isinstance(args.get("module"), dict):
        raise ValueError(f"{where}: its init_args need the user's module as "
                         "{class_path: ..., init_args: ...}")
    module = _value(args["module"], f"{where}.module")
    floats = {v.dtype for v in state.values() if isinstance(v, Tensor) and v.is_floating_point()}
    if len(floats) == 1:
        module = module.to(floats.pop())  # before loading: float64 weights are not rounded
    with torch.no_grad():
        composed = Composed(module)
        try:
            composed.load_state_dict(state)
        except RuntimeError as err:  # missing, unexpected or mis-shaped weights
            first = str(err).strip().splitlines()[0]
            raise ValueError(f"{where}: the weights do not fit the module "
                             f"{args['module'].get('class_path')}: {first}") from None
    composed.check()  # the trained weights, in the recorded range
    return composed
