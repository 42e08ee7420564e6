"""The number of torch threads of a ``torchhys`` command.

A fit is dominated by small tensor operations in loops (operator scans, line searches, one
full batch per step): with several intra-op threads per process the threads spin and wait
for each other, and several fits on the same cores thrash. The command therefore runs
torch with one thread unless told otherwise: ``--threads N`` on the command line, or the
environment variable ``TORCHHYS_THREADS`` (``--threads`` wins). It says what it chose on
stderr.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Sequence

__all__ = ["DEFAULT_THREADS", "THREADS_ENV", "THREADS_FLAG", "choose_threads",
           "split_threads_flag"]

THREADS_FLAG = "--threads"
THREADS_ENV = "TORCHHYS_THREADS"
DEFAULT_THREADS = 1
"""Torch threads of a command when neither ``--threads`` nor ``TORCHHYS_THREADS`` is given:
one, for latency-bound work (see the module docstring)."""


def _count(text: str, where: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise ValueError(f"{where} must be a whole number >= 1 (torch threads), got {text!r}")
    return n


def split_threads_flag(argv: Sequence[str]) -> tuple[list[str], int | None]:
    """``argv`` without ``--threads N`` / ``--threads=N``, and N (None when absent).

    Raises:
        ValueError: a missing or bad N.
    """
    args, threads, it = [], None, iter(argv)
    for a in it:
        if a == THREADS_FLAG:
            value = next(it, None)
            if value is None:
                raise ValueError("--threads needs a number, e.g. --threads 2")
            threads = _count(value, THREADS_FLAG)
        elif a.startswith(THREADS_FLAG + "="):
            threads = _count(a.split("=", 1)[1], THREADS_FLAG)
        else:
            args.append(a)
    return args, threads


def choose_threads(flag: int | None, prog: str, *, say: bool = True) -> int:
    """Set torch's intra-op threads: ``flag`` (``--threads``), else ``TORCHHYS_THREADS``,
    else :data:`DEFAULT_THREADS`; print the choice on stderr when ``say``; the number.

    Raises:
        ValueError: a bad ``TORCHHYS_THREADS``.
    """
    import torch

    if flag is not None:
        n, source = flag, THREADS_FLAG
    elif os.environ.get(THREADS_ENV, "").strip():
        n, source = _count(os.environ[THREADS_ENV].strip(), THREADS_ENV), THREADS_ENV
    else:
        n, source = DEFAULT_THREADS, "default for latency-bound fits"
    torch.set_num_threads(n)
    if say:
        print(f"{prog}: torch threads {n} ({source}; {THREADS_FLAG} N or {THREADS_ENV} to "
              f"change; {os.cpu_count()} cores)", file=sys.stderr, flush=True)
    return n
