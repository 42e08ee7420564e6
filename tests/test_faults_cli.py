"""Faults of the command line and the Python API found by the fault probe (issue 51): what
``--import`` adds to ``sys.path``, a broken ``torchhys.operators`` entry point, switching
the optimizer on the command line, ``--config`` given a data file, a float64 input to a
float32 network."""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

import pytest
import torch
from _training_helpers import DROP, small_config

import torchhys.registry as registry_module
from torchhys import InverseHysteresisNet
from torchhys.cli.main import main
from torchhys.cli.plugins import (
    IMPORT_ENV,
    IMPORT_PATH_ENV,
    import_modules,
    split_import_path_flags,
)
from torchhys.registry import OPERATORS, load_entry_points, make_operator
from torchhys.testing import example_of
from torchhys.training import InverseHysteresisModule

USER_MODULE = "from torchhys.registry import register_operator\nLOADED = True\n"


def error_line(capsys: pytest.CaptureFixture, *args: str) -> str:
    """``torchhys ARGS`` in this process as users run it: exit status 2 and one line on
    stderr, ``torchhys ...: error: ...``; that line."""
    with pytest.raises(SystemExit) as exit_info:
        main(list(args))
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and ": error: " in err[-1] and "Traceback" not in "\n".join(err)
    return err[-1]


@pytest.fixture
def clean_path(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    """The working folder ``tmp_path/work`` and a ``sys.path`` without it (as the
    ``torchhys`` console script runs: its own folder first, not the working folder)."""
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    monkeypatch.setattr(sys, "path", [p for p in sys.path
                                      if p not in ("", ".", str(work), str(Path.cwd()))])
    monkeypatch.setattr(sys, "argv", ["torchhys"])
    for key in (IMPORT_ENV, IMPORT_PATH_ENV, "TORCHHYS_TRACEBACK"):
        monkeypatch.delenv(key, raising=False)
    return work


# ------------------------------------------------------------------------------------------
# 9. imports: nothing on sys.path but what the user names
# ------------------------------------------------------------------------------------------

def test_import_adds_nothing_to_sys_path(clean_path: Path, monkeypatch) -> None:
    """A module found as Python finds it (here the standard library's) leaves sys.path as
    it was: the working folder is not put first (where a file of it named like an installed
    package, e.g. onnxscript.py, would replace the package for every later import)."""
    before = list(sys.path)
    import_modules(["json"])
    assert sys.path == before


def test_a_module_of_the_working_folder_needs_import_path(clean_path: Path,
                                                          monkeypatch) -> None:
    (clean_path / "my_ops_faults.py").write_text(USER_MODULE)
    monkeypatch.delitem(sys.modules, "my_ops_faults", raising=False)
    with pytest.raises(ValueError, match=r"--import my_ops_faults: ModuleNotFoundError.*"
                                         r"working folder.*--import-path \."):
        import_modules(["my_ops_faults"])
    import_modules(["my_ops_faults"], ["."])
    assert sys.modules["my_ops_faults"].LOADED
    assert sys.path[-1] == str(clean_path)  # appended: after the installed packages
    with pytest.raises(ValueError, match="--import-path nowhere: no such folder"):
        import_modules([], ["nowhere"])


def test_import_path_does_not_shadow_an_installed_package(clean_path: Path, tmp_path: Path,
                                                          monkeypatch) -> None:
    """A file of an --import-path folder named like an installed package does not replace
    it (the folder is searched after it)."""
    site = tmp_path / "site"
    (site / "shadowed_pkg_faults").mkdir(parents=True)
    (site / "shadowed_pkg_faults" / "__init__.py").write_text("WHICH = 'installed'\n")
    monkeypatch.syspath_prepend(str(site))
    (clean_path / "shadowed_pkg_faults.py").write_text("WHICH = 'working folder'\n")
    (clean_path / "my_ops_faults2.py").write_text(USER_MODULE)
    for name in ("shadowed_pkg_faults", "my_ops_faults2"):
        monkeypatch.delitem(sys.modules, name, raising=False)
    import_modules(["my_ops_faults2"], ["."])
    import shadowed_pkg_faults

    assert shadowed_pkg_faults.WHICH == "installed"


def test_the_command_takes_import_path(clean_path: Path, monkeypatch, capsys) -> None:
    """``torchhys --import-path DIR --import MODULE`` imports it (then the config, a data
    file, is refused); ``TORCHHYS_IMPORT`` / ``TORCHHYS_IMPORT_PATH`` stand for the options,
    and are as they were after the command."""
    assert split_import_path_flags(["fit", "--import-path", "a", "--import-path=b"]) == (
        ["fit"], ["a", "b"])
    with pytest.raises(ValueError, match="--import-path needs a folder"):
        split_import_path_flags(["fit", "--import-path"])
    lib = clean_path / "lib"
    lib.mkdir()
    (lib / "my_ops_faults3.py").write_text(USER_MODULE)
    (clean_path / "d.csv").write_text("x,y\n1,2\n")
    monkeypatch.delitem(sys.modules, "my_ops_faults3", raising=False)
    line = error_line(capsys, "fit", "--import", "my_ops_faults3", "--config", "d.csv")
    assert "--import my_ops_faults3: ModuleNotFoundError" in line
    error_line(capsys, "fit", "--import-path", "lib", "--import", "my_ops_faults3",
               "--config", "d.csv")
    assert sys.modules["my_ops_faults3"].LOADED and str(lib) in sys.path
    assert IMPORT_ENV not in os.environ
    monkeypatch.delitem(sys.modules, "my_ops_faults3")
    sys.path.remove(str(lib))
    monkeypatch.setenv(IMPORT_ENV, "my_ops_faults3")
    monkeypatch.setenv(IMPORT_PATH_ENV, str(lib))
    error_line(capsys, "fit", "--config", "d.csv")
    assert sys.modules["my_ops_faults3"].LOADED


# ------------------------------------------------------------------------------------------
# 9. a broken entry point of another package: reported once, skipped unless it is used
# ------------------------------------------------------------------------------------------

@pytest.fixture
def broken_entry_point(tmp_path: Path, monkeypatch) -> None:
    """An installed distribution with two ``torchhys.operators`` entry points: one whose
    module fails to import, one that works."""
    site = tmp_path / "ep_site"
    site.mkdir()
    (site / "broken_ep_faults.py").write_text("import no_such_dependency_faults\n")
    (site / "good_ep_faults.py").write_text(
        "from torchhys.registry import OPERATORS\nGood = OPERATORS['eiho']\n")
    info = site / "ep_faults-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: ep-faults\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[torchhys.operators]\nbroken_op_faults = broken_ep_faults:Op\n"
        "good_op_faults = good_ep_faults:Good\n")
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.setattr(registry_module, "_entry_points_loaded", False)
    monkeypatch.setattr(registry_module, "BROKEN_ENTRY_POINTS", {})
    for name in ("broken_op_faults", "good_op_faults"):
        monkeypatch.delitem(OPERATORS, name, raising=False)
    yield
    for name in ("broken_op_faults", "good_op_faults"):
        OPERATORS.pop(name, None)


def test_a_broken_entry_point_is_reported_once_and_skipped(broken_entry_point) -> None:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        net = InverseHysteresisNet(["eiho", "good_op_faults"], 4)  # loads the entry points
        InverseHysteresisNet("eiho", 4)
        load_entry_points()
    assert len(net.operators) == 2
    ours = [str(w.message) for w in caught if "broken_op_faults" in str(w.message)]
    assert len(ours) == 1
    assert "'broken_ep_faults:Op'" in ours[0] and "no_such_dependency_faults" in ours[0]
    assert "good_op_faults" in OPERATORS and "broken_op_faults" not in OPERATORS


def test_a_broken_entry_point_used_by_name_is_one_error(broken_entry_point) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        load_entry_points()
    with pytest.raises(ValueError) as info:
        make_operator({"name": "broken_op_faults"}, argument="operator[1]")
    text = str(info.value)
    assert text.startswith("operator[1]: entry point 'broken_op_faults' = 'broken_ep_faults:Op'")
    assert "ModuleNotFoundError" in text and "no_such_dependency_faults" in text
    assert "\n" not in text


# ------------------------------------------------------------------------------------------
# 10. switching the optimizer on the command line
# ------------------------------------------------------------------------------------------

LBFGS_CONFIG = {"trainer": {"max_epochs": 1, "check_val_every_n_epoch": DROP,
                             "default_root_dir": "run"},
                 "model": {"operator_kwargs": DROP, "hidden": 2, "optimizer": "lbfgs",
                           "optimizer_kwargs": {"max_iter": 5, "history_size": 3}}}
"""The sections of :func:`small_config`: a Zhao-Tan operator and 2 sigmoids by L-BFGS."""


@pytest.mark.parametrize(("optimizer", "cls"), [("adam", "Adam"), ("cg", "PowellBealeCG")])
def test_switching_the_optimizer_keeps_lbfgs_kwargs(clean_path: Path, capsys, optimizer: str,
                                                    cls: str) -> None:
    small_config(clean_path, "c.yaml", **LBFGS_CONFIG)
    line = error_line(capsys, "fit", "--config", "c.yaml", "--model.optimizer", optimizer)
    assert f"--model.optimizer {optimizer} keeps the config's model.optimizer_kwargs" in line
    assert f"{cls} takes no history_size, max_iter" in line
    assert "reset them with --model.optimizer_kwargs '{}'" in line
    assert not (clean_path / "run").exists()


def test_a_candidate_that_switches_the_optimizer(clean_path: Path, capsys) -> None:
    """A model.select candidate ``{optimizer: adam}`` on the section's L-BFGS kwargs: one
    line naming the candidate, before any candidate trains."""
    small_config(clean_path, "c.yaml", **{**LBFGS_CONFIG, "model": {
        **LBFGS_CONFIG["model"], "select": [{}, {"optimizer": "adam"}]}})
    line = error_line(capsys, "fit", "--config", "c.yaml")
    assert "model.select[1] {'optimizer': 'adam'}: optimizer_kwargs ['history_size', " in line
    assert "--model.optimizer_kwargs '{}'" in line
    assert not (clean_path / "run").exists()


def test_optimizer_kwargs_of_another_optimizer_in_python(clean_path: Path) -> None:
    with pytest.raises(ValueError, match=r"optimizer_kwargs \['lr'\] are not keyword "
                                         r"arguments of optimizer='cg' \(PowellBealeCG takes"):
        InverseHysteresisModule(operator=None, hidden=2, optimizer="cg",
                                optimizer_kwargs={"lr": 0.1})
    module = InverseHysteresisModule(operator=None, hidden=2, optimizer="adam",
                                     optimizer_kwargs={"betas": (0.8, 0.9)})
    assert module.hparams.optimizer_kwargs == {"betas": (0.8, 0.9)}


# ------------------------------------------------------------------------------------------
# smaller: --config data.csv, a float64 input to a float32 network
# ------------------------------------------------------------------------------------------

def test_config_that_is_a_data_file(clean_path: Path, capsys) -> None:
    rows = "".join(f"{i},{i * i}\n" for i in range(200))
    (clean_path / "data.csv").write_text("x,y\n" + rows)
    (clean_path / "data").write_text("x,y\n" + rows)
    line = error_line(capsys, "fit", "--config", "data.csv")
    assert line == ("torchhys fit: error: --config data.csv is not a YAML config (a config "
                    "is a YAML mapping of sections: model:, data:, trainer:); a .csv data "
                    "file goes to --data.path data.csv")
    line = error_line(capsys, "fit", "--config=data")
    assert "--config data is not a YAML config" in line and "'x,y'" in line
    assert "199,39601" not in line


def test_float64_input_to_a_float32_network() -> None:
    net = InverseHysteresisNet("eiho", 4)
    x = torch.linspace(0.0, 1.0, 20, dtype=torch.float64)
    expected = (r"^x is float64 but the network is float32: convert the input "
                r"\(x.to\(torch.float32\)\) or the network \(network.to\(torch.float64\)\)$")
    with pytest.raises(TypeError, match=expected):
        net(x)
    with pytest.raises(TypeError, match=expected):
        net.fit_normalization(x, x.square())
    module = InverseHysteresisModule(operator=None, hidden=2)
    with pytest.raises(TypeError, match=expected):
        module(x)
    y, _ = net(x.float())  # the network's own dtype works, and so does a converted network
    assert y.dtype == torch.float32 and net.double()(x)[0].dtype == torch.float64


@pytest.mark.parametrize("name", ["duhem", "play_hysteresis"])
def test_float64_input_to_a_float32_feedback_element(name: str) -> None:
    op = example_of(name).build()
    assert any(n.startswith("net.") for n, _ in op.named_parameters())
    with pytest.raises(TypeError, match=r"^x is float64 but the \w+ operator is float32"):
        op(torch.linspace(0.0, 1.0, 20, dtype=torch.float64))


def test_a_narrower_input_is_widened_to_the_network() -> None:
    """float32 into a float64 network (torch's default dtype into a 64-true fit) is widened,
    as before the dtype check: the same output as the float64 input, in float64."""
    net = InverseHysteresisNet("eiho", 4).double()
    x = torch.linspace(0.0, 1.0, 20, dtype=torch.float32)
    y, _ = net(x)
    assert y.dtype == torch.float64
    torch.testing.assert_close(y, net(x.double())[0], rtol=0, atol=0)
    op = example_of("duhem").build().double()
    z, _ = op(x)
    assert z.dtype == torch.float64
    torch.testing.assert_close(z, op(x.double())[0], rtol=0, atol=0)
