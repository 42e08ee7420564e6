"""The lock that makes a stepper's stored state safe across threads: one step at a time.

:class:`StepLock` is a :class:`threading.Lock` that a copy or a pickle of its owner does not
share: ``copy.deepcopy`` of a compensator (or ``torch.save`` of the whole module) gives the
copy a lock of its own, unlocked.
"""

from __future__ import annotations

import threading


class StepLock:
    """A context manager holding a :class:`threading.Lock`; copies get a new one."""

    __slots__ = ("_lock",)

    def __init__(self) -> None:
        self._lock = threading.Lock()

    def __enter__(self) -> StepLock:
        self._lock.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self._lock.release()

    def __reduce__(self) -> tuple[type, tuple]:
        return (StepLock, ())
