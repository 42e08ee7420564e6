"""A fleet identified in one call: :func:`identify_fleet`, the library object behind
``torchhys fleet``.

Each device is identified as ``torchhys fit`` identifies it alone (the same config and
options, :func:`torchhys.fleet.task.identify_device`: the same choice and numbers), each a
Dask task (:mod:`torchhys.fleet.cluster`), into its own run folder ``ROOT/fleet_N/<device>``;
then the report (:mod:`torchhys.fleet.report`): ``fleet.csv``, ``loops.png`` and a summary.

Failures do not stop the fleet: a device whose file cannot be read, whose columns differ
from the fleet's, or whose fit fails with a user error is a ``failed`` row with its reason;
a task that raises otherwise is retried ``retries`` times (Dask's ``retries=``), and one
whose worker dies is rescheduled (a local cluster's ``allowed-failures``: ``retries``) before
it is reported failed. ``resume=ROOT/fleet_N`` runs into that folder again: a device whose
run folder holds a finished result (``result.json`` with status ``ok``) is not refitted,
the others (failed, unfinished) are fitted afresh.
"""

from __future__ import annotations

import math
import os
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torchhys.fleet.cluster import ClusterError, check_workers, connect
from torchhys.fleet.devices import check_columns, find_devices
from torchhys.fleet.report import flag_outliers, plot_loops, summary, write_csv
from torchhys.fleet.task import identify_device, read_result
from torchhys.selection.jobs import wait_timeout

__all__ = ["FleetResult", "identify_fleet", "reserve_fleet_dir"]

_OWN = ("--trainer.default_root_dir", "--data.path", "--model.select_jobs")
"""Options of ``fit`` the fleet sets for each device itself."""


@dataclass(frozen=True)
class FleetResult:
    """What :func:`identify_fleet` found."""

    folder: Path
    """The fleet's folder ``ROOT/fleet_N``."""
    rows: list[dict[str, Any]]
    """One report row per device (:data:`torchhys.fleet.report.COLUMNS`, with ``loop``)."""
    csv: Path
    """``fleet.csv``."""
    picture: Path | None
    """``loops.png`` (None without matplotlib or without a fitted device)."""
    seconds: float
    text: str = field(repr=False, default="")
    """The summary printed at the end."""

    def row(self, device: str) -> dict[str, Any]:
        """The report row of ``device`` (KeyError: no such device)."""
        for r in self.rows:
            if r["device"] == device:
                return r
        raise KeyError(device)

    @property
    def failed(self) -> list[str]:
        """The devices that failed, by name."""
        return [r["device"] for r in self.rows if r["status"] != "ok"]

    @property
    def outliers(self) -> list[str]:
        """The devices flagged as outliers, by name."""
        return [r["device"] for r in self.rows if r.get("outlier")]


def reserve_fleet_dir(root: str | os.PathLike) -> Path:
    """The next free ``ROOT/fleet_N``, created now (``os.mkdir``: concurrent fleets get
    different folders)."""
    parent = Path(root)
    parent.mkdir(parents=True, exist_ok=True)
    found = [int(p.name[6:]) for p in parent.glob("fleet_*") if p.name[6:].isdigit()]
    n = max(found, default=-1) + 1
    while True:
        folder = parent / f"fleet_{n}"
        try:
            os.mkdir(folder)
            return folder
        except FileExistsError:
            n += 1


def _fit_args(config: str | os.PathLike | Sequence[str | os.PathLike] | None,
              args: Sequence[str]) -> list[str]:
    configs = [] if config is None else (
        [config] if isinstance(config, (str, os.PathLike)) else list(config))
    out = []
    for c in configs:
        if not Path(c).is_file():
            raise ValueError(f"config {c} does not exist")
        out += ["--config", str(Path(c).resolve())]
    for a in args:
        if not isinstance(a, str):
            raise TypeError(f"args must be strings (fit's options), got {a!r}")
        if a.split("=", 1)[0] in _OWN:
            raise ValueError(f"{a.split('=', 1)[0]} is set by the fleet for each device (the "
                             "devices: data; their folders: root); leave it out")
    return out + list(args)


def _failed(name: str, path: Any, run_dir: Path, reason: str) -> dict[str, Any]:
    return {"device": name, "path": str(path), "run_dir": str(run_dir), "status": "failed",
            "reason": reason, "candidate": "", "config": "", "family": "", "ratio": math.nan,
            "width": math.nan, "gain": math.nan, "fit_s": math.nan, "checkpoint": "",
            "loop": None}


def _run_tasks(client: Any, todo: list[tuple[Any, Path]], fit_args: list[str], retries: int,
               tell: Callable[[str], None], limit: float | None) -> dict[str, dict[str, Any]]:
    """Each device of ``todo`` a task on ``client``; their rows by device, as they finish
    (a task that failed after its retries: a failed row with the exception's first line;
    where no device finishes within ``limit`` seconds, the unfinished ones are cancelled
    and each is a failed row saying so)."""
    import distributed

    futures = {}
    for d, run_dir in todo:
        f = client.submit(identify_device, d.name, str(Path(d.path).resolve()), str(run_dir),
                          fit_args, key=f"fleet-{d.name}-{uuid.uuid4().hex}", pure=False,
                          retries=retries)
        futures[f] = (d, run_dir)
    rows: dict[str, dict[str, Any]] = {}
    pending = list(futures)
    while pending:
        try:
            done, left = distributed.wait(pending, timeout=limit, return_when="FIRST_COMPLETED")
        except TimeoutError:  # distributed's is one: nothing finished within the limit
            names = [futures[f][0].name for f in pending]
            client.cancel(pending)
            reason = (f"no device finished within {limit:g} s (the longest wait for the "
                      "next device: --device-timeout, TORCHHYS_TIMEOUT_S); cancelled")
            tell(f"torchhys fleet: {reason}: {', '.join(names)}")
            for f in pending:
                d, run_dir = futures[f]
                rows[d.name] = _failed(d.name, d.path, run_dir, reason)
            break
        pending = list(left)
        for f in sorted(done, key=lambda f: futures[f][0].name):
            d, run_dir = futures[f]
            try:
                row = f.result()
            except Exception as err:  # noqa: BLE001 (the task's, after its retries)
                text = str(err).strip().splitlines()[0] if str(err).strip() else ""
                row = _failed(d.name, d.path, run_dir,
                              f"{type(err).__name__} after {retries} retries: {text}")
            rows[d.name] = row
            what = (f"{row['family']} (candidate {row['candidate']}), ratio "
                    f"{row['ratio']:.3g}, {row['fit_s']:.1f} s" if row["status"] == "ok"
                    else f"failed: {row['reason']}")
            tell(f"torchhys fleet: [{len(rows)}/{len(todo)}] {d.name}: {what}")
    return rows


def _warm() -> None:
    import torchhys.cli.train  # noqa: F401 (Lightning and the command, imported)


def identify_fleet(data: str | os.PathLike | Sequence[str | os.PathLike] | Mapping[str, str],
                   *, config: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
                   args: Sequence[str] = (), root: str | os.PathLike = "runs/fleet",
                   device_column: str | None = None, cluster: Any = None,
                   workers: int | None = None, retries: int = 2, timeout: float = 10.0,
                   resume: str | os.PathLike | None = None,
                   device_timeout: float | None = None,
                   say: Callable[[str], None] | None = None) -> FleetResult:
    """Identify every device of a fleet, each as ``torchhys fit`` would alone, on Dask.

    Args:
        data: the devices' recordings: a glob (``devices/*.csv``, each file a device named
            by its stem), a list of files, a mapping name -> file, or one file with
            ``device_column`` (:func:`torchhys.fleet.devices.find_devices`).
        config: ``fit``'s config file(s) (``--config``; e.g. configs/measured.yaml).
        args: more ``fit`` options, as on its command line (``--trainer.max_epochs=5``,
            ``--model.select '[...]'``); not ``--data.path``, ``--trainer.default_root_dir``
            or ``--model.select_jobs`` (the fleet sets them).
        root: the folder of the fleets: this one goes to the next free ``root/fleet_N``.
        device_column: the column of ``data`` (one file) naming each row's device.
        cluster: None (a local cluster of ``workers`` processes), a ``distributed.Client``,
            an address ``tcp://HOST:8786`` or a scheduler file
            (:func:`~torchhys.fleet.cluster.connect`).
        workers: the local cluster's processes (default: the usable cores).
        retries: retries of a task that raised (and, on a local cluster, of one whose
            worker died) before the device is reported failed.
        timeout: seconds to wait for a cluster's scheduler.
        resume: an earlier fleet's folder to run into again (its finished devices kept).
        device_timeout: the longest wait, in seconds, for the next device to finish; past
            it the unfinished devices are cancelled and reported failed, saying so (default
            :func:`torchhys.selection.jobs.wait_timeout`: ``TORCHHYS_TIMEOUT_S``, or six
            hours; ``math.inf``: no limit).
        say: where progress lines go (default: stderr).

    Raises:
        ValueError: no device (an empty glob), duplicate device names, a bad option, a
            cluster that does not answer (:class:`~torchhys.fleet.cluster.ClusterError`).
    """
    start = time.perf_counter()
    tell = say or (lambda s: print(s, file=sys.stderr, flush=True))
    if isinstance(retries, bool) or not isinstance(retries, int) or retries < 0:
        raise ValueError(f"retries must be a whole number >= 0, got {retries!r}")
    limit = wait_timeout() if device_timeout is None else device_timeout
    if limit is not None and (isinstance(limit, bool) or not isinstance(limit, (int, float))
                              or math.isnan(limit) or limit <= 0):
        raise ValueError(f"device_timeout must be a number of seconds > 0, got {limit!r}")
    if limit is not None and math.isinf(limit):
        limit = None
    fit_args = _fit_args(config, args)
    folder = None
    if resume is not None:
        folder = Path(resume)
        if not folder.is_dir():
            raise ValueError(f"resume {folder}: no such fleet folder")
    if device_column is None:
        devices = find_devices(data)  # before a folder is made: an empty glob leaves none
        folder = folder or reserve_fleet_dir(root)
    else:
        created = folder is None
        folder = folder or reserve_fleet_dir(root)
        try:  # each device's rows, in the fleet's folder
            devices = find_devices(data, device_column=device_column,
                                   split_dir=folder / "_data")
        except BaseException:
            if created:
                shutil.rmtree(folder, ignore_errors=True)
            raise
    folder = folder.resolve()
    bad = check_columns(devices)
    rows: dict[str, dict[str, Any]] = {}
    todo = []
    for d in devices:
        run_dir = folder / d.name
        done = read_result(run_dir)
        if d.name in bad:
            rows[d.name] = _failed(d.name, d.path, run_dir, bad[d.name])
        elif done is not None and done.get("status") == "ok":
            rows[d.name] = {**done, "resumed": True}
        else:
            todo.append((d, run_dir))
    if len(todo) < len(devices):
        tell(f"torchhys fleet: {len(devices) - len(todo) - len(bad)} devices already "
             f"identified in {folder}, {len(bad)} unusable, {len(todo)} to fit")
    if todo:
        try:
            with connect(cluster, workers=workers, timeout=timeout, retries=retries) as client:
                check_workers(client)
                client.run(_warm)  # imported once per worker before the fits are timed
                rows.update(_run_tasks(client, todo, fit_args, retries, tell, limit))
        except ClusterError:
            if resume is None:  # a cluster refused before any device ran: no fleet folder left
                shutil.rmtree(folder, ignore_errors=True)
            raise
    ordered = flag_outliers([rows[d.name] for d in devices])
    table = write_csv(ordered, folder / "fleet.csv")
    picture = plot_loops(ordered, folder / "loops.png")
    seconds = time.perf_counter() - start
    text = summary(ordered, folder, seconds)
    return FleetResult(folder, ordered, table, picture, seconds, text)
