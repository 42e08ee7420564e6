"""What the model families' spec builders share (:mod:`torchhys.identification.specs`): the
option checks, the penalty grid of ``"auto"`` and its hold-out, the memory check of a
family's columns. What a family's search of its options returns is
:class:`torchhys.registry.Searched`."""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import check_choice, check_int, check_nonnegative, check_positive
from torchhys._memory import check_memory
from torchhys.identification.errors import FitError

PENALTIES = (0.0, 1e-8, 1e-6, 1e-4, 1e-2, 1e-1)
"""The grid of ``ridge``/``smoothness: "auto"``."""
VALIDATION = 0.25
"""The hold-out share of ``"auto"`` penalties: the last quarter of each row's scored
samples."""

Fitter = Callable[[Tensor, Tensor, int, Tensor | None], nn.Module]
"""Builds the fitted operator from the training input and target, (batch, time) each, the
number of leading warm-up samples to leave out of the fit, and the mask of the samples to use
((batch, time) bool, False: a held-out block or a shorter row's padding, the states running
through them; None: all)."""


def _keys(spec: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = sorted(set(spec) - allowed - {"fit"})
    if unknown:
        raise ValueError(
            f"fit {spec['fit']!r}: unknown option(s) {unknown}; valid: {sorted(allowed)}"
        )


def _penalty(spec: Mapping[str, Any], key: str) -> float | str:
    value = spec.get(key, "auto")
    if value == "auto":
        return value
    return check_nonnegative(value, f"fit {spec['fit']!r}: {key}",
                             alternatives="'auto' or ")


FIT_BYTES = 8 * 12
"""Bytes a fit takes per column (a play or stop of the grid, a unit of ``gpi``) and fitted
sample: float64 columns times 12, measured on real fits (pi_nonneg, gpi and stop_pi, 2000
columns of 2000 samples: 9 to 11.5 times the float64 columns at their peak)."""
PLACEHOLDER_BYTES = 16
"""Bytes of the placeholder operator per column (its widths built as int64, then float32
widths and weights), before any data are seen."""


def _check_columns(spec: Mapping[str, Any], columns: int, what: str,
                   samples: int | None = None) -> None:
    """Refuse a spec whose ``columns`` (``what``: the option) would take more than the memory
    limit: its placeholder (``samples`` None: when the spec is read) or its fit on
    ``samples`` samples (:data:`FIT_BYTES`), before allocating."""
    nbytes = columns * (PLACEHOLDER_BYTES if samples is None else FIT_BYTES * samples)
    on = "" if samples is None else f" fitted on {samples} samples"
    check_memory(nbytes, f"fit {spec['fit']!r}: {what} ({columns} columns){on}",
                 "lower " + " or ".join(re.findall(r"(\w+)=", what)))


def _grid(spec: Mapping[str, Any], n_default: int) -> tuple[int, float, str]:
    n = check_int(spec.get("n_widths", n_default), f"fit {spec['fit']!r}: n_widths",
                  minimum=1)
    if spec["fit"] == "pi_nonneg":
        _check_columns(spec, n, f"n_widths={n}")
    power = check_positive(spec.get("power", 2.0), f"fit {spec['fit']!r}: power")
    direction = check_choice(spec.get("direction", "direct"),
                             f"fit {spec['fit']!r}: direction", ["direct", "inverse"])
    return n, power, direction


def _holdout(scored: Tensor) -> float:
    """:data:`VALIDATION`, the share of each row's scored samples (the mask given to
    ``select_pi_ridge`` / ``select_penalty``) held out to choose a penalty.

    Raises:
        FitError: fewer than 8 scored samples (no hold-out to choose a penalty on).
    """
    n = int(scored.sum())
    if n < 8:
        raise FitError(f"{n} scored training samples are too few to choose a penalty "
                       "on a hold-out; give the penalty as a number")
    return VALIDATION


def holdout_rmse(predict: Callable[[Tensor], Tensor], x: Tensor, y: Tensor, cut: int) -> float:
    """RMS error of ``predict(x)`` against ``y`` on samples ``cut:`` of every row."""
    with torch.no_grad():
        return float((predict(x)[:, cut:] - y[:, cut:]).square().mean().sqrt())


def holdout_share(x: Tensor, cut: int) -> float:
    """The hold-out ``cut:`` of rows of ``x`` as the share ``select_pi_ridge``,
    ``select_penalty`` and ``select_stop_pi_ridge`` take (``validation``)."""
    return (x.shape[1] - cut) / x.shape[1]
