"""The wheel alone: built from the checkout, installed into a folder outside it, and the
README's first commands run there (``torchhys --version``, ``torchhys configs``, ``torchhys
fit --config measured --print_config``) from a folder that holds no ``configs/``.

The installed folder comes first on ``PYTHONPATH``, before the environment's site-packages
(torch, Lightning come from there); the editable install of the checkout, a finder at the
end of ``sys.meta_path``, is never asked: the test checks that ``torchhys.__file__`` is the
installed one.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]

# ~12 s (a wheel build, an install, four commands), not marked slow: the only test of the
# installed wheel


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder the wheel is installed into (``pip install --no-deps --target``)."""
    wheels, target = tmp_path_factory.mktemp("wheels"), tmp_path_factory.mktemp("installed")
    pip = [sys.executable, "-m", "pip"]
    subprocess.run([*pip, "wheel", "--quiet", "--no-deps", "--no-build-isolation", "-w",
                    str(wheels), str(ROOT)], check=True, capture_output=True, cwd=wheels,
                   timeout=600)
    (wheel,) = wheels.glob("torchhys-*.whl")
    subprocess.run([*pip, "install", "--quiet", "--no-deps", "--no-index", "--target",
                    str(target), str(wheel)], check=True, capture_output=True, cwd=wheels,
                   timeout=600)
    return target


def run(installed: Path, cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """The wheel's console script, ``torchhys ARGS``, with the installed folder first."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("TORCHHYS_")}
    env["PYTHONPATH"] = str(installed)
    proc = subprocess.run([sys.executable, str(installed / "bin" / "torchhys"), *args],
                          capture_output=True, text=True, cwd=cwd, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    return proc


def test_the_installed_package_is_the_wheels(installed: Path, tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(installed))
    proc = subprocess.run([sys.executable, "-c", "import torchhys; print(torchhys.__file__)"],
                          capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()) == installed / "torchhys" / "__init__.py"
    assert not (installed / "torchhys" / "configs").is_symlink()  # the files themselves
    assert (installed / "torchhys" / "py.typed").is_file()


def test_the_readmes_commands_run_from_the_wheel(installed: Path, tmp_path: Path) -> None:
    from torchhys._version import __version__

    assert not (tmp_path / "configs").exists()
    assert run(installed, tmp_path, "--version").stdout == f"torchhys {__version__}\n"
    listed = run(installed, tmp_path, "configs").stdout.splitlines()
    names = sorted(p.stem for p in (ROOT / "configs").glob("*.yaml"))
    assert [line.split()[0] for line in listed[:len(names)]] == names
    printed = yaml.safe_load(run(installed, tmp_path, "fit", "--config", "measured",
                                 "--print_config").stdout)
    with (ROOT / "configs" / "measured.yaml").open() as fh:
        measured = yaml.safe_load(fh)
    assert printed["model"]["select"] == measured["model"]["select"]
    assert printed["trainer"]["default_root_dir"] == measured["trainer"]["default_root_dir"]
    assert list(tmp_path.iterdir()) == []  # --print_config writes nothing


def test_the_shipped_recordings_load_from_the_wheel(installed: Path, tmp_path: Path) -> None:
    """``torchhys.datasets`` from the wheel: every shipped recording, byte for byte the
    checkout's, and ``fit --config measured`` on its default data outside the checkout."""
    import torchhys.datasets as datasets

    for name, file in datasets.FILES.items():
        got = installed / "torchhys" / "example_data" / file
        assert got.read_bytes() == (ROOT / "examples" / "data" / file).read_bytes(), name
    env = dict(os.environ, PYTHONPATH=str(installed))
    code = ("import torchhys.datasets as d; r = d.load('piezo_micromanipulator'); "
            "print(len(r['voltage_V']), d.path('bouc_wen'))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr
    n, where = proc.stdout.split()
    assert int(n) == len(datasets.load("piezo_micromanipulator")["voltage_V"])
    assert Path(where).is_relative_to(installed)
    run(installed, tmp_path, "fit", "--config", "measured", "--trainer.max_epochs=1",
        "--model.select=[{operator: null}]", "--trainer.enable_progress_bar=false",
        f"--trainer.default_root_dir={tmp_path / 'run'}")
    assert any((tmp_path / "run").glob("logs/version_0/checkpoints/*.ckpt"))
