"""Faults of ``torchhys export`` and of the fits it exports: an output over its own
checkpoint, over an existing file, into a folder or a read-only folder, a disk that fills up
while the files are written (the previous good output survives), negative numbers in
scientific notation, non-finite weights (refused by export; a fit that diverges stops),
data whose normalization is not finite, and a crafted checkpoint whose hyperparameters ask
for a huge network."""

from __future__ import annotations

import builtins
import errno
import os
from pathlib import Path

import pytest
import torch

from torchhys import InverseHysteresisNet
from torchhys.deploy.export import load_torchscript, to_torchscript
from torchhys.deploy.export_c import to_c
from torchhys.training.export_cmd import main as export_main

OPERATOR_KWARGS = {"a": 1.3, "rule": "dominant", "threshold": 0.1}


def trained(hidden: int = 8) -> InverseHysteresisNet:
    torch.manual_seed(0)
    net = InverseHysteresisNet("eiho", hidden, operator_kwargs=OPERATOR_KWARGS)
    x = 3 * torch.sin(torch.linspace(0, 20, 400))
    net.fit_normalization(x, 0.5 * x)
    return net


def lightning_ckpt(net: InverseHysteresisNet, **hp: object) -> dict:
    state = {f"net.{k}": v for k, v in net.state_dict().items()}
    state["normalization_fitted"] = torch.tensor(True)
    hparams = {"operator": "eiho", "hidden": net.hidden.out_features, "activation": "sigmoid",
               "operator_kwargs": OPERATOR_KWARGS, "optimizer": "cg", **hp}
    return {"state_dict": state, "hyper_parameters": hparams, "epoch": 3}


@pytest.fixture
def ckpt(tmp_path: Path) -> Path:
    path = tmp_path / "m.ckpt"
    torch.save(lightning_ckpt(trained()), path)
    return path


def export(ckpt: Path, fmt: str, out: Path, *more: str) -> int:
    return export_main(["--ckpt", str(ckpt), "--format", fmt, "--out", str(out), *more])


def one_error_line(capsys: pytest.CaptureFixture) -> str:
    """The export's stderr: exactly one line, ``torchhys export: error: ...``."""
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    assert err.startswith("torchhys export: error: "), err
    return err


def partial_files(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name.endswith(".partial")]


# ------------------------------------------------------------------------------------------
# 5. the export never destroys a file: not its checkpoint, not an existing output
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["torchscript", "onnx", "aoti"])
def test_out_equal_to_ckpt_is_refused(ckpt: Path, capsys, fmt: str) -> None:
    before = ckpt.read_bytes()
    assert export(ckpt, fmt, ckpt, "--force") == 2
    assert "is the --ckpt file itself" in one_error_line(capsys)
    assert ckpt.read_bytes() == before


def test_out_through_a_link_to_ckpt_is_refused(ckpt: Path, tmp_path: Path, capsys) -> None:
    """The same file by another name (a symbolic and a hard link) is the same file."""
    before = ckpt.read_bytes()
    (tmp_path / "sym.pt").symlink_to(ckpt)
    os.link(ckpt, tmp_path / "hard.pt")
    for name in ("sym.pt", "hard.pt"):
        assert export(ckpt, "torchscript", tmp_path / name, "--force") == 2
        assert "is the --ckpt file itself" in one_error_line(capsys)
    assert ckpt.read_bytes() == before


def test_c_out_over_ckpt_is_refused(tmp_path: Path, capsys) -> None:
    """--format c into the checkpoint's folder with a --prefix that names it."""
    ckpt = tmp_path / "comp.c"
    torch.save(lightning_ckpt(trained()), ckpt)
    before = ckpt.read_bytes()
    assert export(ckpt, "c", tmp_path, "--prefix", "comp", "--force") == 2
    assert "is the --ckpt file itself" in one_error_line(capsys)
    assert ckpt.read_bytes() == before and not (tmp_path / "comp.h").exists()


@pytest.mark.parametrize("fmt", ["torchscript", "onnx", "aoti"])
def test_an_existing_output_is_replaced_only_with_force(ckpt: Path, tmp_path: Path, capsys,
                                                        fmt: str) -> None:
    out = tmp_path / {"torchscript": "m.pt", "onnx": "m.onnx", "aoti": "m.pt2"}[fmt]
    out.write_bytes(b"a previous export")
    assert export(ckpt, fmt, out) == 2
    err = one_error_line(capsys)
    assert f"--out {out} exists" in err and "--force" in err
    assert out.read_bytes() == b"a previous export"


def test_force_replaces_an_existing_output(ckpt: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "m.pt"
    out.write_bytes(b"a previous export")
    assert export(ckpt, "torchscript", out, "--force") == 0
    assert "wrote" in capsys.readouterr().out
    load_torchscript(out)
    assert partial_files(tmp_path) == []


def test_an_existing_c_pair_is_replaced_only_with_force(ckpt: Path, tmp_path: Path,
                                                        capsys) -> None:
    out = tmp_path / "gen"
    out.mkdir()
    (out / "torchhys_comp.c").write_text("/* a previous export */\n")
    assert export(ckpt, "c", out) == 2
    err = one_error_line(capsys)
    assert "torchhys_comp.c exists" in err and "--force" in err
    assert not (out / "torchhys_comp.h").exists()
    assert export(ckpt, "c", out, "--force") == 0
    assert "torchhys_comp_step" in (out / "torchhys_comp.c").read_text()


class FullDisk:
    """No room left on the disk under ``root``: a file opened there for writing with
    ``open()`` takes ``room`` bytes, then its write stores what fits and raises
    ``OSError(ENOSPC)``."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, root: Path, room: int = 100) -> None:
        self.root, self.room, self.failed = os.path.realpath(root), room, 0
        real_open = builtins.open
        disk = self

        class File:
            def __init__(self, f) -> None:  # noqa: ANN001 (a file)
                self._f = f

            def write(self, data) -> int:  # noqa: ANN001 (bytes-like)
                size = memoryview(data).nbytes if not isinstance(data, str) else len(data)
                if size <= disk.room:
                    disk.room -= size
                    return self._f.write(data)
                self._f.write(data[:disk.room])
                disk.room, disk.failed = 0, disk.failed + 1
                raise OSError(errno.ENOSPC, "No space left on device")

            def __getattr__(self, name: str):  # noqa: ANN204
                return getattr(self._f, name)

            def __enter__(self):  # noqa: ANN204
                return self

            def __exit__(self, *exc: object) -> None:
                self._f.close()

        def limited_open(file, mode="r", *args, **kwargs):  # noqa: ANN001, ANN202 (open's)
            f = real_open(file, mode, *args, **kwargs)
            if (isinstance(file, str | os.PathLike) and set(mode) & set("wax+")
                    and os.path.realpath(file).startswith(self.root + os.sep)):
                return File(f)
            return f

        monkeypatch.setattr(builtins, "open", limited_open)


@pytest.mark.parametrize("fmt", ["torchscript", "onnx"])
def test_full_disk_keeps_the_previous_file(ckpt: Path, tmp_path: Path, monkeypatch, capsys,
                                           fmt: str) -> None:
    if fmt == "onnx":
        pytest.importorskip("onnxscript", reason="the onnx extra (pip install 'torchhys[onnx]')")
    out = tmp_path / "out" / f"m.{'pt' if fmt == 'torchscript' else 'onnx'}"
    out.parent.mkdir()
    assert export(ckpt, fmt, out) == 0
    before = out.read_bytes()
    capsys.readouterr()
    disk = FullDisk(monkeypatch, out.parent)
    assert export(ckpt, fmt, out, "--force", "--limits", "-1", "1") == 2
    err = one_error_line(capsys)
    assert disk.failed == 1 and str(out) in err and "No space left on device" in err
    assert out.read_bytes() == before and partial_files(out.parent) == []


def test_full_disk_keeps_the_previous_c_pair(ckpt: Path, tmp_path: Path, monkeypatch,
                                             capsys) -> None:
    """The disk fills up while the second file (.c) is written: neither file of the
    previous pair is replaced or removed."""
    out = tmp_path / "gen"
    out.mkdir()
    assert export(ckpt, "c", out) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    capsys.readouterr()
    disk = FullDisk(monkeypatch, out, room=len(before["torchhys_comp.h"]) + 100)
    assert export(ckpt, "c", out, "--force", "--limits", "-1", "1") == 2
    err = one_error_line(capsys)
    assert disk.failed == 1 and "No space left on device" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_full_disk_python_api_keeps_the_previous_files(tmp_path: Path, monkeypatch) -> None:
    net = trained()
    path = tmp_path / "m.pt"
    to_torchscript(net, path)
    h, c = to_c(net, tmp_path)
    before = {p: p.read_bytes() for p in (path, h, c)}
    FullDisk(monkeypatch, tmp_path)
    with pytest.raises(OSError) as err:
        to_torchscript(net, path, limits=(-1.0, 1.0))
    assert err.value.errno == errno.ENOSPC and err.value.filename == str(path)
    with pytest.raises(OSError):
        to_c(net, tmp_path, limits=(-1.0, 1.0))
    assert {p: p.read_bytes() for p in before} == before
    assert partial_files(tmp_path) == []


# ------------------------------------------------------------------------------------------
# 10. the output path is checked before anything is compiled; negative scientific numbers
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["torchscript", "onnx", "aoti"])
def test_out_an_existing_folder_is_one_line(ckpt: Path, tmp_path: Path, monkeypatch, capsys,
                                            fmt: str) -> None:
    def no_compile(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("compiled before the output path was checked")

    monkeypatch.setattr(torch.export, "export", no_compile)
    monkeypatch.setattr(torch.jit, "script", no_compile)
    folder = tmp_path / "a_folder"
    folder.mkdir()
    assert export(ckpt, fmt, folder) == 2
    assert f"--out {folder} is a folder" in one_error_line(capsys)


@pytest.mark.parametrize("fmt", ["torchscript", "aoti", "c"])
def test_out_a_read_only_folder_is_one_line(ckpt: Path, tmp_path: Path, monkeypatch, capsys,
                                            fmt: str) -> None:
    """A folder the process cannot write to (as root the permission bits do not stop a
    write, so ``os.access`` answers as it would for a user)."""
    def no_compile(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("compiled before the output path was checked")

    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o555)
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, *a, **k: (
        False if os.path.realpath(p) == str(folder.resolve()) and mode & os.W_OK
        else real_access(p, mode, *a, **k)))
    monkeypatch.setattr(torch.export, "export", no_compile)
    monkeypatch.setattr(torch.jit, "script", no_compile)
    out = folder if fmt == "c" else folder / ("m.pt2" if fmt == "aoti" else "m.pt")
    try:
        assert export(ckpt, fmt, out) == 2
    finally:
        folder.chmod(0o755)
    assert f"the folder {folder} is not writable" in one_error_line(capsys)
    assert list(folder.iterdir()) == []


@pytest.mark.parametrize("limits, initial", [
    (["-5e-3", "5e-3"], "-1e-3"), (["-5E-3", "5.0e-3"], "-1.5e-3"),
    (["-.005", "0.005"], "-1e-3"),
])
def test_negative_numbers_in_scientific_notation(ckpt: Path, tmp_path: Path, capsys,
                                                 limits: list[str], initial: str) -> None:
    out = tmp_path / "m.pt"
    assert export(ckpt, "torchscript", out, "--limits", *limits,
                  "--initial-command", initial) == 0
    assert "command limits [-0.005, 0.005]" in capsys.readouterr().out
    m = load_torchscript(out)
    assert float(m.torchhys_metadata["low"]) == pytest.approx(-0.005, rel=1e-6)  # float32
    # the first sample NaN: the initial command is held
    assert float(m(torch.tensor([float("nan")]))[0]) == pytest.approx(float(initial))


def test_negative_margin_is_still_refused(ckpt: Path, tmp_path: Path, capsys) -> None:
    """A negative number is read as a value, then the option's own check refuses it."""
    with pytest.raises(SystemExit):
        export(ckpt, "torchscript", tmp_path / "m.pt", "--input-margin", "-1e-2")
    assert "expected a finite number >= 0" in capsys.readouterr().err
