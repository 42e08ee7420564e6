"""torchhys.fleet: a fleet of simulated devices identified on a real Dask LocalCluster (two
worker processes), each as a lone ``torchhys fit`` identifies it; the report's outliers;
failures, resume, a worker that dies, bad input; a cluster of a ``dask scheduler`` and a
``dask worker`` started as processes of their own."""

from __future__ import annotations

import csv
import math
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

distributed = pytest.importorskip("distributed")

from torchhys.cli.fleet import split_fleet_options  # noqa: E402
from torchhys.fleet import ClusterError, find_devices, flag_outliers, identify_fleet  # noqa: E402
from torchhys.fleet.cluster import check_workers, connect  # noqa: E402
from torchhys.fleet.loops import loop_metrics  # noqa: E402
from torchhys.fleet.report import COLUMNS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
MEASURED = ROOT / "configs" / "measured.yaml"
SMALL = """model:
  select:
    - operator: null
    - operator: [{fit: pi_nonneg, n_widths: 6, power: 2.0, direction: direct}]
    - operator: [{fit: stop_pi, n_widths: 8, power: 2.0, segments: 2}]
  select_cv: 2
"""
"""Over configs/measured.yaml: three candidates by 2-fold cross-validation (fast)."""

GOOD = [(0.50, 1.00), (0.51, 0.99), (0.49, 1.01), (0.505, 1.005), (0.495, 0.995),
        (0.50, 1.01)]
"""(A, gain) of the good units: a Bouc-Wen plant with a spread of 1-2 %."""
FAULTY = (1.6, 1.0)
"""A faulty unit: a much wider loop (A three times the others')."""


def _device(path: Path, a: float, gain: float, seed: int, t_end: float = 20.0) -> None:
    """A recording of ``t_end`` s at 100 Hz (2000 rows) of a Bouc-Wen plant, as
    examples/data/bouc_wen.csv (columns time, command, response)."""
    from torchhys.plants import bouc_wen
    from torchhys.signals import multisine, time_grid, to_range

    t = time_grid(dt=0.01, t_end=t_end, dtype=torch.float64)
    u = to_range(multisine(t, band=(0.2, 3.0), n_tones=8, seed=0), -6.0, 6.0)
    y = gain * bouc_wen(u, t, A=a)
    y = y + 0.005 * torch.randn(y.shape, generator=torch.Generator().manual_seed(seed),
                                dtype=torch.float64)
    np.savetxt(path, torch.stack([t, u, y], 1).numpy(), delimiter=",",
               header="time,command,response", comments="", fmt="%.6f")


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    (d / "small.yaml").write_text(SMALL)
    devs = d / "devices"
    devs.mkdir()
    for i, (a, g) in enumerate(GOOD):
        _device(devs / f"unit{i}.csv", a, g, seed=i)
    _device(devs / "faulty.csv", *FAULTY, seed=9)
    # a fit error (text where numbers belong) and other columns than the fleet's
    (devs / "garbled.csv").write_text("time,command,response\n" + "a,b,c\n" * 50)
    (devs / "other.csv").write_text("t,u,v\n" + "0,1,2\n" * 50)
    return d


@pytest.fixture(scope="module")
def client():
    with connect(None, workers=2, retries=2) as c:
        yield c


def _configs(folder: Path) -> list[Path]:
    return [MEASURED, folder / "small.yaml"]


@pytest.fixture(scope="module")
def fleet(folder, client):
    return identify_fleet(str(folder / "devices" / "*.csv"), config=_configs(folder),
                          root=folder / "runs", cluster=client, say=lambda s: None)


def test_every_device_has_its_run_folder_and_row(fleet, folder):
    assert fleet.folder == (folder / "runs" / "fleet_0").resolve()
    names = sorted(["faulty", "garbled", "other", *[f"unit{i}" for i in range(len(GOOD))]])
    assert [r["device"] for r in fleet.rows] == names
    for r in fleet.rows:
        if r["status"] != "ok":
            continue
        run = fleet.folder / r["device"] / "logs" / "version_0"
        assert (run / "selection.csv").is_file() and (run / "checkpoints" / "last.ckpt").is_file()
        assert 0 < r["ratio"] < 1 and r["fit_s"] > 0 and math.isfinite(r["width"])
    with (fleet.folder / "fleet.csv").open(newline="") as fh:
        reader = csv.DictReader(fh)
        table = list(reader)
    assert tuple(reader.fieldnames) == COLUMNS
    assert [t["device"] for t in table] == names
    assert fleet.picture is not None and fleet.picture.read_bytes()[:4] == b"\x89PNG"
    assert f"{len(names)} devices, {len(GOOD) + 1} identified" in fleet.text


def test_failures_are_rows_with_their_reason(fleet):
    assert sorted(fleet.failed) == ["garbled", "other"]
    other = fleet.row("other")["reason"]
    assert "differ from the fleet's ['time', 'command', 'response']" in other
    garbled = fleet.row("garbled")["reason"]
    assert garbled.startswith("torchhys fit: error:") and "\n" not in garbled


def test_the_faulty_unit_is_flagged_and_no_good_one(fleet):
    assert fleet.outliers == ["faulty"], [(r["device"], r["outlier_reason"]) for r in fleet.rows]
    assert "loop width" in fleet.row("faulty")["outlier_reason"]
    good = [fleet.row(f"unit{i}")["width"] for i in range(len(GOOD))]
    assert fleet.row("faulty")["width"] > 1.5 * max(good)


def test_a_device_is_identified_as_a_lone_fit_identifies_it(fleet, folder, monkeypatch):
    """The same command alone (model.select_jobs auto, as the config says): the same
    selection table and the same weights in last.ckpt, bit for bit."""
    from torchhys.cli.main import main

    lone = folder / "lone"
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    torch.set_num_threads(1)
    args = [a for c in _configs(folder) for a in ("--config", str(c))]
    main(["fit", *args, "--data.path", str(folder / "devices" / "unit0.csv"),
          "--trainer.default_root_dir", str(lone), "--trainer.enable_progress_bar", "false"])
    mine = lone / "logs" / "version_0"
    theirs = fleet.folder / "unit0" / "logs" / "version_0"
    assert (mine / "selection.csv").read_text() == (theirs / "selection.csv").read_text()
    a = torch.load(mine / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    b = torch.load(theirs / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_resume_keeps_the_finished_devices(fleet, folder, client):
    stamps = {r["device"]: os.stat(fleet.folder / r["device"] / "result.json").st_mtime_ns
              for r in fleet.rows if r["status"] == "ok"}
    again = identify_fleet(str(folder / "devices" / "*.csv"), config=_configs(folder),
                           resume=fleet.folder, cluster=client, say=lambda s: None)
    assert again.folder == fleet.folder
    for name, stamp in stamps.items():
        assert again.row(name)["resumed"] is True
        assert os.stat(fleet.folder / name / "result.json").st_mtime_ns == stamp
        assert again.row(name)["ratio"] == fleet.row(name)["ratio"]
    assert sorted(again.failed) == ["garbled", "other"]  # tried again, failed again
    assert again.outliers == ["faulty"]


def test_a_worker_that_dies_is_retried(folder, client, tmp_path):
    """A plugin that kills its process the first time it is imported: the worker dies with
    the device's task, Dask reschedules it, and the device is identified."""
    marker = tmp_path / "died"
    (tmp_path / "die_once.py").write_text(
        "import os\nfrom pathlib import Path\n"
        f"m = Path({str(marker)!r})\n"
        "if not m.exists():\n    m.write_text('died')\n    os._exit(1)\n")
    result = identify_fleet({"unit1": str(folder / "devices" / "unit1.csv")},
                            config=_configs(folder), root=tmp_path / "runs", cluster=client,
                            args=["--import-path", str(tmp_path), "--import", "die_once"],
                            say=lambda s: None)
    assert marker.read_text() == "died"
    assert result.rows[0]["status"] == "ok", result.rows[0]["reason"]
    assert result.rows[0]["candidate"] == "2"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_a_cluster_that_does_not_answer_is_one_line_within_the_timeout(folder, tmp_path):
    start = time.perf_counter()
    address = f"tcp://127.0.0.1:{_free_port()}"
    with pytest.raises(ClusterError, match=f"--cluster {address}: no Dask scheduler answered "
                                           "within 1 s") as err:
        identify_fleet(str(folder / "devices" / "unit0.csv"), config=_configs(folder),
                       root=tmp_path, cluster=address, timeout=1.0, say=lambda s: None)
    assert "\n" not in str(err.value)
    assert time.perf_counter() - start < 10
    assert list(tmp_path.iterdir()) == []  # no fleet folder left behind
    with pytest.raises(ClusterError, match="neither an address"):
        identify_fleet(str(folder / "devices" / "unit0.csv"), root=tmp_path,
                       cluster=str(tmp_path / "absent.json"), say=lambda s: None)


def test_workers_sharing_a_process_are_refused():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as local, \
            distributed.Client(local) as c, \
            pytest.raises(ClusterError, match="two workers share a process"):
        check_workers(c)


def test_bad_input(folder, tmp_path):
    with pytest.raises(ValueError, match="matches no file"):
        identify_fleet(str(tmp_path / "none" / "*.csv"), root=tmp_path / "r")
    assert not (tmp_path / "r").exists()
    (tmp_path / "a").mkdir()
    shutil.copy(folder / "devices" / "unit0.csv", tmp_path / "a" / "unit0.csv")
    with pytest.raises(ValueError, match="two devices are named 'unit0'"):
        find_devices([folder / "devices" / "unit0.csv", tmp_path / "a" / "unit0.csv"])
    with pytest.raises(ValueError, match="--trainer.default_root_dir is set by the fleet"):
        identify_fleet(str(folder / "devices" / "unit0.csv"),
                       args=["--trainer.default_root_dir=x"])
    with pytest.raises(ValueError, match="retries must be a whole number"):
        identify_fleet(str(folder / "devices" / "unit0.csv"), retries=-1)


def test_device_column_splits_one_file(tmp_path, folder):
    rows = ["device,time,command,response"]
    for name in ("b1", "a1"):
        with (folder / "devices" / "unit0.csv").open() as fh:
            rows += [f"{name},{line.strip()}" for line in list(fh)[1:4]]
    (tmp_path / "all.csv").write_text("\n".join(rows) + "\n")
    devices = find_devices(str(tmp_path / "all.csv"), device_column="device",
                           split_dir=tmp_path / "split")
    assert [d.name for d in devices] == ["a1", "b1"]
    text = devices[0].path.read_text().splitlines()
    assert text[0] == "time,command,response" and len(text) == 4
    with pytest.raises(ValueError, match="has no such column"):
        find_devices(str(tmp_path / "all.csv"), device_column="unit", split_dir=tmp_path)


def test_loop_width_and_gain_against_a_plain_loop():
    """A parallelogram loop y = 2 x +- 0.5 (rising: -0.5, falling: +0.5) on x in [-1, 1]:
    the gap 1 over the output range 5, the slope 2."""
    up = np.linspace(-1, 1, 101)
    x = np.concatenate([up, up[::-1]])
    y = 2 * x + np.concatenate([np.full(101, -0.5), np.full(101, 0.5)])
    width, gain = loop_metrics(x, y)
    assert width == pytest.approx(1.0 / 5.0) and gain == pytest.approx(2.0)


def test_outlier_rule_names_each_reason():
    rows = [{"device": f"d{i}", "status": "ok", "width": 0.2 + 0.001 * i, "gain": 1.0,
             "ratio": 0.1, "family": "stop_pi"} for i in range(6)]
    rows.append({"device": "odd", "status": "ok", "width": 0.2, "gain": 2.0, "ratio": 0.1,
                 "family": "preisach"})
    rows.append({"device": "dead", "status": "failed", "reason": "x"})
    out = flag_outliers(rows)
    assert [r["device"] for r in out if r["outlier"]] == ["odd"]
    reason = out[6]["outlier_reason"]
    assert reason.startswith("gain 2 vs median 1") and "family preisach vs the fleet's " \
        "stop_pi (6 of 7)" in reason


@pytest.mark.slow
def test_a_scheduler_and_a_worker_of_their_own_give_the_local_results(fleet, folder, tmp_path):
    """``dask scheduler`` and ``dask worker --nthreads 1`` started as processes (standing in
    for two machines), the fleet sent to them by address: the same rows as the local run."""
    dask = Path(sys.executable).with_name("dask")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = [subprocess.Popen([str(dask), "scheduler", "--port", str(port),
                               "--no-dashboard"], stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen([str(dask), "worker", address, "--nthreads", "1",
                                       "--nworkers", "1", "--no-dashboard"],
                                      stderr=subprocess.DEVNULL, cwd=tmp_path))
        with distributed.Client(address, timeout=30) as c:
            c.wait_for_workers(1, timeout=60)
            names = {"unit0": str(folder / "devices" / "unit0.csv"),
                     "faulty": str(folder / "devices" / "faulty.csv")}
            far = identify_fleet(names, config=_configs(folder), root=tmp_path / "runs",
                                 cluster=address, say=lambda s: None)
    finally:
        for p in procs[::-1]:
            p.terminate()
            p.wait(timeout=30)
    for r in far.rows:
        near = fleet.row(r["device"])
        for key in ("status", "candidate", "config", "ratio", "width", "gain"):
            assert r[key] == near[key], (r["device"], key)


def test_the_command_runs_a_fleet_on_a_cluster_by_address(fleet, folder, client, tmp_path,
                                                          capsys):
    """``torchhys fleet`` with fit's options (a trainer option passed to every fit), sent
    to the running cluster by its address: the rows of the library's run; an empty glob is
    one line and status 2."""
    from torchhys.cli.main import main

    args = ["fleet", "--config", str(MEASURED), "--config", str(folder / "small.yaml"),
            "--data.path", str(folder / "devices" / "unit[01].csv"), "--root",
            str(tmp_path / "runs"), "--cluster", client.scheduler.address,
            "--trainer.enable_model_summary=false", "--quiet"]
    with pytest.raises(SystemExit) as done:
        main(args)
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert "2 devices, 2 identified" in out and "fleet.csv" in out
    with (tmp_path / "runs" / "fleet_0" / "fleet.csv").open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["device"] for r in rows] == ["unit0", "unit1"]
    with fleet.csv.open(newline="") as fh:
        library = {r["device"]: r for r in csv.DictReader(fh)}
    for r in rows:
        assert (r["ratio"], r["width"], r["candidate"]) == (
            library[r["device"]]["ratio"], library[r["device"]]["width"],
            library[r["device"]]["candidate"])
    with pytest.raises(SystemExit) as bad:
        main(["fleet", "--data.path", str(tmp_path / "none*.csv")])
    assert bad.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("torchhys fleet: error: data.path") and "matches no file" in err[-1]


@pytest.mark.slow
def test_the_benchmark_quick_mode_flags_the_faulty_unit_only():
    """benchmarks/fleet.py --quick: 7 simulated devices, the local cluster's rows equal to
    the serial run's, the one faulty unit flagged and no good one."""
    from benchmarks.fleet import main as bench

    (row,) = bench(["--quick"])
    assert row["devices"] == 7 and row["failed"] == 0 and row["identical"] == "yes"
    assert row["faulty_flagged"] == 1.0 and row["good_flagged"] == 0.0
    assert row["cluster_s"] > 0 and row["serial_s"] > 0


def test_one_file_with_a_device_column_is_a_fleet(fleet, folder, client, tmp_path):
    """The rows of unit0 and unit1 in one file with a ``serial`` column: each device split
    into the fleet's folder and identified as its own file was (the same numbers)."""
    lines = ["serial,time,command,response"]
    for name in ("unit0", "unit1"):
        with (folder / "devices" / f"{name}.csv").open() as fh:
            lines += [f"{name},{row.strip()}" for row in list(fh)[1:]]
    (tmp_path / "all.csv").write_text("\n".join(lines) + "\n")
    result = identify_fleet(str(tmp_path / "all.csv"), device_column="serial",
                            config=_configs(folder), root=tmp_path / "runs", cluster=client,
                            say=lambda s: None)
    assert [r["device"] for r in result.rows] == ["unit0", "unit1"]
    assert (result.folder / "_data" / "unit0.csv").is_file()
    for r in result.rows:
        near = fleet.row(r["device"])
        assert (r["candidate"], r["ratio"], r["width"], r["gain"]) == (
            near["candidate"], near["ratio"], near["width"], near["gain"])


def test_the_local_cluster_s_workers_run_without_dask_s_profiler(client):
    """The local cluster's workers keep no profile of their tasks' stacks (a tree per second
    of work, for 1000 s: it grew a worker by about 2.4 MiB a device fitted)."""
    def profiler(dask_worker):
        import dask

        return ("profile" in dask_worker.periodic_callbacks,
                dask.config.get("distributed.worker.profile.enabled"))

    assert list(client.run(profiler).values()) == [(False, False)] * 2


@pytest.mark.slow
def test_a_device_that_does_not_finish_is_reported_within_the_device_timeout(folder, tmp_path):
    """A plugin that sleeps when imported stands in for a fit that hangs: past
    ``device_timeout`` the device is cancelled and is a failed row saying so; the fleet's
    report is still written."""
    (tmp_path / "hang.py").write_text("import time\ntime.sleep(60)\n")
    start = time.perf_counter()
    with connect(None, workers=1, retries=0) as own:  # its own: the sleeping worker dies with it
        result = identify_fleet({"unit0": str(folder / "devices" / "unit0.csv")},
                                config=_configs(folder), root=tmp_path / "runs", cluster=own,
                                args=["--import-path", str(tmp_path), "--import", "hang"],
                                device_timeout=3.0, say=lambda s: None)
    assert time.perf_counter() - start < 45
    (row,) = result.rows
    assert row["status"] == "failed"
    assert row["reason"].startswith("no device finished within 3 s")
    assert "--device-timeout" in row["reason"]
    assert result.csv.exists()


def test_the_device_timeout_is_checked_and_read_from_the_command_line(folder, tmp_path):
    with pytest.raises(ValueError, match="device_timeout must be a number of seconds > 0"):
        identify_fleet({"unit0": str(folder / "devices" / "unit0.csv")}, root=tmp_path,
                       device_timeout=0, say=lambda s: None)
    options, _, _ = split_fleet_options(["--data.path", "x", "--device-timeout", "30"])
    assert options["device_timeout"] == 30.0
