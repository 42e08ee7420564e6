"""The train extra: torchhys without Lightning, jsonargparse, torchmetrics and matplotlib.

Each check runs in a subprocess whose ``sitecustomize`` puts a finder first on
``sys.meta_path`` that refuses the training packages, as if they were not installed.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import torchhys.cli.commands as commands
import torchhys.cli.main as command

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ("lightning", "jsonargparse", "torchmetrics", "matplotlib")
BLOCKED = (*TRAIN, "pytorch_lightning", "lightning_fabric", "lightning_utilities")
LIGHTNING_SIDE = {"torchhys.training", "torchhys.reproduce", "torchhys.cli.train",
                  "torchhys.cli.checks", "torchhys.cli.ckpt_paths", "torchhys.cli.run_dirs",
                  "torchhys.cli.selection", "torchhys.cli.help_format"}
"""The modules (and packages) that need the train extra."""
ERROR = ('torchhys: error: the torchhys command needs the training extra: '
         'pip install "torchhys[train]" (missing: {})')

SITECUSTOMIZE = textwrap.dedent("""
    import os
    import sys

    _BLOCKED = frozenset(os.environ["TORCHHYS_TEST_BLOCK"].split(","))


    class _Blocker:
        @staticmethod
        def find_spec(name, path=None, target=None):
            if name.split(".")[0] in _BLOCKED:
                raise ModuleNotFoundError(f"No module named {name!r} (blocked)", name=name)
            return None


    sys.meta_path.insert(0, _Blocker())
""")


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("site")
    (folder / "sitecustomize.py").write_text(SITECUSTOMIZE)
    return folder


def run(site: Path, args: list[str], blocked=BLOCKED) -> subprocess.CompletedProcess:
    """Run ``args`` with the packages ``blocked``, outside the repository (its folders are
    then not on ``sys.path``: the installed torchhys is imported)."""
    env = dict(os.environ, PYTHONPATH=str(site), TORCHHYS_TEST_BLOCK=",".join(blocked))
    return subprocess.run(args, capture_output=True, text=True, env=env, cwd=Path(sys.prefix),
                          timeout=300)


def python(site: Path, code: str, blocked=BLOCKED) -> subprocess.CompletedProcess:
    return run(site, [sys.executable, "-c", textwrap.dedent(code)], blocked)


def test_core_dependencies_hold_none_of_the_training_packages() -> None:
    tomllib = pytest.importorskip("tomllib", reason="tomllib: Python 3.11 or later")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    core = " ".join(project["dependencies"]).lower()
    for name in TRAIN:
        assert name not in core, f"{name} is a core dependency"
    train = " ".join(project["optional-dependencies"]["train"]).lower()
    for name in TRAIN:
        assert name in train, f"{name} is missing from the train extra"
    assert "torchhys[train]" in project["optional-dependencies"]["dev"]
    assert project["scripts"]["torchhys"] == "torchhys.cli.main:main"


def test_every_module_but_training_imports_without_the_training_packages(site) -> None:
    """Every module imports without the extra but those of the training side: training/,
    the paper reproduction and the LightningCLI's modules of the command line."""
    proc = python(site, f"""
        import importlib, pkgutil, sys

        for name in ("lightning", "jsonargparse", "torchmetrics", "matplotlib"):
            try:
                importlib.import_module(name)
            except ModuleNotFoundError:
                pass
            else:
                raise AssertionError(f"{{name}} was not blocked")

        import torchhys

        imported = []

        def walk(package):
            for info in pkgutil.iter_modules(package.__path__, package.__name__ + "."):
                if info.name in {sorted(LIGHTNING_SIDE)!r}:
                    continue
                module = importlib.import_module(info.name)
                imported.append(info.name)
                if info.ispkg:
                    walk(module)

        walk(torchhys)
        assert len(imported) > 30, imported
        for name in ("torchhys.deploy.export", "torchhys.deploy.streaming",
                     "torchhys.functional.backlash", "torchhys.__main__", "torchhys.cli.main",
                     "torchhys.cli.export", "torchhys.data.files", "torchhys.data.tensors"):
            assert name in imported, name
        print(len(imported), "modules")
    """)
    assert proc.returncode == 0, proc.stderr
    assert "modules" in proc.stdout


def test_to_torchscript_works_without_the_training_packages(site, tmp_path) -> None:
    path = tmp_path / "comp.pt"
    proc = python(site, f"""
        import sys
        import torch
        from torchhys import Backlash, InverseHysteresisNet
        from torchhys.deploy.export import load_torchscript, to_torchscript

        torch.manual_seed(0)
        net = InverseHysteresisNet([Backlash([0.2, 0.7])], hidden=4)
        x = torch.linspace(0, 6.28, 200).sin() * 2
        net.fit_normalization(x, torch.tanh(x))
        to_torchscript(net, {str(path)!r}, limits=(-5.0, 5.0), direction="none",
                       input_margin=None)
        scripted = load_torchscript({str(path)!r})
        with torch.no_grad():
            assert torch.allclose(scripted(x), net(x)[0].clamp(-5.0, 5.0), atol=1e-5)
        assert not any(m.split(".")[0] in ("lightning", "matplotlib", "torchmetrics",
                                           "jsonargparse") for m in sys.modules)
    """)
    assert proc.returncode == 0, proc.stderr
    assert path.is_file()


def test_every_training_subcommand_says_which_extra_to_install(site) -> None:
    subs = ["fit", "validate", "test", "predict"]
    proc = python(site, f"""
        import sys
        from torchhys.cli.main import main

        for sub in {subs!r}:
            try:
                main([sub, "--help"])
            except SystemExit as exc:
                print(sub, exc.code)
    """)
    assert proc.stdout.split() == [w for sub in subs for w in (sub, "2")], proc.stderr
    assert proc.stderr.splitlines() == [ERROR.format(", ".join(TRAIN))] * len(subs)


def test_export_runs_without_the_extra(site) -> None:
    """``torchhys export`` reads a checkpoint as a spec plus weights (a real export without
    the extra: tests/test_layout.py)."""
    proc = python(site, """
        from torchhys.cli.main import main

        try:
            main(["export", "--help"])
        except SystemExit as exc:
            print("status", exc.code)
    """)
    assert proc.returncode == 0, proc.stderr
    assert "--ckpt" in proc.stdout and proc.stdout.split()[-2:] == ["status", "0"]
    assert proc.stderr == ""


def test_the_message_names_only_what_is_missing(site) -> None:
    proc = python(site, "from torchhys.cli.main import main; main(['fit'])",
                  blocked=("lightning",))
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == ERROR.format("lightning")


def test_python_dash_m_torchhys_says_which_extra_to_install(site) -> None:
    proc = run(site, [sys.executable, "-m", "torchhys", "fit", "--config", "c.yaml"])
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == ERROR.format(", ".join(TRAIN))


def test_the_installed_script_says_which_extra_to_install(site) -> None:
    script = Path(sys.executable).parent / ("torchhys.exe" if os.name == "nt" else "torchhys")
    if not script.exists():
        pytest.skip(f"no installed torchhys script beside {sys.executable}")
    proc = run(site, [str(script), "fit", "--config", "c.yaml"])
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip() == ERROR.format(", ".join(TRAIN))


def test_with_the_extra_the_command_runs_the_training_cli(monkeypatch) -> None:
    import torchhys.cli.train as cli

    seen = []
    monkeypatch.setattr(cli, "run", lambda args, **kwargs: seen.append((args, kwargs)))
    command.main(["fit", "--config", "c.yaml", "--traceback"])
    monkeypatch.setattr(sys, "argv", ["torchhys", "validate", "--config", "c.yaml"])
    command.main(None)
    assert seen == [(["fit", "--config", "c.yaml"], {"from_sys_argv": False, "traceback": True,
                                                     "help_all": False}),
                    (["validate", "--config", "c.yaml"],
                     {"from_sys_argv": True, "traceback": False, "help_all": False})]
    assert commands.missing_train_packages() == []


def test_a_missing_dependency_of_the_extra_is_named(monkeypatch, capsys) -> None:
    import builtins

    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "torchhys.cli.train":
            raise ModuleNotFoundError("No module named 'docstring_parser'",
                                      name="docstring_parser")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(SystemExit) as info:
        command.main(["fit"])
    assert info.value.code == 2
    assert capsys.readouterr().err.strip() == ERROR.format("docstring_parser")
