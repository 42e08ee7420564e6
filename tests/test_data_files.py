"""Data files as people write them: encodings, delimiters, decimal commas, blank lines,
ragged rows, constant columns, and the options ``encoding``, ``delimiter``, ``decimal``."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from torchhys.data.files import read_record, read_recordings
from torchhys.data.tables import DataFileError
from torchhys.training import HysteresisDataModule

N = 24
TIME = np.round(np.arange(N) * 0.01, 2)
COMMAND = np.round(np.sin(3 * np.arange(N) * 0.1), 6)
RESPONSE = np.round(0.9 * COMMAND + 0.05, 6)
COLS = dict(input_column="response", target_column="command", time_column="time")


def lines(header: str = "time,command,response", sep: str = ",", decimal: str = ".",
          response: np.ndarray = RESPONSE) -> list[str]:
    """The text lines of a file of TIME, COMMAND and ``response``."""
    def fmt(v: float) -> str:
        return repr(float(v)).replace(".", decimal)

    rows = [sep.join(fmt(v) for v in r) for r in zip(TIME, COMMAND, response, strict=True)]
    return [header.replace(",", sep)] + rows


def write(path: Path, text: str | bytes) -> Path:
    if isinstance(text, str):
        path.write_bytes(text.encode("utf-8"))
    else:
        path.write_bytes(text)
    return path


def check_values(rec, response: np.ndarray = RESPONSE) -> None:
    np.testing.assert_array_equal(rec.t, TIME)
    np.testing.assert_array_equal(rec.y, COMMAND)
    np.testing.assert_array_equal(rec.x, response)


def test_utf8_byte_order_mark_is_read_as_utf8(tmp_path: Path) -> None:
    """Excel's "CSV UTF-8" starts with a byte-order mark; the first column keeps its name."""
    path = write(tmp_path / "excel.csv", b"\xef\xbb\xbf" + "\r\n".join(lines()).encode())
    check_values(read_record(path, **COLS))
    (rec,) = read_recordings(path, **COLS)
    check_values(rec)
    # given as utf-8, the mark is dropped too
    check_values(read_record(path, encoding="utf-8", **COLS))


def test_latin1_file_names_the_byte_and_the_encoding_to_try(tmp_path: Path) -> None:
    header = "time,command,response_\xb5m"  # 'µm' in Latin-1 is the single byte 0xb5
    path = write(tmp_path / "latin.csv", "\n".join(lines(header)).encode("latin-1"))
    cols = dict(COLS, input_column="response_µm")
    with pytest.raises(DataFileError) as err:
        read_record(path, **cols)
    msg = str(err.value)
    byte = header.encode("latin-1").index(b"\xb5")
    assert msg.startswith(f"{path}: byte {byte} (line 1) is b'\\xb5'")
    assert "not UTF-8" in msg and "encoding='latin-1'" in msg and "data.encoding: latin-1" in msg
    assert "cp1252" in msg and "\n" not in msg
    check_values(read_record(path, encoding="latin-1", **cols))
    check_values(read_record(path, encoding="cp1252", **cols))


def test_latin1_through_the_data_module(tmp_path: Path) -> None:
    path = write(tmp_path / "latin.csv",
                 "\n".join(lines("time,command,r\xe9ponse")).encode("latin-1"))
    cols = dict(COLS, input_column="réponse")
    with pytest.raises(DataFileError, match=r"latin\.csv: byte 14 \(line 1\) is b'\\xe9'"):
        HysteresisDataModule(path=str(path), min_samples=8, **cols).setup("fit")
    dm = HysteresisDataModule(path=str(path), min_samples=8, encoding="latin-1", **cols)
    dm.setup("fit")
    np.testing.assert_array_equal(dm.x.numpy(), RESPONSE)
    np.testing.assert_array_equal(dm.y.numpy(), COMMAND)


def test_utf16_file_is_pointed_to_utf16(tmp_path: Path) -> None:
    path = write(tmp_path / "unicode.csv", "\n".join(lines()).encode("utf-16"))
    with pytest.raises(DataFileError, match=r"UTF-16 byte-order mark: set encoding='utf-16'"):
        read_record(path, **COLS)
    check_values(read_record(path, encoding="utf-16", **COLS))


@pytest.mark.parametrize("tail", ["\n\n\n", "\r\n\r\n", "\n   \n\t\n", "\n,,\n,  ,\n"])
def test_blank_lines_are_skipped(tmp_path: Path, tail: str) -> None:
    text = lines()
    text.insert(5, "")  # a blank line inside the data too
    text.insert(9, ",,")
    path = write(tmp_path / "blank.csv", "\n".join(text) + tail)
    check_values(read_record(path, **COLS))


def test_lines_after_blank_lines_keep_their_line_numbers(tmp_path: Path) -> None:
    text = ["# a comment", ""] + lines()
    text.insert(5, "")
    text[9] = text[9].rsplit(",", 1)[0] + ",oops"  # data row 5, line 10
    path = write(tmp_path / "bad.csv", "\n".join(text) + "\n")
    with pytest.raises(DataFileError, match=r"column 'response' \(input_column\), row 5 "
                                            r"\(line 10\): 'oops' is not a finite number"):
        read_record(path, **COLS)


@pytest.mark.parametrize("sep, name", [(";", "semicolon"), ("\t", "tab")])
def test_delimiter_is_sniffed(tmp_path: Path, sep: str, name: str) -> None:
    path = write(tmp_path / f"{name}.csv", "\n".join(lines(sep=sep)) + "\n")
    check_values(read_record(path, **COLS))
    check_values(read_record(path, delimiter=sep, **COLS))


def test_sniffing_prefers_a_consistent_delimiter(tmp_path: Path) -> None:
    """Commas inside a ';' file's header do not make it a ',' file, and ',' wins a tie."""
    text = lines(sep=";")
    text[0] = "time [s];command, V;response, um"
    path = write(tmp_path / "units.csv", "\n".join(text) + "\n")
    rec = read_record(path, input_column="response, um", target_column="command, V",
                      time_column="time [s]")
    check_values(rec)
    path = write(tmp_path / "both.csv", "a;b,c;d\n1;2,3;4\n")  # ',': 2 fields, ';': 3
    with pytest.raises(DataFileError, match=r"the file's columns are \['a;b', 'c;d'\]"):
        read_record(path, input_column="a", target_column="d", min_samples=1)


def test_delimiter_option(tmp_path: Path) -> None:
    path = write(tmp_path / "pipe.csv", "\n".join(lines(sep="|")) + "\n")
    check_values(read_record(path, delimiter="|", **COLS))
    tabs = write(tmp_path / "tabs.csv", "\n".join(lines(sep="\t")) + "\n")
    for spelling in ("\t", "tab", "\\t"):
        check_values(read_record(tabs, delimiter=spelling, **COLS))


@pytest.mark.parametrize("sep", [";", "\t"])
def test_decimal_commas(tmp_path: Path, sep: str) -> None:
    path = write(tmp_path / "komma.csv", "\n".join(lines(sep=sep, decimal=",")) + "\n")
    assert "0,05" in path.read_text()
    check_values(read_record(path, decimal=",", **COLS))
    dm = HysteresisDataModule(path=str(path), decimal=",", min_samples=8, **COLS)
    dm.setup("fit")
    np.testing.assert_array_equal(dm.x.numpy(), RESPONSE)
    np.testing.assert_array_equal(dm.t.numpy(), TIME)


def test_decimal_commas_without_the_option_hint_at_it(tmp_path: Path) -> None:
    """With ';' the numbers are fields of their own: '0,05' is not a number."""
    path = write(tmp_path / "komma.csv", "\n".join(lines(sep=";", decimal=",")) + "\n")
    with pytest.raises(DataFileError, match=r"row 0 \(line 2\): '0,05' is not a finite "
                                            r"number; .*decimal commas: set decimal=','"):
        read_record(path, **COLS)


def test_decimal_commas_split_by_commas_name_line_and_counts(tmp_path: Path) -> None:
    """A file written with ',' both between the fields and in the numbers."""
    path = write(tmp_path / "mixed.csv", "\n".join(lines(sep=",", decimal=",")) + "\n")
    with pytest.raises(DataFileError) as err:
        read_record(path, **COLS)
    msg = str(err.value)
    assert msg.startswith(f"{path}: line 2: expected 3 fields as the header, got 6")
    assert "decimal commas" in msg and "data.decimal: ','" in msg and "';'" in msg
    with pytest.raises(DataFileError, match=r"separated by ',', which decimal=','.*';' "
                                            r"between the fields"):
        read_record(path, decimal=",", **COLS)
    dm = HysteresisDataModule(path=str(path), min_samples=8, **COLS)
    with pytest.raises(DataFileError, match=r"line 2: expected 3 fields as the header, got 6"):
        dm.setup("fit")


def test_comma_file_with_decimal_comma_option(tmp_path: Path) -> None:
    path = write(tmp_path / "points.csv", "\n".join(lines()) + "\n")
    with pytest.raises(DataFileError, match=r"leave decimal '\.' for a file with decimal "
                                            r"points"):
        read_record(path, decimal=",", **COLS)


@pytest.mark.parametrize("row, got", [("0.5,1.0", 2), ("0.5,1.0,2.0,3.0", 4)])
def test_short_and_long_rows_name_line_and_counts(tmp_path: Path, row: str, got: int) -> None:
    text = ["# logger v2", *lines()]
    text[8] = row  # line 9
    path = write(tmp_path / "ragged.csv", "\n".join(text) + "\n")
    with pytest.raises(DataFileError) as err:
        read_record(path, **COLS)
    msg = str(err.value)
    assert msg.startswith(f"{path}: line 9: expected 3 fields as the header, got {got}")
    assert "decimal" not in msg


def test_short_row_without_header(tmp_path: Path) -> None:
    text = lines()[1:]
    text[3] = "0.5,1.0"
    path = write(tmp_path / "raw.csv", "\n".join(text) + "\n")
    with pytest.raises(DataFileError, match=r"line 4: expected 3 fields as the first row, "
                                            r"got 2"):
        read_record(path, input_column=2, target_column=1)


@pytest.mark.parametrize("column, option", [("response", "input_column"),
                                            ("command", "target_column")])
def test_constant_column_names_file_and_column(tmp_path: Path, column: str,
                                               option: str) -> None:
    const = np.full(N, 0.25)
    if column == "response":
        text = lines(response=const)
    else:
        text = [lines()[0]] + [f"{float(t)!r},0.25,{float(r)!r}"
                               for t, r in zip(TIME, RESPONSE, strict=True)]
    path = write(tmp_path / "flat.csv", "\n".join(text) + "\n")
    dm = HysteresisDataModule(path=str(path), min_samples=8, **COLS)
    dm.setup("fit")  # read and split; the check is on the training tensors
    with pytest.raises(DataFileError) as err:
        dm.train_tensors()
    msg = str(err.value)
    assert msg.startswith(f"{path}: data.{option} {column!r} is constant over the training "
                          f"split ({N} samples, all 0.25)")


def test_constant_over_the_training_split_only(tmp_path: Path) -> None:
    """Constant in the training part of a time split: named although the file varies later."""
    response = RESPONSE.copy()
    response[:12] = 1.0
    path = write(tmp_path / "late.csv", "\n".join(lines(response=response)) + "\n")
    dm = HysteresisDataModule(path=str(path), min_samples=4, split=[0.5, 0.25, 0.25], **COLS)
    with pytest.raises(DataFileError, match=re.escape(f"{path}: data.input_column 'response' "
                                                      "is constant over the training split")):
        dm.train_tensors()
    dm = HysteresisDataModule(path=str(path), min_samples=4, split=[0.75, 0.25, 0.0], **COLS)
    x, _ = dm.train_tensors()  # varies over the first 18 rows
    np.testing.assert_array_equal(x[0].numpy(), response[:18])


def test_constant_over_training_recordings_names_the_files(tmp_path: Path) -> None:
    flat = np.full(N, 2.0)
    a = write(tmp_path / "a.csv", "\n".join(lines(response=flat)) + "\n")
    b = write(tmp_path / "b.csv", "\n".join(lines(response=flat)) + "\n")
    c = write(tmp_path / "c.csv", "\n".join(lines()) + "\n")
    dm = HysteresisDataModule(path=[str(a), str(b), str(c)], min_samples=8,
                              split_by="recording", train_recordings=[0, 1],
                              test_recordings=[2], val_recordings=[], **COLS)
    with pytest.raises(DataFileError, match=re.escape(f"{a}, {b}, {c} (training recordings "
                                                      "[0, 1]): data.input_column 'response' "
                                                      "is constant")):
        dm.train_tensors()


@pytest.mark.parametrize(
    "kwargs, match",
    [(dict(decimal=";"), "decimal must be '.' or ',', got ';'"),
     (dict(decimal=None), "decimal must be '.' or ',', got None"),
     (dict(delimiter=";;"), "delimiter must be one character"),
     (dict(delimiter="x"), "delimiter must be one character"),
     (dict(delimiter=","), None),
     (dict(delimiter=",", decimal=","), "delimiter ',' cannot also be the decimal mark"),
     (dict(encoding="utf-9"), "encoding 'utf-9' is not a known text encoding"),
     (dict(encoding=8), "encoding must be the name of a text encoding")],
)
def test_bad_options_name_the_option(tmp_path: Path, kwargs: dict, match: str | None) -> None:
    path = write(tmp_path / "log.csv", "\n".join(lines()) + "\n")
    if match is None:
        check_values(read_record(path, **kwargs, **COLS))
        HysteresisDataModule(path=str(path), **kwargs)
        return
    option = next(iter(kwargs)) if len(kwargs) == 1 else "delimiter"
    with pytest.raises(ValueError, match=re.escape(match)) as err:
        read_record(path, **kwargs, **COLS)
    assert str(err.value).startswith(option)
    with pytest.raises(ValueError, match=re.escape(match)) as err:
        HysteresisDataModule(path=str(path), **kwargs)
    assert str(err.value).startswith(f"data.{option}") and "\n" not in str(err.value)


def test_npz_ignores_the_csv_options(tmp_path: Path) -> None:
    path = tmp_path / "log.npz"
    np.savez(path, time=TIME, command=COMMAND, response=RESPONSE)
    check_values(read_record(path, encoding="latin-1", delimiter=";", decimal=",", **COLS))


def test_constant_column_stops_the_model_set_up_with_the_file_named(tmp_path: Path) -> None:
    from torchhys.training import InverseHysteresisModule

    path = write(tmp_path / "flat.csv", "\n".join(lines(response=np.full(N, 3.0))) + "\n")
    dm = HysteresisDataModule(path=str(path), min_samples=8, **COLS)
    module = InverseHysteresisModule(operator=None, hidden=4)
    module._trainer = type("T", (), {"datamodule": dm})()  # all that setup reads
    with pytest.raises(DataFileError, match=re.escape(f"{path}: data.input_column 'response' "
                                                      "is constant")):
        module.setup("fit")
