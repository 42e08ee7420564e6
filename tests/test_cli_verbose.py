"""What the command prints besides its own lines: by default a warning is one line without
its source line and Lightning's tips and device lines are left out; ``--verbose`` (or
``TORCHHYS_VERBOSE=1``) keeps both as Lightning and Python print them."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from _training_helpers import small_config

from torchhys.cli.verbose import HIDDEN_INFO, format_warning

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str, cwd: Path, **env: str) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if not k.startswith("TORCHHYS_")}
    return subprocess.run([sys.executable, "-W", "always", "-c", textwrap.dedent(code)],
                          cwd=cwd, env={**base, "PYTHONPATH": str(ROOT), **env},
                          capture_output=True, text=True, timeout=300, check=False)


def test_a_warning_is_one_line_named_by_where_it_comes_from() -> None:
    own = str(ROOT / "torchhys" / "selection" / "coverage.py")
    assert format_warning("torchhys fit", UserWarning("fit: less than\n a loop"), UserWarning,
                          own, 127) == "torchhys fit: warning: fit: less than a loop\n"
    other = "/site-packages/lightning/pytorch/x.py"
    assert format_warning("torchhys test", UserWarning("The dirpath changed"), UserWarning,
                          other, 5) == f"{other}:5: UserWarning: The dirpath changed\n"


@pytest.mark.parametrize(("message", "hidden"), [
    ("💡 Tip: For seamless cloud logging and experiment tracking, try installing", True),
    ("GPU available: False, used: False", True),
    ("TPU available: False, using: 0 TPU cores", True),
    ("You are using a CUDA device ('NVIDIA H200') that has Tensor Cores.", True),
    ("[rank: 1] Seed set to 0", True),
    ("LOCAL_RANK: 0 - CUDA_VISIBLE_DEVICES: [0,1]", True),
    ("-" * 100 + "\ndistributed_backend=gloo\nAll distributed processes registered.", True),
    ("`Trainer.fit` stopped: `max_epochs=1` reached.", False),
    ("Restoring states from the checkpoint path at x.ckpt", False),
    ("  | Name | Type | Params", False),
])
def test_the_hidden_lightning_lines(message: str, hidden: bool) -> None:
    assert bool(HIDDEN_INFO.match(message)) is hidden


def test_warnings_without_and_with_verbose(tmp_path: Path) -> None:
    """A torchhys warning (raised with a stacklevel that names its caller's file) and
    another module's, inside :func:`default_output`: one line each; with
    ``TORCHHYS_VERBOSE=1`` Python's format, the source line under the other's."""
    (tmp_path / "helper.py").write_text(
        "import warnings\n\n\ndef warn():\n    warnings.warn('from a helper', UserWarning)\n")
    code = """
        import sys
        sys.path.insert(0, ".")
        import helper
        from torchhys._deprecated import moved
        from torchhys.cli.verbose import default_output

        with default_output("torchhys fit"):
            helper.warn()
            moved("old", {"pi": "math"})("pi")  # a DeprecationWarning attributed to this file
        print("done")
    """
    plain = _python(code, tmp_path)
    assert plain.returncode == 0, plain.stderr
    assert plain.stderr.splitlines() == [
        f"{tmp_path / 'helper.py'}:5: UserWarning: from a helper",
        "torchhys fit: warning: old.pi is deprecated: use math.pi (from math import pi)"]
    verbose = _python(code, tmp_path, TORCHHYS_VERBOSE="1")
    assert verbose.returncode == 0, verbose.stderr
    lines = verbose.stderr.splitlines()
    assert lines[:2] == [f"{tmp_path / 'helper.py'}:5: UserWarning: from a helper",
                         "  warnings.warn('from a helper', UserWarning)"]
    assert "DeprecationWarning: old.pi is deprecated" in lines[2]


def _fit(tmp_path: Path, *extra: str) -> list[str]:
    cfg = small_config(tmp_path, "c.yaml", trainer={"max_epochs": 1}, data={"t_end": 3.0})
    base = {k: v for k, v in os.environ.items() if not k.startswith("TORCHHYS_")}
    proc = subprocess.run(
        [sys.executable, "-m", "torchhys", "fit", "--config", str(cfg),
         f"--trainer.default_root_dir={tmp_path / 'run'}", *extra], cwd=ROOT,
        env={**base, "OMP_NUM_THREADS": "1"}, capture_output=True, text=True, timeout=300,
        check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return (proc.stdout + proc.stderr).splitlines()


@pytest.mark.slow
def test_a_fit_without_and_with_verbose(tmp_path: Path) -> None:
    """A fit on less than one loop warns (torchhys's coverage warning): by default one line
    under the command's name and none of Lightning's tips or device lines; ``--verbose``
    shows Lightning's lines (~20 s: slow)."""
    lines = _fit(tmp_path)
    warned = [i for i, line in enumerate(lines) if "warning" in line.lower()]
    assert [lines[i].split(":")[:3] for i in warned] == [
        ["torchhys fit", " warning", " fit"]], lines
    assert not any(line.startswith((" ", "\t")) for line in lines), lines  # no source echo
    assert not any(HIDDEN_INFO.match(line) or "Tip:" in line for line in lines), lines
    verbose = _fit(tmp_path, "--verbose")
    assert any(line.startswith("GPU available: ") for line in verbose), verbose
    assert any("less than one closed loop" in line for line in verbose)
    assert not any(line.startswith("torchhys fit: warning") for line in verbose)
