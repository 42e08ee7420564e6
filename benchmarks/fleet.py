"""A fleet at scale: simulated devices identified on a Dask LocalCluster against the same
devices fitted one after another, and the fraction of faulty and of good units flagged.

The fleet: a Bouc-Wen plant family (the default :class:`torchhys.plants.BoucWen` plant
driven as examples/data/bouc_wen.csv is, 100 Hz) with device-to-device spread: each good
unit's ``A`` (the loop's width) and output gain drawn within +-3 %, its ``beta`` (how early
it saturates) within +-5 %, its sensor noise seed its own; one unit in twenty (at least
one) is faulty, its ``A`` three times the others' (a loop about three times as wide). Each
device is identified by configs/measured.yaml, or with ``--small`` by three candidates (the
line, a non-negative PI, stop operators) by 2-fold cross-validation.

Printed per fleet size: the wall time of the local cluster (one worker process per usable
core, ``--workers``; started, and its imports done, before the clock starts) and of the
serial run (:func:`torchhys.fleet.task.identify_device` in this process, device after
device, after the same imports), the speed-up, whether the two give the same rows (the
choice, held-out ratio, width, gain and outlier flag of each device, exactly), the peak
resident memory of a worker, and the fractions of faulty units flagged and of good units
flagged. Then the same fleet on a cluster of processes of their own (:func:`separate`:
``dask scheduler`` and two ``dask worker --nthreads 1``, each started as a command of its
own, standing in for two machines), sent to it by address (``cluster="tcp://..."``): its
wall time (its workers' imports done before the clock starts), whether its rows are those
of the serial run (of the local cluster with ``--no-serial``) and its workers' largest peak
resident memory; ``--no-separate`` leaves it out::

    python benchmarks/fleet.py [--sizes 20 100 500] [--samples 10000] [--small]
                               [--workers N] [--no-serial] [--no-separate] [--quick]

``--quick``: 7 devices of 2000 samples with ``--small`` (a smoke test, about a minute on
two cores).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "measured.yaml"
SMALL = """model:
  select:
    - operator: null
    - operator: [{fit: pi_nonneg, n_widths: 6, power: 2.0, direction: direct}]
    - operator: [{fit: stop_pi, n_widths: 8, power: 2.0, segments: 2}]
  select_cv: 2
"""


def make_fleet(folder: Path, n: int, samples: int, seed: int = 0) -> dict[str, bool]:
    """Write ``n`` devices' recordings to ``folder`` (``unit_NNNN.csv``); name -> faulty."""
    from torchhys.plants import bouc_wen
    from torchhys.signals import multisine, time_grid, to_range

    rng = np.random.default_rng(seed)
    t = time_grid(dt=0.01, t_end=(samples - 1) * 0.01, dtype=torch.float64)
    u = to_range(multisine(t, band=(0.2, 3.0), n_tones=8, seed=0), -6.0, 6.0)
    n_faulty = max(1, n // 20)
    faulty_at = set(rng.choice(n, size=n_faulty, replace=False).tolist())
    truth = {}
    for i in range(n):
        a = 0.5 * (1 + rng.uniform(-0.03, 0.03))
        gain = 1 + rng.uniform(-0.03, 0.03)
        beta = 0.3 * (1 + rng.uniform(-0.05, 0.05))
        if i in faulty_at:
            a *= 3.0
        y = gain * bouc_wen(u, t, A=a, beta=beta)
        y = y + 0.005 * torch.randn(y.shape, generator=torch.Generator().manual_seed(i + 1),
                                    dtype=torch.float64)
        name = f"unit_{i:04d}"
        np.savetxt(folder / f"{name}.csv", torch.stack([t, u, y], 1).numpy(), delimiter=",",
                   header="time,command,response", comments="", fmt="%.6f")
        truth[name] = i in faulty_at
    return truth


def _warm() -> None:
    import torchhys.cli.train  # noqa: F401 (Lightning and the command)


def _peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _stop(proc: subprocess.Popen) -> None:
    """End a process started by :func:`separate` and its children (a worker's nanny's),
    SIGTERM first, then SIGKILL."""
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pass
    with contextlib.suppress(ProcessLookupError):  # a nanny's worker left behind
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait(timeout=30)


@contextlib.contextmanager
def separate(folder: Path, workers: int = 2, timeout: float = 120.0) -> Iterator[str]:
    """A Dask scheduler and ``workers`` worker processes of one thread, each started as a
    command of its own (``python -m dask scheduler`` / ``dask worker ADDRESS --nthreads 1``,
    in sessions of their own, their output in ``folder/*.log``): the scheduler's address,
    ``tcp://127.0.0.1:PORT``. The workers run without Dask's profiler
    (``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False``, as docs/fleet.md advises). Every
    process is ended on exit, also on error.

    Raises:
        RuntimeError: the scheduler wrote no address, or the workers did not join, within
            ``timeout`` seconds (with its log's last line).
    """
    folder.mkdir(parents=True, exist_ok=True)
    file = folder / "scheduler.json"
    procs = []

    # the workers as docs/fleet.md starts them: without Dask's profiler (its history of
    # the fits' stacks grows a worker by MiBs a device: torchhys.fleet.cluster)
    env = {**os.environ, "DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED": "False"}

    def start(name: str, *args: str) -> subprocess.Popen:
        with open(folder / f"{name}.log", "w") as log:
            procs.append(subprocess.Popen([sys.executable, "-m", "dask", *args], cwd=folder,
                                          stdout=log, stderr=subprocess.STDOUT, env=env,
                                          stdin=subprocess.DEVNULL, start_new_session=True))
        return procs[-1]

    def fail(name: str, what: str) -> RuntimeError:
        lines = (folder / f"{name}.log").read_text().strip().splitlines() or ["(no output)"]
        return RuntimeError(f"separate cluster: {what} within {timeout:g} s ({lines[-1]})")

    try:
        start("scheduler", "scheduler", "--host", "127.0.0.1", "--port", "0",
              "--no-dashboard", "--scheduler-file", str(file))
        deadline = time.monotonic() + timeout
        while not file.exists() or not file.read_text().strip():
            if time.monotonic() > deadline or procs[0].poll() is not None:
                raise fail("scheduler", "the scheduler wrote no address")
            time.sleep(0.2)
        address = json.loads(file.read_text())["address"]
        for i in range(workers):
            start(f"worker{i}", "worker", address, "--nthreads", "1", "--nworkers", "1",
                  "--no-dashboard", "--name", f"separate-{i}", "--local-directory",
                  str(folder / f"worker{i}"))
        import distributed

        with distributed.Client(address, timeout=timeout) as client:
            try:
                client.wait_for_workers(workers, timeout=timeout)
            except TimeoutError:
                raise fail("worker0", f"{workers} workers did not join") from None
        yield address
    finally:
        for proc in procs[::-1]:
            _stop(proc)


def _separate_run(data: Path, configs: list[Path], folder: Path, n: int,
                  workers: int = 2) -> tuple[object, float]:
    """The fleet on :func:`separate`'s cluster, by address: its result and its workers'
    largest peak resident memory (MiB)."""
    import distributed

    from torchhys.fleet import identify_fleet

    if __name__ != "__main__":  # the workers (other machines) have no benchmarks/ to import
        import cloudpickle

        cloudpickle.register_pickle_by_value(sys.modules[__name__])
    with separate(folder / f"separate{n}", workers) as address:
        with distributed.Client(address, timeout=60) as client:
            client.run(_warm)  # the workers' imports, before the clock starts
            result = identify_fleet(str(data / "*.csv"), config=configs,
                                    root=folder / f"runs_separate{n}", cluster=address,
                                    say=lambda s: None)
            peak = max(client.run(_peak_mib).values())
    return result, peak


def _serial(devices: dict[str, Path], root: Path, args: list[str]) -> tuple[list[dict], float]:
    from torchhys.fleet.report import flag_outliers
    from torchhys.fleet.task import identify_device

    start = time.perf_counter()
    rows = [identify_device(name, str(path), str(root / name), args)
            for name, path in devices.items()]
    return flag_outliers(rows), time.perf_counter() - start


def _key(r: dict) -> tuple:
    return (r["status"], r["candidate"], r["ratio"], r["width"], r["gain"], r["outlier"])


def _same(a: list[dict], b: list[dict]) -> str:
    """"yes" if two runs' rows agree exactly (device by device), else "NO"."""
    return "yes" if [(r["device"], *_key(r)) for r in a] == [
        (r["device"], *_key(r)) for r in b] else "NO"


def run_size(n: int, samples: int, small: bool, workers: int | None, serial: bool,
             folder: Path, separate_run: bool = True) -> dict:
    """One fleet size's row of the table."""
    from torchhys.fleet import identify_fleet
    from torchhys.fleet.cluster import connect

    data = folder / f"n{n}"
    data.mkdir()
    truth = make_fleet(data, n, samples)
    configs = [CONFIG]
    if small:
        (folder / "small.yaml").write_text(SMALL)
        configs.append(folder / "small.yaml")
    with connect(None, workers=workers) as client:
        client.run(_warm)  # each worker's imports, before the clock starts (as the serial's)
        cluster = identify_fleet(str(data / "*.csv"), config=configs, root=folder / f"runs{n}",
                                 cluster=client, say=lambda s: None)
        peak = max(client.run(_peak_mib).values())
        n_workers = len(client.scheduler_info()["workers"])
    row = {"devices": n, "samples": samples, "workers": n_workers,
           "cluster_s": cluster.seconds, "serial_s": math.nan, "speedup": math.nan,
           "identical": "n/a", "worker_mib": peak,
           "failed": len(cluster.failed), "separate_s": math.nan,
           "separate_identical": "n/a", "separate_mib": math.nan}
    flagged = set(cluster.outliers)
    faulty = {k for k, v in truth.items() if v}
    good = set(truth) - faulty
    row["faulty_flagged"] = len(flagged & faulty) / len(faulty)
    row["good_flagged"] = len(flagged & good) / len(good)
    if serial:
        args = [a for c in configs for a in ("--config", str(Path(c).resolve()))]
        torch.set_num_threads(1)
        _warm()
        rows, seconds = _serial({p.stem: p for p in sorted(data.glob("*.csv"))},
                                folder / f"serial{n}", args)
        row["serial_s"], row["speedup"] = seconds, seconds / cluster.seconds
        row["identical"] = _same(rows, cluster.rows)
    if separate_run:
        far, row["separate_mib"] = _separate_run(data, configs, folder, n)
        row["separate_s"] = far.seconds
        row["separate_identical"] = _same(far.rows, rows if serial else cluster.rows)
        row["failed"] += len(far.failed)
    return row


COLUMNS = ("devices", "samples", "workers", "cluster_s", "serial_s", "speedup", "identical",
           "worker_mib", "separate_s", "separate_identical", "separate_mib", "failed",
           "faulty_flagged", "good_flagged")


def table(rows: list[dict]) -> str:
    """The rows as a Markdown table."""
    def fmt(v: object) -> str:
        return f"{v:.3g}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(fmt(r[c]) for c in COLUMNS) + " |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    """Run the benchmark (module docstring); its rows."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[20, 100, 500])
    p.add_argument("--samples", type=int, default=10_000)
    p.add_argument("--small", action="store_true", help="three candidates, 2-fold CV")
    p.add_argument("--workers", type=int, default=None)
    p.add_argument("--no-serial", action="store_true", help="the clusters only")
    p.add_argument("--no-separate", action="store_true",
                   help="without the cluster of separate scheduler and worker processes")
    p.add_argument("--quick", action="store_true", help="7 devices of 2000 samples, --small")
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.samples, a.small = [7], 2000, True
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in a.sizes:
            rows.append(run_size(n, a.samples, a.small, a.workers, not a.no_serial,
                                 Path(tmp), not a.no_separate))
            print(table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
    print(table(rows))
    return rows


if __name__ == "__main__":
    main()
