"""Faults of checkpoints and signals: a checkpoint named by a URL is refused in one line and
nothing from it runs; every loader of checkpoints reads local files with
``weights_only=True``; SIGTERM ends a fit with a non-zero status after ``last.ckpt``;
``--ckpt_path last`` resumes the newest earlier run; the processes of ``model.select_jobs``
die with the command (SIGTERM, SIGKILL) and Ctrl-C during model selection is one line."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from _training_helpers import DROP, small_config

from torchhys.checkpoints import CheckpointError, read_checkpoint
from torchhys.cli.export import main as export_main
from torchhys.cli.main import main
from torchhys.training.checkpoint_io import AtomicCheckpointIO

ROOT = Path(__file__).resolve().parents[1]

TINY = {"trainer": {"max_epochs": 1},
        "model": {"operator": None, "operator_kwargs": DROP, "hidden": 2,
                  "optimizer_kwargs": DROP}}
"""The sections of :func:`small_config` for a plain network of 2 sigmoids, one epoch."""


class _Payload:
    """An object whose unpickling creates the folder ``marker``: loaded with
    ``weights_only=False``, the file runs code."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):  # noqa: ANN204 (pickle's protocol)
        return os.mkdir, (self.marker,)


@pytest.fixture
def evil(tmp_path: Path) -> tuple[Path, Path]:
    """A checkpoint-shaped file holding a payload, and the marker the payload would make."""
    marker = tmp_path / "payload-ran"
    path = tmp_path / "evil.ckpt"
    torch.save({"state_dict": {}, "x": _Payload(marker)}, path)
    return path, marker


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    return small_config(tmp_path, "tiny.yaml", **TINY)


def _one_line(capsys, prog: str, *names: str) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert lines and lines[-1].startswith(f"{prog}: error: "), err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    for name in names:
        assert name in lines[-1], lines[-1]
    return lines[-1]


# --- 1. checkpoints from URLs ---------------------------------------------------------------
@pytest.mark.parametrize("sub", ["fit", "test", "validate", "predict"])
def test_ckpt_path_url_is_refused_in_one_line(monkeypatch, capsys, tmp_path, tiny,
                                              sub) -> None:
    """Nothing listens on port 1: a download attempt would fail with a traceback."""
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    url = "http://127.0.0.1:1/evil.ckpt"
    with pytest.raises(SystemExit) as exc:
        main([sub, "--config", str(tiny), "--trainer.default_root_dir=run",
              f"--ckpt_path={url}"])
    assert exc.value.code == 2
    line = _one_line(capsys, f"torchhys {sub}", url, "URL", "local file")
    assert "download" in line
    assert not (tmp_path / "run").exists()  # refused before anything is written


def test_file_url_is_refused_and_runs_nothing(monkeypatch, capsys, tmp_path, tiny,
                                              evil) -> None:
    path, marker = evil
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    url = f"file://{path}"
    with pytest.raises(SystemExit) as exc:
        main(["test", "--config", str(tiny), "--trainer.default_root_dir=run",
              f"--ckpt_path={url}"])
    assert exc.value.code == 2
    _one_line(capsys, "torchhys test", url, "URL")
    assert not marker.exists()


def test_registry_ckpt_path_is_refused(monkeypatch, capsys, tmp_path, tiny) -> None:
    """Lightning's ``registry:`` values download a model: refused as a URL is."""
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["test", "--config", str(tiny), "--ckpt_path=registry:some/model"])
    assert exc.value.code == 2
    _one_line(capsys, "torchhys test", "registry:some/model", "local file")


@pytest.mark.parametrize("url", ["http://127.0.0.1:1/evil.ckpt", "https://h/x.ckpt",
                                 "s3://bucket/x.ckpt"])
def test_export_ckpt_url_is_refused(capsys, tmp_path, url) -> None:
    rc = export_main(["--ckpt", url, "--format", "torchscript", "--out",
                      str(tmp_path / "m.pt")])
    assert rc == 2
    _one_line(capsys, "torchhys export", "URL", "local file")
    assert not list(tmp_path.iterdir())


def test_read_checkpoint_refuses_urls_and_runs_nothing(evil) -> None:
    path, marker = evil
    for url in (f"file://{path}", Path(f"file://{path}"), "http://127.0.0.1:1/evil.ckpt"):
        with pytest.raises(CheckpointError, match="URL"):
            read_checkpoint(url, "--ckpt")
    with pytest.raises(CheckpointError, match="holds objects other than tensors"):
        read_checkpoint(path, "--ckpt")  # the local file: refused, not run
    assert not marker.exists()


def test_checkpoint_io_loads_local_files_with_weights_only(evil) -> None:
    """The trainer plugin of ``torchhys`` (Lightning's second read of ``--ckpt_path``, and
    ``best``/``hpc``): a URL is refused and ``weights_only=False`` does not run the file."""
    path, marker = evil
    io = AtomicCheckpointIO()
    with pytest.raises(CheckpointError, match="URL"):
        io.load_checkpoint("http://127.0.0.1:1/evil.ckpt")
    with pytest.raises(CheckpointError, match="URL"):
        io.load_checkpoint(f"file://{path}", weights_only=False)
    with pytest.raises(Exception, match="(?i)weights.only"):
        io.load_checkpoint(path, weights_only=False)
    assert not marker.exists()
    good = path.parent / "good.ckpt"
    torch.save({"state_dict": {"w": torch.ones(2)}, "epoch": 3}, good)
    assert io.load_checkpoint(good)["epoch"] == 3


# --- 6. --ckpt_path last ---------------------------------------------------------------------
def test_ckpt_path_last_without_an_earlier_run_is_one_line(monkeypatch, capsys, tmp_path,
                                                          tiny) -> None:
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(["fit", "--config", str(tiny), "--trainer.default_root_dir=run",
              "--ckpt_path=last"])
    assert exc.value.code == 2
    _one_line(capsys, "torchhys fit", "--ckpt_path last", "no earlier run's last.ckpt",
              "version_*")
    assert not (tmp_path / "run").exists()


def test_ckpt_path_last_resumes_the_newest_earlier_run(monkeypatch, tmp_path, tiny) -> None:
    monkeypatch.setenv("TORCHHYS_TRACEBACK", "1")
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    monkeypatch.chdir(tmp_path)
    fit = ["fit", "--config", str(tiny), "--trainer.default_root_dir=run"]
    main(fit)  # version_0: epoch 0
    main([*fit, "--trainer.max_epochs=2", "--ckpt_path=last"])  # version_1: epoch 1
    main([*fit, "--trainer.max_epochs=3", "--ckpt_path=last"])  # version_2: epoch 2
    logs = tmp_path / "run" / "logs"
    for v in (1, 2):
        first = (logs / f"version_{v}" / "metrics.csv").read_text().splitlines()[1]
        assert first.split(",")[0] == str(v), (v, first)  # the epoch after the resumed one
        saved = torch.load(logs / f"version_{v}" / "checkpoints" / "last.ckpt",
                           weights_only=True)
        assert saved["epoch"] == v


# --- 6. signals --------------------------------------------------------------------------------
FOREVER = {**TINY, "trainer": {"max_epochs": 1000000}}
"""TINY training until a signal stops it."""

SELECT = {**FOREVER, "model": {**TINY["model"], "select": [{"hidden": 2}, {"hidden": 3}],
                               "select_jobs": 2}}
"""Two candidates of FOREVER, in two processes."""


_ERR: dict[int, Path] = {}
"""The file of each spawned command's stderr, by its process id."""


def _spawn(tmp_path: Path, config: dict, *extra: str, session: bool = False
           ) -> subprocess.Popen:
    path = small_config(tmp_path, "c.yaml", **config)
    env = {k: v for k, v in os.environ.items() if k != "TORCHHYS_TRACEBACK"}
    env.update(OMP_NUM_THREADS="1", PYTHONWARNINGS="ignore")
    # a file, not a pipe: orphaned workers would hold a pipe open after the command ends
    with (tmp_path / "stderr.txt").open("wb") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "torchhys", "fit", "--config", str(path),
             f"--trainer.default_root_dir={tmp_path / 'run'}", *extra],
            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=err,
            start_new_session=session)
    _ERR[proc.pid] = tmp_path / "stderr.txt"
    return proc


def _until(condition, proc: subprocess.Popen, what: str, timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if proc.poll() is not None:
            pytest.fail(f"ended ({proc.returncode}) before {what}:\n{_stderr(proc)}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"no {what} within {timeout} s")
        time.sleep(0.05)


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, ended but not yet reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


def _children(pid: int) -> list[int]:
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid and fields[0] != "Z":
            found.append(int(stat.parent.name))
    return found


def _stderr(proc: subprocess.Popen) -> str:
    return _ERR[proc.pid].read_text(errors="replace")


def _finish(proc: subprocess.Popen, timeout: float = 60) -> tuple[int, str]:
    try:
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        pytest.fail(f"still running {timeout} s after the signal:\n{_stderr(proc)[-3000:]}")
    return proc.returncode, _stderr(proc)


def test_sigterm_ends_a_fit_with_143_after_saving_last_ckpt(monkeypatch, tmp_path) -> None:
    """Checkpoints every 10**6 epochs: Lightning alone would save none at a SIGTERM (and end
    with status 0); the run saves last.ckpt, says so, and resumes from it."""
    proc = _spawn(tmp_path, FOREVER, "--checkpoint.every_n_epochs=1000000")
    config = tmp_path / "run" / "logs" / "version_0" / "config.yaml"
    _until(config.exists, proc, "training")
    time.sleep(1.0)  # some epochs
    proc.send_signal(signal.SIGTERM)
    rc, err = _finish(proc)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 128 + signal.SIGTERM, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    trained = config.parent.joinpath("metrics.csv").read_text().splitlines()[1:]
    n = int(trained[-1].split(",")[0]) + 1  # epochs 0 .. n-1 trained
    assert lines[-1] == (f"torchhys fit: interrupted by SIGTERM after {n} epochs; last.ckpt "
                         f"saved in {config.parent / 'checkpoints'} (resume: --ckpt_path "
                         "last)"), lines[-1]
    saved = torch.load(config.parent / "checkpoints" / "last.ckpt", weights_only=True)
    assert saved["global_step"] == n  # one full batch per epoch: saved as the run stopped
    # resumed: the next run trains from epoch n, none repeated or skipped
    monkeypatch.setenv("TORCHHYS_TRACEBACK", "1")
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    main(["fit", "--config", str(tmp_path / "c.yaml"),
          f"--trainer.default_root_dir={tmp_path / 'run'}", "--ckpt_path=last",
          f"--trainer.max_epochs={n + 1}"])
    metrics = (tmp_path / "run" / "logs" / "version_1" / "metrics.csv").read_text()
    assert [r.split(",")[0] for r in metrics.splitlines()[1:]] == [str(n)], metrics[:300]


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
@pytest.mark.parametrize("how", [pytest.param("SIGTERM", marks=pytest.mark.slow), "Ctrl-C",
                                 "SIGKILL"])
def test_select_jobs_workers_end_with_the_command(tmp_path, how) -> None:
    """Two candidates training without end in two processes; a signal to the command (a
    Ctrl-C reaches its whole process group): the workers end, and but for SIGKILL the
    command says it was interrupted, in one line, with 128 + the signal's number."""
    proc = _spawn(tmp_path, SELECT, session=True)
    workers: list[int] = []
    try:
        _until(lambda: len(_children(proc.pid)) >= 2, proc, "two worker processes")
        workers = _children(proc.pid)
        time.sleep(1.0)  # the candidates are training
        if how == "Ctrl-C":
            os.killpg(proc.pid, signal.SIGINT)
        else:
            proc.send_signal(getattr(signal, how))
        rc, err = _finish(proc)
        deadline = time.monotonic() + 10
        while any(map(_alive, workers)) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(map(_alive, workers)), (how, workers)
    finally:
        if proc.poll() is None:
            proc.kill()
        for pid in workers:  # orphans, where the fault is back
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
    if how == "SIGKILL":
        assert rc == -signal.SIGKILL
        return
    signum = signal.SIGINT if how == "Ctrl-C" else signal.SIGTERM
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert rc == 128 + signum, err[-3000:]
    assert "Traceback" not in err, err[-3000:]
    assert lines[-1] == f"torchhys fit: interrupted by {signal.Signals(signum).name}", err
