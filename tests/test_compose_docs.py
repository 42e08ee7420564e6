"""docs/composing.md runs as written: its Python block runs in a temporary folder, its
assert holds and it prints the state's blocks the page says."""

from __future__ import annotations

import ast
import contextlib
import io
import os
import re
from pathlib import Path

import pytest

PAGE = Path(__file__).resolve().parents[1] / "docs" / "composing.md"


@pytest.mark.filterwarnings("ignore::DeprecationWarning")
def test_the_worked_example_runs_as_written(tmp_path):
    text = PAGE.read_text()
    (code,) = re.findall(r"^```python\n(.*?)^```", text, flags=re.M | re.S)
    printed = re.search(r"It prints the state's blocks, `(\[.*?\])`", text, flags=re.S)
    cwd = os.getcwd()
    out = io.StringIO()
    try:
        os.chdir(tmp_path)
        with contextlib.redirect_stdout(out):
            exec(compile(code, str(PAGE), "exec"), {"__name__": "composing"})
    finally:
        os.chdir(cwd)
    assert ast.literal_eval(out.getvalue().strip()) == ast.literal_eval(
        " ".join(printed.group(1).split()))
    assert (tmp_path / "model.pt").is_file()
    assert sorted(p.suffix for p in (tmp_path / "model_c").iterdir()) == [".c", ".h"]
