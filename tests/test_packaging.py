"""Packaging: the wheel installs the Lightning side as ``torchhys.training`` only, with the
training packages in the ``train`` extra (tests/test_packaging_extras.py: torchhys without
them)."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> zipfile.ZipFile:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
         "-w", str(out), str(ROOT)],
        check=True, capture_output=True, cwd=out,
    )
    (path,) = out.glob("torchhys-*.whl")
    return zipfile.ZipFile(path)


def test_training_installs_under_the_package_namespace(wheel: zipfile.ZipFile) -> None:
    names = wheel.namelist()
    assert "torchhys/cli/train.py" in names
    assert "torchhys/training/__init__.py" in names
    assert not any(n.startswith("training/") for n in names), "a top-level training package"


def test_every_subpackage_is_in_the_wheel(wheel: zipfile.ZipFile) -> None:
    names = set(wheel.namelist())
    for init in (ROOT / "torchhys").rglob("__init__.py"):
        rel = init.relative_to(ROOT).as_posix()
        assert rel in names, f"{rel} is missing from the wheel (pyproject's package list)"
    for module in (ROOT / "torchhys" / "training").glob("*.py"):
        assert f"torchhys/training/{module.name}" in names


def test_console_script_points_into_the_namespace(wheel: zipfile.ZipFile) -> None:
    (entry,) = [n for n in wheel.namelist() if n.endswith("entry_points.txt")]
    text = wheel.read(entry).decode()
    # torchhys.cli.main: export without the train extra, the training commands with it
    assert "torchhys = torchhys.cli.main:main" in text


def test_the_training_packages_are_in_the_train_extra_only(wheel: zipfile.ZipFile) -> None:
    (meta,) = [n for n in wheel.namelist() if n.endswith(".dist-info/METADATA")]
    requires = [line.removeprefix("Requires-Dist:").strip()
                for line in wheel.read(meta).decode().splitlines()
                if line.startswith("Requires-Dist:")]
    for name in ("lightning", "jsonargparse", "torchmetrics", "matplotlib"):
        (req,) = [r for r in requires if r.startswith(name)]
        assert 'extra == "train"' in req, req
    assert "Provides-Extra: train" in wheel.read(meta).decode()


def test_import_torchhys_imports_no_lightning_and_no_training_package() -> None:
    code = (
        "import sys, importlib.util, torchhys\n"
        "assert not any(m.split('.')[0] in ('lightning', 'pytorch_lightning', 'matplotlib')"
        " for m in sys.modules), 'lightning or matplotlib imported'\n"
        "assert importlib.util.find_spec('training') is None, 'top-level training importable'\n"
        "import torchhys.training\n"
        "assert 'lightning' in sys.modules\n"
    )
    # outside the repository, so the checkout's folders are not on sys.path
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(sys.prefix))


def test_the_wheel_marks_the_package_as_typed(wheel: zipfile.ZipFile) -> None:
    """``torchhys/py.typed`` (PEP 561): type checkers read the package's annotations."""
    assert (ROOT / "torchhys" / "py.typed").is_file()
    assert "torchhys/py.typed" in wheel.namelist()


def test_the_wheel_holds_the_shipped_configs(wheel: zipfile.ZipFile) -> None:
    """Every ``configs/*.yaml`` of the checkout, byte for byte, as ``torchhys/configs/`` (the
    link in the checkout; ``torchhys fit --config measured`` reads it)."""
    configs = sorted((ROOT / "configs").glob("*.yaml"))
    assert len(configs) >= 9
    shipped = sorted(n for n in wheel.namelist() if n.startswith("torchhys/configs/"))
    assert shipped == [f"torchhys/configs/{c.name}" for c in configs]
    for config in configs:
        assert wheel.read(f"torchhys/configs/{config.name}") == config.read_bytes()
