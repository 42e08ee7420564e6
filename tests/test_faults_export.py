"""Faults of ``torchhys export`` and of the fits it exports: an output over its own
checkpoint, over an existing file, into a folder or a read-only folder, a disk that fills up
while the files are written (the previous good output survives), negative numbers in
scientific notation, non-finite weights (refused by export; a fit that diverges stops),
data whose normalization is not finite, and a crafted checkpoint whose hyperparameters ask
for a huge network."""

from __future__ import annotations

import builtins
import errno
import json
import os
from pathlib import Path

import pytest
import torch

from torchhys import InverseHysteresisNet
from torchhys.cli.export import main as export_main
from torchhys.deploy.c import to_c
from torchhys.deploy.export import load_torchscript, to_torchscript

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


@pytest.mark.parametrize("fmt", ["torchscript", pytest.param("onnx", marks=pytest.mark.slow)])
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


# ------------------------------------------------------------------------------------------
# 4. a diverged fit stops; data whose normalization is not finite are refused; export
#    refuses non-finite weights
# ------------------------------------------------------------------------------------------

def tiny(tmp_path: Path, precision: str = "64-true") -> Path:
    """The small config (tests/_training_helpers.py) with Adam, for a few epochs."""
    from _training_helpers import DROP, small_config

    return small_config(tmp_path, "tiny.yaml",
                        trainer={"precision": precision, "max_epochs": 4},
                        model={"optimizer": "adam", "optimizer_kwargs": DROP})


@pytest.mark.parametrize("precision", ["64-true", "32-true"])
def test_a_diverged_fit_stops_naming_the_epoch(tmp_path: Path, monkeypatch,
                                               precision: str) -> None:
    """``--model.lr 1e300``: the weights overflow after the first steps; the fit stops
    with one line naming the epoch and the learning rate, and saves no checkpoint."""
    from _training_helpers import cli

    from torchhys._finite import DivergedError

    cfg = tiny(tmp_path, precision)
    ckpts = tmp_path / "ckpts"
    with pytest.raises(DivergedError) as err:
        cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path}",
            f"--checkpoint.dirpath={ckpts}", "--model.lr", "1e300",
            "--model.optimizer_kwargs", "{}")
    text = str(err.value)
    assert "\n" not in text and "model.lr 1e+300" in text
    if precision == "32-true":  # beyond float32: refused before the first step
        assert "is not a finite number in the weights' float32" in text
    else:
        assert "the fit diverged in epoch " in text and "learning rate too large" in text
    # what was saved before the loss overflowed (float64: weights near 1e300) is finite
    for saved in (ckpts.glob("*.ckpt") if ckpts.exists() else []):
        state = torch.load(saved, weights_only=True)["state_dict"]
        assert all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point())


def test_a_fit_that_stays_finite_is_not_stopped(tmp_path: Path, monkeypatch) -> None:
    from _training_helpers import cli

    cfg = tiny(tmp_path)
    cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path}",
        f"--checkpoint.dirpath={tmp_path / 'ckpts'}", "--checkpoint.save_last=true")
    assert (tmp_path / "ckpts" / "last.ckpt").is_file()


def test_the_cli_reports_a_diverged_fit_in_one_line(tmp_path: Path, monkeypatch,
                                                    capsys) -> None:
    from torchhys.cli.main import main

    cfg = tiny(tmp_path)
    monkeypatch.setattr("sys.argv", ["torchhys"])
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    torch.set_num_threads(1)
    with pytest.raises(SystemExit) as exit_:
        main(["fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path}",
              "--model.optimizer", "adam", "--model.lr", "1e300",
              "--model.optimizer_kwargs", "{}"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("torchhys fit: error: the fit diverged in epoch ")
    assert not any("Traceback" in line for line in err)


def test_data_near_1e300_are_refused_when_read(tmp_path: Path) -> None:
    import numpy as np

    from torchhys.data.tables import DataFileError
    from torchhys.training import HysteresisDataModule

    t = np.linspace(0, 20, 400)
    path = tmp_path / "huge.csv"
    np.savetxt(path, np.column_stack([1e300 * np.sin(t), 0.5e300 * np.sin(t - 0.3)]),
               delimiter=",", header="response,command", comments="")
    with pytest.raises(DataFileError) as err:
        dm = HysteresisDataModule(path=str(path), min_samples=8)
        dm.setup("fit")
        dm.train_tensors()  # what a fit reads first
    text = str(err.value)
    assert "huge.csv" in text and "data.input_column 'response'" in text
    assert "not finite" in text and "\n" not in text


def test_data_beyond_float32_are_refused_by_a_float32_normalization() -> None:
    """Values float32 holds (up to 3e38) whose mean it does not (the sum overflows): the
    normalization fitted in float32 is refused before any training step."""
    from torchhys.training import InverseHysteresisModule

    module = InverseHysteresisModule(operator="zhao_tan", hidden=4)
    t = torch.linspace(0, 20, 400, dtype=torch.float64)
    x = (3e38 * (1 + torch.sin(t)) / 2)[None]
    with pytest.raises(ValueError, match="normalization fitted on the training data is not "
                                         "finite in float32"):
        module.fit_normalization(x, 0.5 * x)


def test_export_refuses_non_finite_weights(tmp_path: Path, capsys) -> None:
    net = trained()
    with torch.no_grad():
        net.hidden.weight[2, 0] = float("nan")
    ckpt = tmp_path / "nan.ckpt"
    torch.save(lightning_ckpt(net), ckpt)
    for fmt, out in (("torchscript", tmp_path / "m.pt"), ("c", tmp_path)):
        assert export(ckpt, fmt, out) == 2
        err = one_error_line(capsys)
        assert f"--ckpt {ckpt}: the weight hidden.weight (1 of 16 values) is not finite" in err
    assert not (tmp_path / "m.pt").exists() and not (tmp_path / "torchhys_comp.c").exists()


def test_export_refuses_weights_whose_output_overflows(tmp_path: Path, capsys) -> None:
    """Finite float64 weights near 1e308 (a fit stopped as it diverged): the network's
    output is infinite, the compensator would hold its initial command."""
    net = trained().double()
    with torch.no_grad():
        net.output.weight.fill_(1e308)
    ckpt = tmp_path / "big.ckpt"
    torch.save(lightning_ckpt(net), ckpt)
    assert export(ckpt, "torchscript", tmp_path / "m.pt", "--limits", "-1", "1") == 2
    err = one_error_line(capsys)
    assert "the network's output is not finite" in err and "1e+308" in err


def test_export_accepts_an_unfitted_range(tmp_path: Path, capsys) -> None:
    """The NaN of a range the network never recorded is not a diverged weight."""
    torch.manual_seed(0)
    net = InverseHysteresisNet("eiho", 4, operator_kwargs=OPERATOR_KWARGS)
    ckpt = tmp_path / "raw.ckpt"
    torch.save(lightning_ckpt(net), ckpt)
    assert export(ckpt, "torchscript", tmp_path / "m.pt", "--limits", "-1", "1") == 0


# ------------------------------------------------------------------------------------------
# 8. a crafted checkpoint's hidden: 10**9 is refused before the network is built
# ------------------------------------------------------------------------------------------


def test_a_crafted_hidden_is_refused_before_building(tmp_path: Path, monkeypatch,
                                                     capsys) -> None:
    def no_build(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("the network was built")

    ckpt = tmp_path / "crafted.ckpt"
    torch.save(lightning_ckpt(trained(), hidden=10**9), ckpt)
    assert ckpt.stat().st_size < 20_000
    monkeypatch.setattr("torchhys.cli.export.InverseHysteresisNet", no_build)
    assert export(ckpt, "torchscript", tmp_path / "m.pt") == 2
    err = one_error_line(capsys)
    assert "hidden=1000000000" in err and "GiB" in err and "do not describe its weights" in err


def test_a_plain_state_dict_with_a_huge_hidden_is_refused(tmp_path: Path, capsys) -> None:
    sd = tmp_path / "sd.pt"
    torch.save(trained().state_dict(), sd)
    assert export_main(["--ckpt", str(sd), "--format", "torchscript", "--out",
                        str(tmp_path / "m.pt"), "--hidden", str(10**9), "--operator-kwargs",
                        json.dumps(OPERATOR_KWARGS)]) == 2
    assert "hidden=1000000000" in one_error_line(capsys)


def test_a_network_over_the_memory_limit_is_refused(tmp_path: Path, monkeypatch,
                                                    capsys) -> None:
    """A checkpoint whose weights agree with its hyperparameters, under a memory limit
    smaller than the network (TORCHHYS_MAX_MEMORY)."""
    ckpt = tmp_path / "m.ckpt"
    torch.save(lightning_ckpt(trained(hidden=64)), ckpt)
    monkeypatch.setenv("TORCHHYS_MAX_MEMORY", "1K")
    assert export(ckpt, "torchscript", tmp_path / "m.pt") == 2
    err = one_error_line(capsys)
    assert "the network of hidden=64" in err and "TORCHHYS_MAX_MEMORY" in err
    monkeypatch.setenv("TORCHHYS_MAX_MEMORY", "1M")
    assert export(ckpt, "torchscript", tmp_path / "m.pt") == 0


def test_fit_reads_negative_numbers_in_scientific_notation(tmp_path: Path, monkeypatch,
                                                           capsys) -> None:
    """LightningCLI's parsers (jsonargparse, on argparse) had export's problem too."""
    from _training_helpers import cli

    cfg = tiny(tmp_path)
    with pytest.raises(SystemExit) as exit_:
        cli(monkeypatch, "fit", "--config", str(cfg), "--model.lr", "-1e-3",
            "--trainer.gradient_clip_val", "-5E-1", "--print_config")
    assert exit_.value.code in (0, None)
    out = capsys.readouterr().out
    assert "lr: -0.001" in out and "gradient_clip_val: -0.5" in out


def test_a_crafted_family_width_is_refused_before_building(tmp_path: Path, monkeypatch,
                                                           capsys) -> None:
    """``{fit: pi_nonneg, n_widths: 10**7}`` in a small file: its placeholder (150 MiB)
    over a limit of 64 MiB is refused naming the option, before anything is built."""
    ckpt = tmp_path / "crafted.ckpt"
    torch.save(lightning_ckpt(trained(), operator=[{"fit": "pi_nonneg", "n_widths": 10**7}]),
               ckpt)
    monkeypatch.setenv("TORCHHYS_MAX_MEMORY", "64M")
    assert export(ckpt, "torchscript", tmp_path / "m.pt") == 2
    err = one_error_line(capsys)
    assert "fit 'pi_nonneg': n_widths=10000000" in err and "lower n_widths" in err


def test_a_crafted_operator_size_is_one_line(tmp_path: Path, capsys) -> None:
    """``{name: state_space, n_states: 10**6}`` in a small file asks for terabytes when the
    operator is built (no estimate covers every registered operator's sizes): one line,
    not the allocator's traceback."""
    ckpt = tmp_path / "crafted.ckpt"
    torch.save(lightning_ckpt(trained(), operator=[{"name": "state_space",
                                                    "n_states": 10**6}]), ckpt)
    assert export(ckpt, "torchscript", tmp_path / "m.pt") == 2
    err = one_error_line(capsys)
    assert "cannot be built: out of memory (3.6 TiB at once)" in err and "crafted" in err
    assert not (tmp_path / "m.pt").exists()


def test_export_refuses_the_last_checkpoint_of_a_diverged_fit(tmp_path: Path, monkeypatch,
                                                              capsys) -> None:
    """``--model.lr 1e300`` in float64: last.ckpt of epoch 0 holds finite weights near
    1e300 whose output is the compensator's limit for every input; export refuses it."""
    from _training_helpers import cli

    from torchhys._finite import DivergedError

    cfg = tiny(tmp_path)
    ckpts = tmp_path / "ckpts"
    with pytest.raises(DivergedError):
        cli(monkeypatch, "fit", "--config", str(cfg), f"--trainer.default_root_dir={tmp_path}",
            f"--checkpoint.dirpath={ckpts}", "--checkpoint.save_last=true", "--model.lr",
            "1e300", "--model.optimizer_kwargs", "{}")
    last = ckpts / "last.ckpt"
    assert last.is_file()
    monkeypatch.delenv("TORCHHYS_TRACEBACK", raising=False)
    capsys.readouterr()
    assert export(last, "torchscript", tmp_path / "m.pt") == 2
    err = one_error_line(capsys)
    assert f"--ckpt {last}: the network's output" in err and "standard deviations" in err
    assert not (tmp_path / "m.pt").exists()
