"""docs/composing.md runs as written: its Python blocks run in a temporary folder, in one
namespace and in order (the worked example, then the conformance check of its model), their
asserts hold and the first prints the state's blocks the page says."""

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
    blocks = re.findall(r"^```python\n(.*?)^```", text, flags=re.M | re.S)
    assert len(blocks) == 2, len(blocks)
    printed = re.search(r"It prints the state's blocks, `(\[.*?\])`", text, flags=re.S)
    cwd = os.getcwd()
    out = io.StringIO()
    try:
        os.chdir(tmp_path)
        namespace = {"__name__": "composing"}
        with contextlib.redirect_stdout(out):
            exec(compile(blocks[0], str(PAGE), "exec"), namespace)
        exec(compile(blocks[1], str(PAGE), "exec"), namespace)
    finally:
        os.chdir(cwd)
    assert ast.literal_eval(out.getvalue().strip()) == ast.literal_eval(
        " ".join(printed.group(1).split()))
    assert (tmp_path / "model.pt").is_file()
    assert sorted(p.suffix for p in (tmp_path / "model_c").iterdir()) == [".c", ".h"]
