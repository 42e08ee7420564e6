"""docs/adding-an-operator.md runs as written.

The page's code blocks are read from the page: the Python blocks headed ``# my_operators.py``
make the module it says to save (in a temporary folder), the other Python blocks run in
order in one process there, and their asserts and prints are checked. With the slow tests,
the page's command lines run too: ``torchhys fit --import-path . --import`` on its config,
the exports, and the conformance suite on the page's operators.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "adding-an-operator.md"
MODULE = "my_operators"
CONFIG = "my_play.yaml"
CC = shutil.which("cc")
KNOWN_DEFECTS: dict[str, str] = {}
"""Conformance checks that the page's operators may fail because of a defect outside the
page (the entry goes when the defect is fixed)."""


def blocks(language: str) -> list[str]:
    """The page's fenced code blocks of ``language``, in order."""
    found = re.findall(r"^```(\w*)\n(.*?)^```", PAGE.read_text(), flags=re.M | re.S)
    return [body for lang, body in found if lang == language]


def headed(body: str, name: str) -> bool:
    return body.splitlines()[0] == f"# {name}"


def write_files(folder: Path, module: str | None = None) -> str:
    """Write the page's module and config into ``folder``; return the other Python blocks
    as one script. ``module``: the module's text instead of the page's."""
    python = blocks("python")
    parts = [b for b in python if headed(b, f"{MODULE}.py")]
    (folder / f"{MODULE}.py").write_text(module if module is not None else "\n\n".join(parts))
    for body in blocks("yaml"):
        if headed(body, CONFIG):
            (folder / CONFIG).write_text(body)
    return "\n".join(b for b in python if not headed(b, f"{MODULE}.py"))


def run(args: list[str], cwd: Path, timeout: int = 600, *, command: bool = False
        ) -> subprocess.CompletedProcess:
    """``args`` in ``cwd`` with ``cwd`` on ``PYTHONPATH``; ``command``: with ``sys.path`` as
    the ``torchhys`` console script has it instead (no working folder: ``PYTHONSAFEPATH``,
    Python 3.11 and later), so that the page's ``--import-path .`` is what finds the module."""
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    if command:
        env["PYTHONSAFEPATH"] = "1"
        env.pop("PYTHONPATH", None)
    else:
        env["PYTHONPATH"] = str(cwd)
    for key in ("TORCHHYS_IMPORT", "TORCHHYS_IMPORT_PATH"):
        env.pop(key, None)
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=timeout,
                          env=env)


def test_the_page_has_the_pieces_it_describes() -> None:
    python = blocks("python")
    module = "\n\n".join(b for b in python if headed(b, f"{MODULE}.py"))
    script = "\n".join(b for b in python if not headed(b, f"{MODULE}.py"))
    assert module and script.count("assert ") >= 8
    assert "state: list[Tensor]) -> tuple[Tensor, list[Tensor]]" in module
    assert module.count("register_operator(") == 2 and "Example(" in module
    assert "constraints = {" in module
    # the entry points name the page's classes under their registered names
    tomllib = pytest.importorskip("tomllib", reason="tomllib: Python 3.11 or later")
    (toml,) = blocks("toml")
    group = tomllib.loads(toml)["project"]["entry-points"]["torchhys.operators"]
    for name, value in group.items():
        cls = value.split(":")[1]
        assert f'register_operator("{name}", {cls},' in module
    assert any(headed(b, CONFIG) for b in blocks("yaml"))


@pytest.mark.skipif(CC is None, reason="no C compiler (cc) on PATH")
def test_the_python_blocks_run_as_written(tmp_path: Path) -> None:
    script = write_files(tmp_path)
    (tmp_path / "page.py").write_text(script)
    out = run([sys.executable, "page.py"], tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.splitlines()
    assert lines[0].startswith("r must be finite and >= 0, got [-1.0]")
    assert lines[1] == "r = 0.200000"
    assert lines[-1] == "network, stream, TorchScript and C agree"
    assert (tmp_path / "c" / "my_comp.h").is_file() and (tmp_path / "my_comp.pt").is_file()


def test_the_blocks_fail_on_a_wrong_operator(tmp_path: Path) -> None:
    """The page's asserts catch a wrong step: a play that follows x within +-2r."""
    page_module = "\n\n".join(b for b in blocks("python") if headed(b, f"{MODULE}.py"))
    wrong = page_module.replace("x + r)", "x + 2 * r)")
    assert wrong != page_module
    first = blocks("python")[1]  # FixedPlay through the base class's forward
    assert not headed(first, f"{MODULE}.py")
    write_files(tmp_path, module=wrong)
    (tmp_path / "page.py").write_text(first)
    out = run([sys.executable, "page.py"], tmp_path)
    assert out.returncode == 1 and "AssertionError" in out.stderr


def commands(prefix: str) -> list[list[str]]:
    """The page's shell command lines that start with ``prefix`` (the words after it)."""
    found = []
    for body in blocks("bash"):
        for line in body.splitlines():
            words = shlex.split(line, comments=True)
            if prefix in words:
                found.append(words[words.index(prefix) + 1:])
    return found


@pytest.mark.slow
def test_the_command_line_route(tmp_path: Path) -> None:
    """``torchhys fit --import-path . --import`` on the page's config, both exports, and the
    TorchScript file run where neither torchhys nor the module is imported."""
    write_files(tmp_path)
    (tmp_path / "c_out").mkdir()
    steps = commands("torchhys")
    assert [s[0] for s in steps] == ["fit", "export", "export"]
    for args in steps:
        out = run([sys.executable, "-m", "torchhys", *args], tmp_path, command=True)
        assert out.returncode == 0, (args, out.stderr[-3000:])
    assert (tmp_path / "c_out" / "my_comp.c").is_file()
    check = textwrap.dedent("""
        import sys, torch
        u = torch.jit.load("my_comp.pt")(torch.linspace(0.0, 5.0, 100, dtype=torch.float64))
        assert torch.isfinite(u).all()
        assert "torchhys" not in sys.modules and "my_operators" not in sys.modules
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", check], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300, env={**os.environ, "PYTHONPATH": ""})
    assert out.returncode == 0 and out.stdout == "ok\n", out.stderr[-2000:]


@pytest.mark.slow
def test_the_conformance_suite_covers_the_page_operators(tmp_path: Path) -> None:
    """The page's pytest line: every check of tests/test_conformance.py runs
    for both names and passes, but for KNOWN_DEFECTS."""
    write_files(tmp_path)
    (args,) = commands("pytest")
    assert args[:2] == ["-p", MODULE]
    env = {**os.environ, "PYTHONPATH": str(tmp_path), "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, "-m", "pytest", *args, "-q", "-rA",
                          "-p", "no:cacheprovider"], cwd=ROOT, capture_output=True, text=True,
                         timeout=600, env=env)
    outcome = {test: status for status, test in
               re.findall(r"^(PASSED|FAILED|ERROR|SKIPPED|XFAIL|XPASS) \S+::(\S+)", out.stdout,
                          flags=re.M)}
    assert outcome, out.stdout[-3000:]
    for name in ("my_play", "my_fixed_play"):  # the default checks, C float64/32, ONNX float64
        assert sum(f"[{name}" in t or f"-{name}" in t for t in outcome) >= 13
        assert outcome[f"test_conformance[step-{name}]"] == "PASSED"
        assert outcome[f"test_conformance[torchscript-{name}]"] == "PASSED"
        assert outcome[f"test_c_equals_torchscript[{name}-float64]"] in ("PASSED", "SKIPPED")
    bad = {t: s for t, s in outcome.items()
           if s not in ("PASSED", "SKIPPED") and t not in KNOWN_DEFECTS}
    assert not bad, out.stdout[-3000:]
