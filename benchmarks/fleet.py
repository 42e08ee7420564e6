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
choice, held-out ratio, width and gain of each device, exactly), the peak resident memory
of a worker, and the fractions of faulty units flagged and of good units flagged::

    python benchmarks/fleet.py [--sizes 20 100 500] [--samples 10000] [--small]
                               [--workers N] [--no-serial] [--quick]

``--quick``: 7 devices of 2000 samples with ``--small`` (a smoke test, about a minute on
two cores).
"""

from __future__ import annotations

import argparse
import math
import resource
import sys
import tempfile
import time
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


def _serial(devices: dict[str, Path], root: Path, args: list[str]) -> tuple[list[dict], float]:
    from torchhys.fleet.report import flag_outliers
    from torchhys.fleet.task import identify_device

    start = time.perf_counter()
    rows = [identify_device(name, str(path), str(root / name), args)
            for name, path in devices.items()]
    return flag_outliers(rows), time.perf_counter() - start


def _key(r: dict) -> tuple:
    return (r["status"], r["candidate"], r["ratio"], r["width"], r["gain"])


def run_size(n: int, samples: int, small: bool, workers: int | None, serial: bool,
             folder: Path) -> dict:
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
           "failed": len(cluster.failed)}
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
        row["identical"] = "yes" if [_key(r) for r in rows] == [
            _key(r) for r in cluster.rows] and [r["outlier"] for r in rows] == [
            r["outlier"] for r in cluster.rows] else "NO"
    return row


COLUMNS = ("devices", "samples", "workers", "cluster_s", "serial_s", "speedup", "identical",
           "worker_mib", "failed", "faulty_flagged", "good_flagged")


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
    p.add_argument("--no-serial", action="store_true", help="the cluster only")
    p.add_argument("--quick", action="store_true", help="7 devices of 2000 samples, --small")
    a = p.parse_args(argv)
    if a.quick:
        a.sizes, a.samples, a.small = [7], 2000, True
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in a.sizes:
            rows.append(run_size(n, a.samples, a.small, a.workers, not a.no_serial,
                                 Path(tmp)))
            print(table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
    print(table(rows))
    return rows


if __name__ == "__main__":
    main()
