"""Old import paths that keep working: a module's ``__getattr__`` (PEP 562) that hands out a
name from its one home with a :class:`DeprecationWarning` naming that home."""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable
from typing import Any


def moved(module: str, names: dict[str, str]) -> Callable[[str], Any]:
    """The ``__getattr__`` of ``module`` for names that moved: ``names`` maps each old name
    to the module that is its home now; any other name is an ``AttributeError``."""

    def __getattr__(name: str) -> Any:
        home = names.get(name)
        if home is None:
            raise AttributeError(f"module {module!r} has no attribute {name!r}")
        warnings.warn(f"{module}.{name} is deprecated: use {home}.{name} "
                      f"(from {home} import {name})", DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module(home), name)

    return __getattr__
