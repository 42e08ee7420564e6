"""One device of a fleet, identified where a Dask worker runs it: :func:`identify_device`.

It runs the command a lone identification runs, in the worker's process:
``torchhys fit ARGS --data.path FILE --trainer.default_root_dir RUN`` (the fleet's options,
the same config, data, model and trainer options for every device; model selection one
candidate at a time, ``--model.select_jobs 1``: a worker is a process of its own, and the
jobs give the same table as one process), then ``torchhys test`` of its ``last.ckpt``
(the held-out ratio to the better memoryless baseline, ``test_ratio``), then the fitted
model's loop on a standard sweep (:mod:`torchhys.fleet.loops`). Everything lands in the
device's run folder ``RUN`` (the fit's ``logs/version_0`` with ``selection.csv`` and
``checkpoints/last.ckpt``; the test's ``logs/version_1``), the commands' output in
``RUN/fit.log``, and the device's row of the report in ``RUN/result.json``, written last
(atomically): a run folder holding it is finished (:func:`finished`), one without it is
cleared before the device is fitted again. Each device starts as a process of its own
would: the shared family fits of earlier devices dropped
(:mod:`torchhys.identification._fit_cache`), the warning filters its commands add removed
after them.

A user error of the commands (a file that cannot be read, data a family cannot fit, ...:
the one line ``torchhys fit: error: ...``) is the device's failure, with that line as its
reason, not retried; any other exception propagates to Dask, which retries the task.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import shutil
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["RESULT", "finished", "identify_device", "read_result"]

RESULT = "result.json"
"""The file of a device's finished result in its run folder."""


def read_result(run_dir: str | os.PathLike) -> dict[str, Any] | None:
    """The device's finished result (its report row), or None (none, or unreadable)."""
    try:
        with open(Path(run_dir) / RESULT) as fh:
            row = json.load(fh)
    except (OSError, ValueError):
        return None
    return row if isinstance(row, dict) else None


def finished(run_dir: str | os.PathLike) -> bool:
    """Whether a device's run folder holds a finished, successful result (resume skips it)."""
    row = read_result(run_dir)
    return row is not None and row.get("status") == "ok"


def _write_result(run_dir: Path, row: dict[str, Any]) -> None:
    tmp = run_dir / (RESULT + ".tmp")
    tmp.write_text(json.dumps(row, indent=1, allow_nan=True))
    os.replace(tmp, run_dir / RESULT)


def _command(args: Sequence[str], log: io.TextIOBase) -> str | None:
    """Run ``torchhys ARGS`` here, its output into ``log``; None, or its one-line user error."""
    from torchhys.cli.commands import main

    before = log.tell()
    with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log):
        try:
            main(list(args))
        except SystemExit as exc:
            if exc.code in (0, None):
                return None
            log.flush()
            with open(log.name) as fh:
                fh.seek(before)
                lines = [ln.strip() for ln in fh.read().splitlines() if ln.strip()]
            errors = [ln for ln in lines if ": error: " in ln]
            return (errors or lines or [f"exit status {exc.code}"])[-1]
    return None


def _chosen(run: Path) -> tuple[str, str]:
    """The chosen candidate's index and config in the fit's ``selection.csv`` ("" without
    model selection)."""
    table = run / "logs" / "version_0" / "selection.csv"
    if not table.exists():
        return "", ""
    with table.open(newline="") as fh:
        for row in csv.DictReader(fh):
            if row.get("selected") == "1":
                return row["candidate"], row["config"]
    return "", ""


def _test_ratio(run: Path) -> float:
    metrics = run / "logs" / "version_1" / "metrics.csv"
    with contextlib.suppress(OSError, KeyError, ValueError, StopIteration):
        with metrics.open(newline="") as fh:
            rows = [r for r in csv.DictReader(fh) if r.get("test_ratio")]
        return float(rows[-1]["test_ratio"])
    return math.nan


def identify_device(name: str, path: str, run_dir: str, args: Sequence[str]) -> dict[str, Any]:
    """Identify one device (the module docstring): its report row, also written to
    ``run_dir/result.json``. Keys: ``device``, ``path``, ``run_dir``, ``status`` (``ok`` or
    ``failed``), ``reason``, ``candidate``, ``config``, ``family``, ``ratio``, ``width``,
    ``gain``, ``fit_s``, ``checkpoint``, ``loop`` (the sweep's input and output, for the
    picture)."""
    from torchhys.fleet.loops import family_name, loop_of

    run = Path(run_dir)
    if run.exists():  # an unfinished earlier try: start afresh, as a lone fit would
        shutil.rmtree(run)
    run.mkdir(parents=True)
    row: dict[str, Any] = {"device": name, "path": str(path), "run_dir": str(run),
                           "status": "failed", "reason": "", "candidate": "", "config": "",
                           "family": "", "ratio": math.nan, "width": math.nan,
                           "gain": math.nan, "fit_s": math.nan, "checkpoint": "", "loop": None}
    common = [*args, "--data.path", str(path), "--trainer.default_root_dir", str(run),
              "--trainer.enable_progress_bar", "false"]
    from torchhys.identification import _fit_cache

    _fit_cache.clear()  # as in a process of its own: no family fitted for an earlier device
    start = time.perf_counter()
    saved_argv = sys.argv[:]
    try:
        sys.argv[:] = ["torchhys"]
        # the filters a fit adds (one per run folder) do not pile up in the worker
        with (run / "fit.log").open("w+") as log, warnings.catch_warnings():
            error = _command(["fit", *common, "--model.select_jobs", "1"], log)
            row["fit_s"] = time.perf_counter() - start
            ckpt = run / "logs" / "version_0" / "checkpoints" / "last.ckpt"
            if error is None and not ckpt.exists():
                error = f"the fit wrote no checkpoint ({ckpt})"
            if error is None:
                row["checkpoint"] = str(ckpt)
                row["candidate"], row["config"] = _chosen(run)
                row["family"] = family_name(row["config"]) if row["config"] else ""
                error = _command(["test", *common, "--ckpt_path", str(ckpt)], log)
                row["ratio"] = _test_ratio(run)
            if error is None:
                loop = loop_of(run, ckpt)
                row.update(width=loop.width, gain=loop.gain,
                           loop={"x": loop.x.tolist(), "y": loop.y.tolist()})
                if not row["family"]:
                    row["family"] = loop.family
    finally:
        sys.argv[:] = saved_argv
    row["status"], row["reason"] = ("ok", "") if error is None else ("failed", error)
    _write_result(run, row)
    return row
