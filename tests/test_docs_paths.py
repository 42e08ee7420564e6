"""Every torchhys module path and file path that README.md and docs/*.md name exists.

A dotted path ``torchhys.a.b`` resolves when its longest importable prefix imports and the
rest are attributes of it; a module reached as an attribute must be that module itself
(an attribute that binds ``torchhys.identification.fitting`` under a second name is no module
path). A file path ``torchhys/...`` (also as a link, ``../torchhys/...``) must exist in the
checkout, and so must a path that starts with a folder of the package without the
``torchhys/`` before it (``training/cli.py``).
Placeholders (``torchhys/operators/<family>.py``) are left out.
"""

from __future__ import annotations

import importlib
import re
import types
from pathlib import Path

import pytest

import torchhys

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
DOTTED = re.compile(r"(?<![\w./-])torchhys(?:\.[A-Za-z_]\w*)+")
FILE = re.compile(r"(?<![\w/.-])(?:\.\./)?torchhys/[\w/.<>*-]*")
SUBPACKAGES = sorted(p.name for p in Path(torchhys.__file__).parent.iterdir()
                     if (p / "__init__.py").is_file())
BARE = re.compile(rf"(?<![\w/.-])(?:{'|'.join(SUBPACKAGES)})/[\w/.-]*\.py\b")


def resolves(dotted: str) -> bool:
    """Whether ``dotted`` names a torchhys module or an attribute of one (module docstring)."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        name = ".".join(parts[:n])
        try:
            obj = importlib.import_module(name)
        except ModuleNotFoundError as e:
            if e.name is not None and name.startswith(e.name):
                continue  # that module does not exist: try the shorter prefix
            raise
        for i in range(n, len(parts)):
            if not hasattr(obj, parts[i]):
                return False
            obj = getattr(obj, parts[i])
            if isinstance(obj, types.ModuleType) and obj.__name__ != ".".join(parts[:i + 1]):
                return False
        return True
    return False


def missing(text: str) -> list[str]:
    """The paths in ``text`` that do not exist, in order of appearance."""
    out = []
    for m in DOTTED.finditer(text):
        if not resolves(m.group(0)):
            out.append(m.group(0))
    for m in FILE.finditer(text):
        path = m.group(0).removeprefix("../").rstrip(".")
        if "<" not in path and "*" not in path and not (ROOT / path).exists():
            out.append(path)
    for m in BARE.finditer(text):
        if not (ROOT / m.group(0)).exists():
            out.append(m.group(0))
    return out


def test_the_checker_finds_paths_that_do_not_exist() -> None:
    text = """`torchhys.fitting.fit_full_batch`, `torchhys.preisach`, `torchhys.export`,
    `torchhys.deploy.export.no_such_function`, [x](../torchhys/_nnls.py), `torchhys/preisach.py`,
    `training/cli.py`, `torchhys.streaming.StreamingCompensator`."""
    assert missing(text) == [
        "torchhys.fitting.fit_full_batch", "torchhys.preisach", "torchhys.export",
        "torchhys.deploy.export.no_such_function", "torchhys.streaming.StreamingCompensator",
        "torchhys/_nnls.py", "torchhys/preisach.py", "training/cli.py"]
    good = """`torchhys.identification.fitting.fit_full_batch`, `torchhys.Backlash`,
    `torchhys.deploy.export_c`, `torchhys.registry.OPERATORS`, [o](../torchhys/operator.py),
    `torchhys/identification/_nnls.py`, `torchhys/operators/<family>.py`, `torchhys/deploy/`,
    `torchhys/cli/train.py`, `deploy/c/example_comp.py`, `torchhys.cli.main.main`."""
    assert missing(good) == []


@pytest.mark.parametrize("page", PAGES, ids=[p.name for p in PAGES])
def test_every_path_a_page_names_exists(page: Path) -> None:
    assert missing(page.read_text()) == []
