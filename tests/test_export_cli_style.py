"""``torchhys export`` in ``torchhys fit``'s style: underscores (``--ckpt_path``), a YAML
``--config`` of its options that the command line overrides, ``--print_config``, and the
required options named where neither gives them."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
import yaml

sys.path.insert(0, str(Path(__file__).parent))
from test_export_cli import lightning_ckpt, trained  # noqa: E402

from torchhys.cli.export import main  # noqa: E402
from torchhys.deploy.export import load_torchscript  # noqa: E402


@pytest.fixture()
def ckpt(tmp_path: Path) -> Path:
    torch.save(lightning_ckpt(trained()), tmp_path / "m.ckpt")
    return tmp_path / "m.ckpt"


def test_underscores_as_fit_spells_them(ckpt: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "a.pt"
    assert main(["--ckpt_path", str(ckpt), "--format", "torchscript", "--out", str(out),
                 "--input_margin", "0.2", "--limits", "-1", "1"]) == 0
    module = load_torchscript(out)
    span = float(module.in_high - module.in_low)
    assert "input clamped to" in capsys.readouterr().out
    again = tmp_path / "b.pt"
    assert main([f"--ckpt-path={ckpt}", "--format=torchscript", f"--out={again}",
                 "--input-margin=0.2", "--limits", "-1", "1"]) == 0
    assert float(load_torchscript(again).in_high - load_torchscript(again).in_low) == span


def test_a_config_file_gives_the_options_and_the_command_line_overrides(
        ckpt: Path, tmp_path: Path, capsys) -> None:
    cfg = tmp_path / "export.yaml"
    cfg.write_text(yaml.safe_dump({"ckpt_path": str(ckpt), "format": "torchscript",
                                   "out": str(tmp_path / "c.pt"), "limits": [-0.5, 0.5],
                                   "input_margin": 0.1}))
    assert main(["--config", str(cfg)]) == 0
    assert float(load_torchscript(tmp_path / "c.pt").high) == 0.5
    assert main(["--config", str(cfg), "--limits", "-0.25", "0.25", "--out",
                 str(tmp_path / "d.pt")]) == 0
    assert float(load_torchscript(tmp_path / "d.pt").high) == 0.25
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        main(["--config", str(cfg), "--print_config", "--dtype", "float32"])
    assert stop.value.code == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["ckpt"] == str(ckpt) and printed["limits"] == [-0.5, 0.5]
    assert printed["dtype"] == "float32" and printed["format"] == "torchscript"


@pytest.mark.parametrize(("content", "message"), [
    ({"formats": "c"}, "'formats' is not an option of this command"),
    ({"format": "zip"}, "format: 'zip' is not one of"),
    ("- a\n- b\n", "expected a mapping of options"),
    ("a: [1,\n", "not YAML"),
])
def test_a_bad_config_is_one_line_naming_it(tmp_path: Path, capsys, content: object,
                                            message: str) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(content if isinstance(content, str) else yaml.safe_dump(content))
    with pytest.raises(SystemExit) as stop:
        main(["--config", str(cfg)])
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert stop.value.code == 2 and message in err and str(cfg) in err, err


def test_the_required_options_are_named(capsys) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--format", "c"])
    err = capsys.readouterr().err
    assert stop.value.code == 2
    assert "the following arguments are required: --ckpt, --out" in err
