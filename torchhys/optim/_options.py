"""Input checks for :class:`torchhys.optim.PowellBealeCG`."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def check_options(options: Mapping[str, Any], searches: Mapping[str, Any]) -> None:
    """Validate the constructor options of ``PowellBealeCG``.

    Args:
        options: the option dict (``alpha``, ``beta``, ... as passed to the constructor).
        searches: the registry of named line searches.

    Raises:
        ValueError: an option is out of range, naming the option and the value received.
        TypeError: an option has the wrong type, naming the option and the type received.
    """
    for name in ("alpha", "beta", "gamma", "delta", "scale_tol", "minstep", "tolerance_grad",
                 "orthogonality"):
        if not _is_real(options[name]):
            raise TypeError(f"{name} must be a real number; got {type(options[name]).__name__}")
    for name in ("iterations_per_step", "max_evals"):
        if not _is_int(options[name]):
            raise TypeError(f"{name} must be an int; got {type(options[name]).__name__}")
        if options[name] < 1:
            raise ValueError(f"{name} must be >= 1; got {options[name]}")
    alpha, beta, gamma = options["alpha"], options["beta"], options["gamma"]
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1); got {alpha}")
    if not alpha < beta < 1.0:
        raise ValueError(f"beta must satisfy alpha < beta < 1; got alpha={alpha}, beta={beta}")
    if not 0.0 < gamma < 0.5:
        raise ValueError(f"gamma must lie in (0, 0.5); got {gamma}")
    for name in ("delta", "scale_tol", "orthogonality"):
        if not options[name] > 0.0:
            raise ValueError(f"{name} must be positive; got {options[name]}")
    for name in ("minstep", "tolerance_grad"):
        if not options[name] >= 0.0:
            raise ValueError(f"{name} must be non-negative; got {options[name]}")
    if not isinstance(options["reuse_evaluation"], bool):
        raise TypeError(
            f"reuse_evaluation must be a bool; got {type(options['reuse_evaluation']).__name__}"
        )
    every = options["restart_every"]
    if every is not None and (not _is_int(every) or every < 1):
        raise ValueError(f"restart_every must be None or an int >= 1; got {every!r}")
    search = options["line_search"]
    if isinstance(search, str):
        if search not in searches:
            raise ValueError(
                f"line_search must be one of {sorted(searches)} or a callable; got {search!r}"
            )
    elif not callable(search):
        raise TypeError(
            f"line_search must be a string or a callable; got {type(search).__name__}"
        )
