"""A fleet worker's memory, device after device: one Dask worker process (a local cluster of
one) fits simulated devices one at a time (:func:`torchhys.fleet.task.identify_device`, the
fleet's task; the devices of benchmarks/fleet.py), and after each reports its resident
memory (``VmRSS``, after a ``gc.collect()``) and the nodes of the profile trees Dask's
statistical profiler keeps (``profile_history``, ``profile_keys_history``), with the
profiler on (Dask's default) and off (the fleet's local cluster,
:data:`torchhys.fleet.cluster.WORKER_CONFIG`)::

    python benchmarks/fleet_memory.py [--devices 50] [--samples 10000] [--every 10]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.fleet import CONFIG, SMALL, _warm, make_fleet  # noqa: E402


def _fit(name: str, path: str, run_dir: str, args: list[str]) -> float:
    """Identify one device in the worker; its resident memory afterwards (MiB)."""
    import gc

    from torchhys.fleet.task import identify_device

    identify_device(name, path, run_dir, args)
    gc.collect()
    with open("/proc/self/status") as fh:
        return next(int(ln.split()[1]) / 1024 for ln in fh if ln.startswith("VmRSS"))


def _profile_nodes(dask_worker: object) -> int:
    """The nodes of the profile trees the worker keeps."""
    def size(tree: dict) -> int:
        return 1 + sum(size(c) for c in tree.get("children", {}).values())

    return (sum(size(t) for _, t in dask_worker.profile_history)
            + sum(size(t) for _, d in dask_worker.profile_keys_history for t in d.values()))


def run(profiler: bool, devices: int, samples: int, every: int, folder: Path) -> list[tuple]:
    """(devices fitted, MiB, profile nodes) after every ``every`` devices."""
    import dask
    import distributed

    data = folder / f"d{int(profiler)}"
    data.mkdir()
    make_fleet(data, devices, samples)
    (folder / "small.yaml").write_text(SMALL)
    args = ["--config", str(CONFIG), "--config", str(folder / "small.yaml")]
    with dask.config.set({"distributed.worker.profile.enabled": profiler}):
        local = distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                                         dashboard_address=None, silence_logs=40)
    out = []
    with local, distributed.Client(local) as client:
        client.run(_warm)
        for i in range(devices):
            mib = client.submit(_fit, f"u{i}", str(data / f"unit_{i:04d}.csv"),
                                str(folder / f"runs{int(profiler)}" / f"u{i}"), args,
                                pure=False).result()
            if (i + 1) % every == 0 or i == 0:
                nodes = next(iter(client.run(_profile_nodes).values()))
                out.append((i + 1, mib, nodes))
                print(f"profiler {'on' if profiler else 'off'}: {i + 1} devices, {mib:.0f} MiB, "
                      f"{nodes} profile nodes", file=sys.stderr, flush=True)
    return out


def main(argv: list[str] | None = None) -> dict[bool, list[tuple]]:
    """Run the benchmark (module docstring); per profiler setting, its rows."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--devices", type=int, default=50)
    p.add_argument("--samples", type=int, default=10_000)
    p.add_argument("--every", type=int, default=10)
    a = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        rows = {on: run(on, a.devices, a.samples, a.every, Path(tmp)) for on in (True, False)}
    print("| devices fitted | MiB, profiler on | profile nodes | MiB, profiler off |")
    print("|---|---|---|---|")
    for (n, on_mib, nodes), (_, off_mib, _) in zip(rows[True], rows[False], strict=True):
        print(f"| {n} | {on_mib:.0f} | {nodes} | {off_mib:.0f} |")
    return rows


if __name__ == "__main__":
    main()
