"""Fault cases of the data and the configs: memory that user input would make unbounded
(a Preisach fit's n, ``data.repeat``, a YAML alias bomb, a large CSV file) refused with an
estimate or read within a bound, a data file rewritten during a fit detected, and CSV files
that look right but are not (duplicate header names, ``1_000``, a spreadsheet saved as
``.csv``, a symlink loop) refused with one line naming the file."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
import torch

from torchhys import fit_preisach
from torchhys._memory import MEMORY_ENV, memory_limit
from torchhys.data.files import read_recordings
from torchhys.data.tables import DataFileError
from torchhys.identification.specs import build_operators
from torchhys.training import HysteresisDataModule


def write_csv(path: Path, rows: int = 200, header: str = "response,command") -> Path:
    """A CSV file of a smooth loop, ``rows`` data rows under ``header``."""
    t = np.linspace(0.0, 2 * np.pi, rows)
    np.savetxt(path, np.c_[np.sin(t) + 0.1 * np.sin(3 * t), np.sin(t)], delimiter=",",
               header=header, comments="")
    return path


# ------------------------------------------------------------------------------------------
# memory estimated before allocating
# ------------------------------------------------------------------------------------------

def test_memory_limit_from_the_environment(monkeypatch) -> None:
    monkeypatch.setenv(MEMORY_ENV, "1.5G")
    assert memory_limit() == int(1.5 * 1024**3)
    monkeypatch.setenv(MEMORY_ENV, "12345")
    assert memory_limit() == 12345
    monkeypatch.setenv(MEMORY_ENV, "lots")
    with pytest.raises(ValueError, match=f"{MEMORY_ENV} must be a size"):
        memory_limit()
    monkeypatch.delenv(MEMORY_ENV)
    assert memory_limit() is None or memory_limit() > 2**20


def test_preisach_family_n_refused_before_training(monkeypatch) -> None:
    """``{fit: preisach, n: 2000}`` (2001000 relays: 10 matrices of 32 TB) is refused when the
    spec is read, with the estimate; a small n under a small limit is refused as well."""
    with pytest.raises(ValueError, match=r"fit 'preisach': n=2000 \(2001000 relays\) needs "
                                         r"about .* TiB.*lower n.*TORCHHYS_MAX_MEMORY"):
        build_operators([{"fit": "preisach", "n": 2000}], {})
    monkeypatch.setenv(MEMORY_ENV, "32M")
    with pytest.raises(ValueError, match=r"n=40 \(820 relays\).*32\.0 MiB \(TORCHHYS_MAX"):
        build_operators([{"fit": "preisach", "n": 40}], {})
    build_operators([{"fit": "preisach", "n": 20}], {})  # 210 relays: 3.5 MB


def test_fit_preisach_n_refused_before_allocating(monkeypatch) -> None:
    monkeypatch.setenv(MEMORY_ENV, "32M")
    x = torch.sin(torch.linspace(0, 6, 100, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"fit_preisach: n=40 \(820 relays\) needs about "
                                         r"51\.\d MiB, more than the memory limit 32\.0 MiB"):
        fit_preisach(x, x, n=40)
    fit_preisach(x, x, n=8)


def test_repeat_refused_with_the_estimate(monkeypatch, tmp_path) -> None:
    """``data.repeat 100000`` on 200 rows (2e7 samples) is refused at setup, before the
    sequences are built, naming the option and the samples."""
    path = write_csv(tmp_path / "d.csv")
    data = HysteresisDataModule(path=str(path), repeat=100_000)
    monkeypatch.setenv(MEMORY_ENV, "4G")
    with pytest.raises(ValueError, match=r"data\.repeat=100000 \(100000 x 200 samples\) "
                                         r"needs about 9\.5 GiB.*lower data\.repeat"):
        data.setup()
    ok = HysteresisDataModule(path=str(path), repeat=3)
    ok.setup()
    assert ok.tensors("train")[0].numel() == 600


# ------------------------------------------------------------------------------------------
# YAML with bounded aliases
# ------------------------------------------------------------------------------------------

def alias_bomb(levels: int) -> str:
    """A config whose ``model.select`` nests ``levels`` lists of nine aliases of the one
    before: 9**(levels + 1) strings from a few hundred bytes."""
    lines = ["model:", "  select:", "  - &a [" + ", ".join(['"lol"'] * 9) + "]"]
    names = "abcdefghijk"
    for k in range(1, levels + 1):
        lines.append(f"  - &{names[k]} [" + ", ".join([f"*{names[k - 1]}"] * 9) + "]")
    return "\n".join(lines) + "\n"


def test_yaml_loader_refuses_an_alias_bomb() -> None:
    """The command's YAML loader (jsonargparse's, as the command installs it) refuses 9**9
    strings of aliases, and a structure that contains itself; a bomb of 9**4 still loads."""
    from jsonargparse import get_loader

    from torchhys.cli.config_yaml import ConfigSizeError
    from torchhys.cli.train import read_config  # noqa: F401 (installs the loader)

    load = get_loader("yaml")
    with pytest.raises(ConfigSizeError, match="expands to more than 1000000 values"):
        load(alias_bomb(8))
    with pytest.raises(ConfigSizeError, match="contains itself"):
        load("a: &x [1, *x]")
    small = load(alias_bomb(3))
    assert len(small["model"]["select"][3][0][0]) == 9
    assert load("a: 1e-8") == {"a": 1e-8}  # jsonargparse's own reading of the values


def test_cli_refuses_an_alias_bomb_naming_the_file(monkeypatch, tmp_path) -> None:
    from _training_helpers import cli

    from torchhys.cli.config_yaml import ConfigSizeError

    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(alias_bomb(8))
    with pytest.raises(ConfigSizeError, match=f"--config {bomb}: the YAML expands"):
        cli(monkeypatch, "fit", "--config", str(bomb))


# ------------------------------------------------------------------------------------------
# a data file that changes during a command
# ------------------------------------------------------------------------------------------

def test_watched_file_rewritten_is_refused(tmp_path) -> None:
    """While watched, a file rewritten with other content of the same size (and a new time)
    is refused naming it; touched (same content) it reads on; unwatched it is read again."""
    from torchhys.data import files

    path = write_csv(tmp_path / "log.csv")
    text = path.read_text()
    cols = dict(input_column="response", target_column="command")
    files.watch_files()
    try:
        first = read_recordings(path, **cols)
        os.utime(path, ns=(1, 2))  # touched: same bytes, a new time
        assert np.array_equal(read_recordings(path, **cols)[0].x, first[0].x)
        path.write_text(text.replace("0.", "1.", 1))  # one digit other, same size
        os.utime(path, ns=(3, 4))
        with pytest.raises(DataFileError, match=f"{path}: the file changed after this run "
                                                r"first read it \(\d+ bytes then, \d+ now\)"):
            read_recordings(path, **cols)
    finally:
        files.watch_files(False)
    assert not np.array_equal(read_recordings(path, **cols)[0].x, first[0].x)


def test_fit_stops_when_the_data_file_grows_during_selection(monkeypatch, tmp_path) -> None:
    """A logger still appending to the file: the candidates would be scored on one version
    and the chosen one trained on another. The fit stops with an error naming the file."""
    from _training_helpers import DROP, cli, small_config

    path = write_csv(tmp_path / "log.csv", rows=120)
    from torchhys.training import data

    calls = []

    def appending(*args, **kwargs):  # the logger writes a row between two reads
        if calls:
            with path.open("a") as f:
                f.write("0.5,0.5\n")
        calls.append(1)
        return read_recordings(*args, **kwargs)

    monkeypatch.setattr(data, "read_recordings", appending)
    config = small_config(
        tmp_path, "fit.yaml", seed_everything=DROP,
        trainer={"max_epochs": 1, "check_val_every_n_epoch": DROP, "logger": False},
        model={"operator_kwargs": DROP, "hidden": 2, "optimizer_kwargs": DROP},
        data={"simulation": DROP, "t_end": DROP, "path": path})
    monkeypatch.chdir(tmp_path)
    with pytest.raises(DataFileError, match=f"{path}: the file changed after this run first"):
        cli(monkeypatch, "fit", "--config", str(config), "--model.select",
            "[{hidden: 1}, {hidden: 2}]")


def test_subnormal_column_is_constant_naming_the_file(tmp_path) -> None:
    """Values that differ only below float64's normal range have a standard deviation of 0
    (the normalization's divisor): refused as constant, naming the file and the column."""
    path = tmp_path / "tiny.csv"
    k = np.arange(40)
    np.savetxt(path, np.c_[(k % 7 + 1) * 1e-310, np.sin(k)], delimiter=",",
               header="response,command", comments="")
    data = HysteresisDataModule(path=str(path))
    data.setup()
    with pytest.raises(DataFileError, match=rf"{path}: data.input_column 'response' is constant "
                                            r"over the training split \(40 samples, 1e-310 to "
                                            r"7e-310, std 0\)"):
        data.train_tensors()


# ------------------------------------------------------------------------------------------
# CSV files that look right but are not
# ------------------------------------------------------------------------------------------

COLS = dict(input_column="response", target_column="command")


def test_duplicate_header_name_is_refused_where_it_is_used(tmp_path) -> None:
    path = tmp_path / "dup.csv"
    path.write_text("response,command,response\n" + "".join(
        f"{np.sin(k):.6f},{np.cos(k):.6f},{k}\n" for k in range(20)))
    with pytest.raises(DataFileError, match=rf"{path}: column 'response' \(input_column\) is "
                                            r"the name of 2 columns \(indices \[0, 2\]\)"):
        read_recordings(path, **COLS)
    rec, = read_recordings(path, input_column=2, target_column="command")  # by index: fine
    assert rec.x[5] == 5.0


def test_underscore_digits_are_not_a_number(tmp_path) -> None:
    """float() reads ``1_000`` as 1000; a data file's ``1_000`` is refused, row and line named."""
    path = write_csv(tmp_path / "d.csv", rows=30)
    lines = path.read_text().splitlines()
    lines[4] = "1_000," + lines[4].split(",")[1]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataFileError, match=rf"{path}: column 'response' \(input_column\), row "
                                            r"3 \(line 5\): '1_000' is not a finite number; "
                                            r"write numbers without '_'"):
        read_recordings(path, **COLS)


@pytest.mark.parametrize(("magic", "kind"), [(b"PK\x03\x04\x14\x00\x06\x00", "xlsx"),
                                             (bytes.fromhex("d0cf11e0a1b11ae1") + b"\0" * 8,
                                              "xls")])
def test_spreadsheet_saved_as_csv(tmp_path, magic: bytes, kind: str) -> None:
    """An Excel workbook renamed ``.csv`` is named a spreadsheet, not an encoding problem."""
    path = tmp_path / "book.csv"
    path.write_bytes(magic + bytes(range(256)) * 4)
    with pytest.raises(DataFileError, match=rf"{path}: the file is an \.{kind} .*spreadsheet, "
                                            r"not CSV text.*save it from the spreadsheet as CSV"):
        read_recordings(path, **COLS)


def test_symlink_loop_is_one_line(tmp_path) -> None:
    loop = tmp_path / "loop.csv"
    loop.symlink_to(loop)
    with pytest.raises(DataFileError, match=rf"{loop}: a symbolic link that leads back to "
                                            "itself"):
        read_recordings(loop, **COLS)
    other = write_csv(tmp_path / "other.csv")
    with pytest.raises(DataFileError, match=rf"{loop}: a symbolic link that leads back"):
        HysteresisDataModule(path=[str(other), str(loop)])


def test_input_column_equal_to_target_column(tmp_path) -> None:
    path = write_csv(tmp_path / "d.csv")
    with pytest.raises(ValueError, match=r"input_column \(data.input_column\) and target_column "
                                         r"\(data.target_column\) are both 'response'"):
        read_recordings(path, input_column="response", target_column="response")


def test_digits_name_a_column_as_on_the_command_line(tmp_path) -> None:
    """``--data.input_column 2`` reaches the reader as the string '2', a YAML ``2`` as the
    int: both are the column named 2 where the header has one, else the index 2."""
    plain = tmp_path / "plain.csv"
    plain.write_text("a,b,c\n" + "".join(f"{k},{k * k},{-k}\n" for k in range(20)))
    by_str, = read_recordings(plain, input_column="2", target_column="1")
    by_int, = read_recordings(plain, input_column=2, target_column=1)
    assert np.array_equal(by_str.x, by_int.x) and by_int.x[3] == -3.0
    named = tmp_path / "named.csv"
    named.write_text("2,a,b\n" + "".join(f"{k},{k * k},{-k}\n" for k in range(20)))
    by_str, = read_recordings(named, input_column="2", target_column="a")
    by_int, = read_recordings(named, input_column=2, target_column="a")
    assert np.array_equal(by_str.x, by_int.x) and by_int.x[3] == 3.0
    data = HysteresisDataModule(path=str(plain), input_column="2", target_column="1")
    data.setup()
    assert data.x[3] == -3.0


def test_csv_reader_peak_memory_is_at_most_four_times_the_file(tmp_path) -> None:
    """tracemalloc's peak (Python and numpy allocations) while a 3e4-row file is read, over
    the file's size: about 3 (the bytes and their text, then float64 columns), was 15."""
    import tracemalloc

    path = tmp_path / "big.csv"
    k = np.arange(30_000)
    np.savetxt(path, np.c_[k * 1e-3, np.sin(k * 1e-3), np.cos(k * 1e-3)], delimiter=",",
               header="time,response,command", comments="", fmt="%.9g")
    tracemalloc.start()
    try:
        rec, = read_recordings(path, time_column="time", **COLS)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert rec.x.shape == (30_000,) and rec.y[0] == 1.0
    assert peak <= 4 * path.stat().st_size, peak / path.stat().st_size


# ------------------------------------------------------------------------------------------
# 8. the widths and units of the fitted families: refused with the estimate
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("spec", [{"fit": "pi_nonneg", "n_widths": 10**7},
                                  {"fit": "gpi", "units": 10**7},
                                  {"fit": "stop_pi", "n_widths": 10**6, "segments": 10}])
def test_family_placeholder_refused_when_the_spec_is_read(monkeypatch, spec) -> None:
    """10**7 columns: a placeholder of 150 MiB, over a limit of 64 MiB."""
    monkeypatch.setenv(MEMORY_ENV, "64M")
    with pytest.raises(ValueError, match=rf"fit '{spec['fit']}': .*\(10000\d+ columns\) needs "
                                         r"about 15\d\.\d MiB.*64\.0 MiB.*lower "):
        build_operators([spec], {})


@pytest.mark.parametrize("spec, what", [
    ({"fit": "pi_nonneg", "n_widths": 1000}, "n_widths=1000 (1000 columns)"),
    ({"fit": "gpi", "n_widths": 10, "units": 1000}, "n_widths=10 + units=1000 (1010 columns)"),
    ({"fit": "stop_pi", "n_widths": 250}, "n_widths=250 x segments=4 (1000 columns)")])
def test_family_fit_refused_before_allocating(monkeypatch, spec, what) -> None:
    """About 1000 columns of 2000 samples (12 float64 copies: 183 MiB) over 64 MiB: refused
    before the width grid (the first allocation of the fit) is made."""
    def no_grid(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("the fit began")

    monkeypatch.setenv(MEMORY_ENV, "64M")
    _, fitters = build_operators([spec], {})
    home = {"pi_nonneg": "prandtl_ishlinskii", "gpi": "generalized_pi", "stop_pi": "stop_pi"}
    monkeypatch.setattr(f"torchhys.identification.{home[spec['fit']]}.play_width_grid", no_grid)
    x = torch.sin(torch.linspace(0, 20, 2000, dtype=torch.float64))[None]
    with pytest.raises(ValueError, match=rf"fit '{spec['fit']}': {re.escape(what)} fitted on "
                                         r"2000 samples needs about 18\d\.\d MiB"):
        fitters[0](x, 0.5 * x, 0)
