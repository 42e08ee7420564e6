"""Operators from other modules in the ``torchhys`` command: ``--import MODULE`` and the
``torchhys.operators`` entry-point group.

A module written in a temporary folder (no torchhys file knows it) defines and registers an
operator; ``torchhys fit --import-path . --import`` trains a config that names it (the
working folder is searched only when named), ``torchhys export --import`` exports the
checkpoint, and the exported file runs in a process that never imports torchhys.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from _training_helpers import DROP, small_config

import torchhys.registry as registry_module
from torchhys.cli.plugins import split_import_flags
from torchhys.registry import OPERATORS, load_entry_points, make_operator

OPERATOR_MODULE = '''
"""A user's operator: a dead zone of fixed width (memoryless), registered on import."""
import torch
from torch import Tensor

from torchhys.operator import HysteresisOperator
from torchhys.registry import register_operator
from torchhys.step import OperatorStep


class SoftZoneStep(OperatorStep):
    def __init__(self, width: float) -> None:
        super().__init__()
        self.width = width
        self.n_outputs = 1
        self.state_spec = []

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        return x - torch.clamp(x, -self.width, self.width), state


class SoftZone(HysteresisOperator):
    n_outputs = 1

    def __init__(self, width: float = 0.5) -> None:
        super().__init__()
        self.width = float(width)

    def forward(self, x: Tensor, state: object = None) -> tuple[Tensor, None]:
        return x - torch.clamp(x, -self.width, self.width), None

    def streaming_step(self, dtype: torch.dtype) -> OperatorStep:
        return SoftZoneStep(self.width)


register_operator("{name}", SoftZone)
'''

CONFIG = {"trainer": {"max_epochs": 2, "check_val_every_n_epoch": DROP},
          "model": {"operator": [{"name": "soft_zone_cli", "width": 0.4}],
                    "operator_kwargs": DROP, "hidden": 4, "optimizer": "lbfgs",
                    "optimizer_kwargs": DROP}}
"""The sections of :func:`small_config`: the user's operator and 4 sigmoids by L-BFGS."""


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """``torchhys ARGS`` in ``cwd`` with ``sys.path`` as the console script has it: without
    the working folder (``PYTHONSAFEPATH``, Python 3.11 and later)."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONSAFEPATH": "1"}
    for key in ("TORCHHYS_IMPORT", "TORCHHYS_IMPORT_PATH", "PYTHONPATH"):
        env.pop(key, None)
    return subprocess.run([sys.executable, "-m", "torchhys", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=600, env=env)


def test_split_import_flags() -> None:
    assert split_import_flags(["fit", "--import", "a", "--import=b.c", "--x", "1"]) == (
        ["fit", "--x", "1"], ["a", "b.c"])
    with pytest.raises(ValueError, match="--import needs a module name"):
        split_import_flags(["fit", "--import"])


def test_fit_and_export_an_operator_of_an_imported_module(tmp_path: Path) -> None:
    (tmp_path / "my_operators.py").write_text(OPERATOR_MODULE.replace("{name}", "soft_zone_cli"))
    small_config(tmp_path, "c.yaml", **CONFIG)
    # without the module the name is unknown: a one-line error
    bad = _run(["fit", "--config", "c.yaml", "--trainer.default_root_dir=run"], tmp_path)
    assert bad.returncode == 2 and "soft_zone_cli" in bad.stderr.strip().splitlines()[-1]
    if sys.version_info >= (3, 11):  # the working folder is not searched unless named
        unnamed = _run(["fit", "--import", "my_operators", "--config", "c.yaml",
                        "--trainer.default_root_dir=run"], tmp_path)
        assert unnamed.returncode == 2 and "add --import-path ." in unnamed.stderr
    fit = _run(["fit", "--import-path", ".", "--import", "my_operators", "--config", "c.yaml",
                "--trainer.default_root_dir=run"], tmp_path)
    assert fit.returncode == 0, fit.stderr[-3000:]
    ckpt = tmp_path / "run/logs/version_0/checkpoints/last.ckpt"
    export = _run(["export", "--import", "my_operators", "--import-path", ".", "--ckpt",
                   str(ckpt), "--format", "torchscript", "--out", "comp.pt"], tmp_path)
    assert export.returncode == 0, export.stderr[-3000:]
    missing = _run(["export", "--import", "no_such_module", "--ckpt", str(ckpt), "--format",
                    "torchscript", "--out", "comp2.pt"], tmp_path)
    assert missing.returncode == 2
    assert "--import no_such_module: ModuleNotFoundError" in missing.stderr
    # the exported file runs without torchhys (and without the user's module)
    script = textwrap.dedent("""
        import sys, torch
        m = torch.jit.load("comp.pt")
        x = torch.linspace(-1.0, 1.0, 200, dtype=torch.float64)
        u = m(x)
        assert torch.isfinite(u).all()
        assert "torchhys" not in sys.modules and "my_operators" not in sys.modules
        print("ok", float(u[-1]))
    """)
    run = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300, env={**os.environ, "PYTHONPATH": ""})
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.startswith("ok")


def test_entry_point_of_an_installed_package(tmp_path: Path, monkeypatch) -> None:
    # an installed distribution (its dist-info on sys.path) declaring the entry point
    pkg = tmp_path / "site"
    pkg.mkdir()
    (pkg / "ep_operators.py").write_text(OPERATOR_MODULE.replace(
        'register_operator("{name}", SoftZone)', ""))
    info = pkg / "ep_operators-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: ep-operators\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[torchhys.operators]\nsoft_zone_ep = ep_operators:SoftZone\n")
    monkeypatch.syspath_prepend(str(pkg))
    monkeypatch.setattr(registry_module, "_entry_points_loaded", False)
    monkeypatch.delitem(OPERATORS, "soft_zone_ep", raising=False)
    op = make_operator("soft_zone_ep", width=0.25)  # loaded on first use of the registry
    assert type(op).__name__ == "SoftZone" and op.width == 0.25
    assert load_entry_points() == []  # once per process
    OPERATORS.pop("soft_zone_ep")
