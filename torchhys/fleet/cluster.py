"""Where a fleet's work runs: a Dask ``distributed`` client (:func:`connect`).

By default a :class:`distributed.LocalCluster` on this machine: one worker process per
usable core (at most ``workers``), one thread each; each fit sets torch to one thread, as
``torchhys fit`` does by default and as ``model.select_jobs`` divides them (the command's
threads over its processes, one each). ``cluster="tcp://HOST:8786"`` connects to a running
scheduler (``dask scheduler`` and ``dask worker ... --nthreads 1``), a path to its
scheduler file (``dask scheduler --scheduler-file FILE``) likewise. A scheduler that does
not answer within ``timeout`` seconds is a one-line :class:`ClusterError`.

The local cluster's workers run without Dask's statistical profiler
(``distributed.worker.profile.enabled``, :data:`WORKER_CONFIG`): it samples the running
task's stack every 10 ms and keeps a tree of it per second of work for the last 1000 s
(``distributed.admin.low-level-log-length``), and a fit's stacks (Lightning, jsonargparse,
torch) make that about 2 MiB a device fitted: a worker grew from about 515 MiB to 573 MiB
over 30 devices with it, and by 7 MiB (all over its first 10) without it. Workers started by hand
get the same with ``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False`` in their
environment.

A fit seeds and sets process-wide state (torch's random generator and threads, the
environment of the command), so two fits must not share a process: :func:`check_workers`
refuses workers of more than one thread, or several in one process (``processes=False``).
"""

from __future__ import annotations

import copy
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from torchhys.selection.jobs import usable_cores

__all__ = ["WORKER_CONFIG", "ClusterError", "check_workers", "connect", "install_hint"]

install_hint = 'pip install "torchhys[fleet]"'

WORKER_CONFIG = {"distributed.worker.profile.enabled": False}
"""Dask settings of the local cluster's workers (the module docstring: no profiler)."""


class ClusterError(ValueError):
    """A cluster that cannot be used, in one line (the address and why)."""


def _distributed() -> Any:
    try:
        import distributed
    except ModuleNotFoundError:
        raise ClusterError(f"a fleet runs on Dask distributed, which is not installed: "
                           f"{install_hint}") from None
    return distributed


@contextmanager
def connect(cluster: Any = None, *, workers: int | None = None, timeout: float = 10.0,
            retries: int = 2) -> Iterator[Any]:
    """A :class:`distributed.Client` for the fleet, closed (with a cluster it started) on
    exit.

    Args:
        cluster: None (a local cluster of processes), a ``distributed.Client`` (used as it
            is, not closed), an address ``tcp://HOST:PORT`` or a scheduler file's path.
        workers: the local cluster's worker processes (default: the usable cores).
        timeout: seconds to wait for a scheduler to answer.
        retries: the local cluster's scheduler reschedules a task whose worker died this
            many times (``distributed.scheduler.allowed-failures``) before it reports it.

    Raises:
        ClusterError: no answer within ``timeout``, a scheduler file that does not exist,
            ``workers`` < 1, distributed not installed.
    """
    distributed = _distributed()
    import dask

    if isinstance(cluster, distributed.Client):
        yield cluster
        return
    if cluster is None:
        n = usable_cores() if workers is None else workers
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ClusterError(f"workers must be a whole number >= 1, got {workers!r}")
        # the workers' settings as a copy of their own: a nanny keeps this process's nested
        # settings by reference, so a worker it restarts would get them back as they are
        settings = copy.deepcopy(dask.config.config)
        dask.config.set(WORKER_CONFIG, config=settings)
        with dask.config.set({"distributed.scheduler.allowed-failures": retries}):
            local = distributed.LocalCluster(n_workers=n, threads_per_worker=1,
                                             processes=True, dashboard_address=None,
                                             silence_logs=40, config=settings)
        try:
            client = distributed.Client(local)
            try:
                yield client
            finally:
                client.close()
        finally:
            local.close()
        return
    text = os.fspath(cluster)
    if "://" in text:
        kwargs = {"address": text}
    else:
        if not Path(text).is_file():
            raise ClusterError(f"--cluster {text}: neither an address (tcp://HOST:8786) nor a "
                               "scheduler file that exists")
        kwargs = {"scheduler_file": text}
    try:
        client = distributed.Client(**kwargs, timeout=timeout)
    except (OSError, TimeoutError, ValueError) as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ClusterError(f"--cluster {text}: no Dask scheduler answered within {timeout:g} s "
                           f"({first})") from None
    try:
        yield client
    finally:
        client.close()


def check_workers(client: Any) -> None:
    """Refuse a cluster whose workers would run two fits in one process (module docstring).

    Raises:
        ClusterError: no worker, a worker with more than one thread, two workers in one
            process.
    """
    info = client.scheduler_info(n_workers=-1)["workers"] if _takes_n(client) else \
        client.scheduler_info()["workers"]
    if not info:
        raise ClusterError("the cluster has no worker: start some (dask worker ADDRESS "
                           "--nthreads 1)")
    threads = {a: w.get("nthreads", 1) for a, w in info.items()}
    many = [a for a, n in threads.items() if n > 1]
    if many:
        raise ClusterError(f"worker {many[0]} runs {threads[many[0]]} threads: a fit seeds and "
                           "sets process-wide state, so each worker must run one (dask worker "
                           "--nthreads 1; one worker process per core)")
    pids = client.run(os.getpid)
    if len(set(pids.values())) < len(pids):
        raise ClusterError("two workers share a process (a cluster with processes=False): a "
                           "fit seeds and sets process-wide state, so each worker must be a "
                           "process of its own")


def _takes_n(client: Any) -> bool:
    import inspect

    return "n_workers" in inspect.signature(client.scheduler_info).parameters
