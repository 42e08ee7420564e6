"""The notebooks execute in the project's Python, and are committed without outputs."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


def test_notebooks_exist() -> None:
    names = {p.name for p in NOTEBOOKS}
    assert {"quickstart.ipynb", "paper_reproduction.ipynb", "composing.ipynb"} <= names


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.stem)
def test_committed_notebook_has_no_outputs(path: Path) -> None:
    nb = nbformat.read(path, as_version=4)
    for i, cell in enumerate(nb.cells):
        if cell.cell_type == "code":
            assert not cell.get("outputs"), f"{path.name}: cell {i} has outputs"
            assert cell.get("execution_count") is None, f"{path.name}: cell {i} was executed"


SLOW_NOTEBOOKS = {"paper_reproduction"}
"""Notebooks executed with the slow tests only: the paper reproduction runs the protocol's
fits (checked in the default run by tests/test_paper_protocol.py and
tests/test_paper_simulation.py; the quickstart keeps a notebook's execution there)."""


@pytest.mark.parametrize("path", [
    pytest.param(p, marks=[pytest.mark.slow] * (p.stem in SLOW_NOTEBOOKS)) for p in NOTEBOOKS],
    ids=lambda p: p.stem)
def test_notebook_executes(path: Path, tmp_path: Path) -> None:
    nb = nbformat.read(path, as_version=4)
    # ipykernel's native "python3" kernel is this interpreter: checked by the first cell
    nb.cells.insert(0, nbformat.v4.new_code_cell("import sys; print(sys.executable)"))
    client = nbclient.NotebookClient(nb, kernel_name="python3", timeout=180,
                                     resources={"metadata": {"path": str(path.parent)}})
    client.execute()
    assert nb.cells[0].outputs[0]["text"].strip() == sys.executable
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs
              if o.get("output_type") == "error"]
    assert not errors
