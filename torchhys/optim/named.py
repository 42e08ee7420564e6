"""The optimizers a model names (``optimizer: lbfgs``), and the check of their keyword
arguments."""

from __future__ import annotations

import inspect
from collections.abc import Mapping
from typing import Any

import torch

from torchhys.optim.powell_beale import PowellBealeCG

__all__ = ["CLOSURE_OPTIMIZERS", "OPTIMIZERS", "RESET_OPTIMIZER_KWARGS", "check_optimizer_kwargs",
           "optimizer_arguments", "optimizer_keywords", "unknown_optimizer_kwargs"]


OPTIMIZERS: dict[str, type[torch.optim.Optimizer]] = {
    "adam": torch.optim.Adam,
    "cg": PowellBealeCG,
    "lbfgs": torch.optim.LBFGS,
}
"""Optimizers by name. ``cg`` is conjugate gradient with Powell-Beale restarts."""


CLOSURE_OPTIMIZERS = frozenset({"cg", "lbfgs"})
"""Optimizers that re-evaluate the loss in a line search: trained full-batch, manually."""


RESET_OPTIMIZER_KWARGS = "--model.optimizer_kwargs '{}'"
"""How the command line resets ``model.optimizer_kwargs`` (in messages)."""


def optimizer_keywords(optimizer: str) -> list[str]:
    """The keyword arguments the optimizer ``optimizer`` (a name of :data:`OPTIMIZERS`)
    takes besides its parameters."""
    signature = inspect.signature(OPTIMIZERS[optimizer].__init__)
    return [n for n, p in signature.parameters.items() if n not in ("self", "params")
            and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]


def unknown_optimizer_kwargs(optimizer: str, optimizer_kwargs: Any) -> list[str]:
    """The keys of ``optimizer_kwargs`` that the optimizer ``optimizer`` does not take,
    sorted."""
    known = optimizer_keywords(optimizer)
    return sorted(str(k) for k in (optimizer_kwargs or {}) if k not in known)


def check_optimizer_kwargs(optimizer: str, optimizer_kwargs: Any) -> None:
    """Raise ``ValueError`` for ``optimizer_kwargs`` that the optimizer ``optimizer`` does
    not take, naming them, the ones it takes and how the command line resets them (an
    unknown optimizer name is left to the module's own check)."""
    if optimizer not in OPTIMIZERS:
        return
    if optimizer_kwargs is not None and not isinstance(optimizer_kwargs, Mapping):
        raise ValueError(f"optimizer_kwargs must be a dict of keyword arguments of the "
                         f"optimizer, got {type(optimizer_kwargs).__name__}")
    unknown = unknown_optimizer_kwargs(optimizer, optimizer_kwargs)
    if unknown:
        raise ValueError(
            f"optimizer_kwargs {unknown} are not keyword arguments of optimizer={optimizer!r} "
            f"({OPTIMIZERS[optimizer].__name__} takes {optimizer_keywords(optimizer)}); kwargs "
            f"of another optimizer are reset with {RESET_OPTIMIZER_KWARGS}")


def optimizer_arguments(optimizer: str, lr: float,
                        optimizer_kwargs: Mapping[str, Any] | None) -> dict[str, Any]:
    """The keyword arguments a model's optimizer is built with: its ``optimizer_kwargs``,
    the model's ``lr`` unless they give one (not for ``cg``, whose line search sets the step),
    and L-BFGS's strong Wolfe line search unless they name another."""
    kwargs = dict(optimizer_kwargs or {})
    if optimizer != "cg":
        kwargs.setdefault("lr", lr)
    if optimizer == "lbfgs":
        kwargs.setdefault("line_search_fn", "strong_wolfe")
    return kwargs

