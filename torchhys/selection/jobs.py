"""Model selection's candidates run one after another or in parallel processes, within a
time budget: ``model.select_jobs`` and ``model.select_budget_s``.

``select_jobs: n`` scores up to n candidates at a time, each in a process of its own (forked
from the command's process, so it has the command's configuration and data as they are),
with torch's threads divided among them (the command's thread count over n, at least one
each); the scores come back in the candidates' order. ``select_jobs: auto`` takes the usable
cores, at most :data:`AUTO_JOBS` (one process where processes cannot be forked).
``select_budget_s: s`` starts no candidate once s seconds have passed since the first
started (the first always runs; the ones running then finish): the others score NaN, and
their ``error`` in ``selection.csv`` and the printed table says that they were skipped. The
chosen candidate is the best of those scored. The processes die with the command's process
however it ends (SIGKILL included) and ignore SIGINT; when the selection stops early (a
signal, Ctrl-C, a candidate's error) the running ones are killed, not waited for
(:func:`die_with_parent`, :func:`_stop`).

Every wait on a process is bounded: a candidate that has not finished
:func:`wait_timeout` seconds after its process started it (``TORCHHYS_TIMEOUT_S``, default
:data:`DEFAULT_TIMEOUT_S`; a group sharing a process, that many per candidate) is a
one-line :class:`SelectionTimeoutError` naming it, and the processes are killed; once all
are scored, the idle processes get :data:`_EXIT_S` seconds to exit before they are killed.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import multiprocessing
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from concurrent.futures.process import BrokenProcessPool
from typing import Any

import torch

__all__ = ["AUTO_JOBS", "DEFAULT_TIMEOUT_S", "TIMEOUT_ENV", "SelectionJobError",
           "SelectionTimeoutError", "check_budget", "check_jobs", "die_with_parent",
           "run_candidates", "usable_cores", "wait_timeout"]

_SCORE: Callable[[int], Any] | None = None
"""The scoring function of the running selection, inherited by the forked processes."""
_SKIPPED: Callable[[int], Any] | None = None
"""Its score of a candidate skipped for the budget, inherited likewise."""


AUTO_JOBS = 4
"""The most processes of ``select_jobs: auto`` (each holds its own copy of the data and the
fits: about 0.8 GiB at 1e5 samples, 4 GiB at 1e6)."""


TIMEOUT_ENV = "TORCHHYS_TIMEOUT_S"
"""The environment variable of the longest wait for a candidate's process, in seconds
(``none``: no limit)."""
DEFAULT_TIMEOUT_S = 6 * 3600.0
"""Its default: six hours per candidate, far beyond a fit of this library's networks (a
process that takes longer has most likely stopped: a deadlock after the fork)."""
_EXIT_S = 30.0
"""Seconds the idle processes get to exit after the last score before they are killed."""


def wait_timeout() -> float | None:
    """The longest wait for a candidate's process, in seconds: ``TORCHHYS_TIMEOUT_S``
    (a finite number > 0, or ``none``: no limit), :data:`DEFAULT_TIMEOUT_S` where unset.

    Raises:
        ValueError: the variable holds anything else (naming it and the value).
    """
    text = os.environ.get(TIMEOUT_ENV, "").strip()
    if not text:
        return DEFAULT_TIMEOUT_S
    if text.lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{TIMEOUT_ENV} must be a finite number of seconds > 0 (or 'none': "
                         f"no limit), got {text!r}")
    return value


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the platform says it)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def _can_fork() -> bool:
    return "fork" in multiprocessing.get_all_start_methods()


class SelectionJobError(ValueError):
    """A process of ``select_jobs`` ended without a result (killed, e.g. out of memory): a
    one-line error that says to run fewer at a time."""


class SelectionTimeoutError(SelectionJobError):
    """A candidate's process did not finish within :func:`wait_timeout`: a one-line error
    naming the candidate and the limit."""


def check_jobs(value: object) -> int:
    """``model.select_jobs`` (None: 1), checked: a whole number >= 1, or ``"auto"``: the
    usable cores, at most :data:`AUTO_JOBS` (1 where processes cannot be forked)."""
    if value is None:
        return 1
    if value == "auto":
        return min(usable_cores(), AUTO_JOBS) if _can_fork() else 1
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"model.select_jobs must be a whole number >= 1 (candidates scored "
                         f"at a time, each in a process) or 'auto', got {value!r}")
    return value


def check_budget(value: object) -> float | None:
    """``model.select_budget_s`` (None: no budget), checked: a finite number of seconds > 0."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            math.isfinite(value) and value > 0):
        raise ValueError(f"model.select_budget_s must be a finite number of seconds > 0 (or "
                         f"null: no budget), got {value!r}")
    return float(value)


def _score_group(indices: list[int], start: float, budget_s: float | None) -> list:
    """The scores of a group of candidates, in order, in one process (the fits they share
    are done once there: :mod:`torchhys.identification._fit_cache`)."""
    assert _SCORE is not None and _SKIPPED is not None
    return [_SKIPPED(i) if _spent(i, start, budget_s) else _SCORE(i) for i in indices]


def _spent(i: int, start: float, budget_s: float | None) -> bool:
    return i > 0 and budget_s is not None and time.perf_counter() - start >= budget_s


def _groups(n: int, together: Sequence[object] | None) -> list[list[int]]:
    """The candidates ``0..n-1`` cut into runs of consecutive ones with the same
    ``together`` key (None: a run of its own)."""
    groups: list[list[int]] = []
    for i in range(n):
        key = None if together is None else together[i]
        if groups and key is not None and together[groups[-1][-1]] == key:  # type: ignore[index]
            groups[-1].append(i)
        else:
            groups.append([i])
    return groups


def run_candidates(n: int, score: Callable[[int], Any], skipped: Callable[[int], Any], *,
                   report: Callable[[Any], None] | None = None, jobs: int = 1,
                   budget_s: float | None = None,
                   together: Sequence[object] | None = None,
                   describe: Callable[[int], str] | None = None,
                   timeout_s: float | None = None) -> list:
    """``score(i)`` of the candidates ``i < n``, ``skipped(i)`` for those not started within
    ``budget_s``; ``jobs`` at a time (forked processes, threads divided); ``report`` called
    with each in order as soon as it and those before it are known. Consecutive candidates
    with the same ``together`` key (not None) run one after another in one process, where
    they share their fits.

    A process's candidates are waited for ``timeout_s`` seconds each (None:
    :func:`wait_timeout`) from its start; ``describe(i)`` names candidate ``i`` in the
    error then (after its index).

    Raises:
        SelectionJobError: a process ended without a result.
        SelectionTimeoutError: a process did not finish in time (the processes are killed).
    """
    global _SCORE, _SKIPPED
    jobs, budget_s = check_jobs(jobs), check_budget(budget_s)
    start = time.perf_counter()
    results: list = []

    def done(result: Any) -> None:
        results.append(result)
        if report is not None:
            report(result)

    if jobs == 1 or n == 1:
        for i in range(n):
            done(skipped(i) if _spent(i, start, budget_s) else score(i))
        return results
    try:
        context = multiprocessing.get_context("fork")
    except ValueError:
        raise ValueError("model.select_jobs > 1 needs processes started by fork (Linux, "
                         "macOS); set model.select_jobs: 1 here") from None
    limit = wait_timeout() if timeout_s is None else timeout_s
    threads = max(1, torch.get_num_threads() // jobs)
    _SCORE, _SKIPPED = score, skipped
    before = set(multiprocessing.active_children())
    pool = ProcessPoolExecutor(jobs, mp_context=context, initializer=_start_worker,
                               initargs=(threads, os.getpid()))
    try:
        pending: list = []  # (group, future or None: skipped, its deadline), in order

        def collect() -> None:
            group, r, deadline = pending.pop(0)
            which = (f"candidate {group[0]}" if len(group) == 1
                     else f"candidates {group[0]}-{group[-1]}")
            try:
                scores = [skipped(j) for j in group] if r is None else r.result(
                    None if deadline is None else max(0.0, deadline - time.perf_counter()))
            except BrokenProcessPool:
                raise SelectionJobError(
                    f"model.select_jobs: the process scoring {which} ended without a "
                    f"result (killed: out of memory?); run fewer at a time "
                    f"(--model.select_jobs=1: all in the command's process)") from None
            except FutureTimeout:
                raise SelectionTimeoutError(_late(which, group, limit, describe)) from None
            for result in scores:
                done(result)

        for group in _groups(n, together):
            while sum(r is not None for _, r, _ in pending) >= jobs:
                collect()
            if _spent(group[0], start, budget_s):
                pending.append((group, None, None))
            else:  # a process is free: the group starts now
                pending.append((group, pool.submit(_score_group, group, start, budget_s),
                                None if limit is None
                                else time.perf_counter() + limit * len(group)))
        while pending:
            collect()
    except BaseException:  # a signal, Ctrl-C, a candidate's error: nothing waits for the rest
        _stop(pool, before)
        raise
    else:
        _finish(pool, before)
    finally:
        _SCORE = _SKIPPED = None
    return results


def _late(which: str, group: list[int], limit: float, describe: Callable[[int], str] | None
          ) -> str:
    """The message of a group not finished within ``limit`` seconds a candidate."""
    named = "" if describe is None else " (" + "; ".join(describe(i) for i in group) + ")"
    each = "" if len(group) == 1 else f" ({limit:g} s each, in one process)"
    return (f"model selection: {which}{named} did not finish within "
            f"{limit * len(group):g} s{each} in its process (model.select_jobs), which was "
            f"stopped; allow more with {TIMEOUT_ENV}=SECONDS (or 'none'), or run "
            f"--model.select_jobs=1 to see where it stops")


def _start_worker(threads: int, parent: int) -> None:
    """A worker's start: its share of torch's threads; it dies with the command's process
    and ignores SIGINT (:func:`die_with_parent`)."""
    die_with_parent(parent)
    torch.set_num_threads(threads)


def _finish(pool: ProcessPoolExecutor, before: set) -> None:
    """End the pool once every score is in: the idle processes get :data:`_EXIT_S` seconds
    to exit, then are killed (the pool's own shutdown would wait for them without limit)."""
    pool.shutdown(wait=False)
    _end_children(before, grace=_EXIT_S)


def _stop(pool: ProcessPoolExecutor, before: set) -> None:
    """End the pool now: queued candidates cancelled, the running ones' processes killed."""
    pool.shutdown(wait=False, cancel_futures=True)
    _end_children(before, grace=0.0)


def _end_children(before: set, grace: float) -> None:
    """End every child process not in ``before``: ``grace`` seconds to exit, then killed,
    asked again until none is left (the pool's processes are not all listed at any one
    moment: one missing from a single look was left running)."""
    def children() -> list:
        return [p for p in multiprocessing.active_children() if p not in before]

    deadline = time.perf_counter() + grace
    for process in children():
        process.join(timeout=max(0.0, deadline - time.perf_counter()))
    deadline = time.perf_counter() + 5.0
    while time.perf_counter() < deadline:
        alive = children()
        if not alive:
            break
        for process in alive:
            process.kill()
        for process in alive:
            process.join(timeout=0.5)


_PR_SET_PDEATHSIG = 1
"""Linux's ``prctl`` option: the signal a process gets when its parent ends."""


_POLL_S = 0.5
"""How often a worker without ``prctl`` looks whether its parent still runs."""


def die_with_parent(parent: int) -> None:
    """In a worker process started by the process ``parent``: end (SIGKILL) as soon as the
    parent ends, however it ends (Linux: ``prctl(PR_SET_PDEATHSIG)``; elsewhere a thread
    that looks every :data:`_POLL_S` s whether the parent changed), ignore SIGINT and take
    SIGTERM as the default does (not a handler inherited from the parent)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    armed = False
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
    if os.getppid() != parent:  # the parent ended before the above took effect
        os._exit(1)
    if not armed:
        def watch() -> None:
            while os.getppid() == parent:
                threading.Event().wait(_POLL_S)
            os._exit(1)

        threading.Thread(target=watch, name="torchhys-parent-watch", daemon=True).start()
