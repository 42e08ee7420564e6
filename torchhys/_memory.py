"""The memory limit of allocations that user input can make large: a Preisach fit's n, a
data module's ``repeat``. Each estimates its bytes before allocating and
:func:`check_memory` refuses an estimate over :func:`memory_limit` with one line naming the
option, the estimate and the limit.

The limit is the environment variable ``TORCHHYS_MAX_MEMORY`` (bytes, or a number with a
suffix ``K``, ``M``, ``G`` or ``T``, powers of 1024: ``8G``), else the machine's physical
memory (where the platform says it; no limit where it does not).
"""

from __future__ import annotations

import os
import re

MEMORY_ENV = "TORCHHYS_MAX_MEMORY"
"""The environment variable of the memory limit."""

_UNITS = {"": 1, "K": 1024, "M": 1024**2, "G": 1024**3, "T": 1024**4}


def _physical_memory() -> int | None:
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (AttributeError, OSError, ValueError):
        return None


def memory_limit() -> int | None:
    """The limit in bytes: ``TORCHHYS_MAX_MEMORY``, else the physical memory (None: none).

    Raises:
        ValueError: ``TORCHHYS_MAX_MEMORY`` is not a size (naming the variable).
    """
    text = os.environ.get(MEMORY_ENV, "").strip()
    if not text:
        return _physical_memory()
    match = re.fullmatch(r"(\d+(?:\.\d*)?(?:[eE]\+?\d+)?)\s*([KMGT]?)(?:i?B)?", text,
                         re.IGNORECASE)
    value = float(match[1]) * _UNITS[match[2].upper()] if match else 0.0
    if not value >= 1:
        raise ValueError(f"{MEMORY_ENV} must be a size in bytes, optionally with a suffix K, "
                         f"M, G or T (e.g. 8G), got {text!r}")
    return int(value)


def format_bytes(n: float) -> str:
    """``n`` bytes as ``"7.3 GiB"``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if n < 1024 or unit == "TiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    raise AssertionError("unreachable")


def check_memory(nbytes: float, what: str, fix: str) -> None:
    """Refuse an allocation estimated at ``nbytes`` over :func:`memory_limit`.

    Args:
        nbytes: the estimate.
        what: the option and what grows, e.g. ``"fit 'preisach': n=250 (31375 relays)"``.
        fix: what to change, e.g. ``"lower n"``.

    Raises:
        ValueError: ``"<what> needs about <estimate>, more than the memory limit <limit>
            (<source>); <fix>, or raise TORCHHYS_MAX_MEMORY"``.
    """
    limit = memory_limit()
    if limit is None or nbytes <= limit:
        return
    source = MEMORY_ENV if os.environ.get(MEMORY_ENV, "").strip() else "the physical memory"
    raise ValueError(f"{what} needs about {format_bytes(nbytes)}, more than the memory limit "
                     f"{format_bytes(limit)} ({source}); {fix}, or raise the limit: "
                     f"{MEMORY_ENV}=<bytes, e.g. 64G>")


SAMPLE_BYTES = 512
"""Bytes a training sample takes, about: the stage batches and a small network's forward and
backward pass (measured: about 580 with one operator and 8 hidden units; larger networks
take more), for the estimate of ``data.repeat``, which multiplies the samples."""


def check_repeat(repeat: int, samples: int) -> None:
    """Refuse ``data.repeat`` whose ``repeat * samples`` training samples would take more
    than the memory limit (:data:`SAMPLE_BYTES` each), before the sequences are built."""
    if repeat > 1:
        check_memory(SAMPLE_BYTES * repeat * samples,
                     f"data.repeat={repeat} ({repeat} x {samples} samples)", "lower data.repeat")
