"""The shipped compensator configs end to end: fitted with ``torchhys fit --config``, exported
with ``torchhys export`` as TorchScript, C99, FMU, CasADi and ONNX, the C step (compiled with
``cc -std=c99 -O2 -Wall -Wextra -Werror -pedantic``), the FMU (FMPy, where the fmu extra is
installed), the CasADi function (where casadi is) and the ONNX step (ONNX Runtime) reproduce
the TorchScript file's commands and final state (the FMU: its commands and counters) within
1e-12 of their scale (float64) and its counters, on a record the model was not trained on:
held-out measurements, then a stress record around the training range (turning points, ties,
signed zeros, samples beyond the range, NaN and inf; tests/_export_helpers.py).

- ``configs/compensator.yaml`` (a re-based EIHO and 16 plays, 64 sigmoids): fitted 2 epochs
  on the first 400 rows of its example file; held out: the file's later rows.
- ``configs/measured.yaml`` on the MnZn ferrite's B-H loops (as docs/training.md runs it:
  trained on the 8 and 80 A/m loops), where its cross-validation chooses the B-H
  compensator (40 stops beside the inverse of a graded 40-level Preisach model); held
  out: the 16 and 40 A/m loops.

Slow: the measured config tries its 11 candidates.
"""

from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import numpy as np
import pytest
import torch
from _export_helpers import (
    CC,
    FLOAT64_RTOL,
    NO_CC,
    assert_equal_runs,
    compile_harness,
    gap,
    record,
    run_c,
    stepped,
)

pytest.importorskip("lightning")
from _training_helpers import cli  # noqa: E402

from torchhys.cli.export import main as export_main  # noqa: E402
from torchhys.deploy.export import load_torchscript  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FERRITE = ROOT / "examples" / "data" / "mnzn_ferrite_bh_loops.csv"


def rows(path: Path) -> list[dict]:
    with path.open() as fh:
        return list(csv.DictReader(ln for ln in fh if not ln.startswith("#")))


def compensator(tmp_path: Path) -> tuple[list[str], np.ndarray]:
    """The fit's arguments and the held-out input (the example file after row 400)."""
    lines = (ROOT / "examples" / "data" / "bouc_wen.csv").read_text().splitlines()
    short = tmp_path / "short.csv"
    short.write_text("\n".join(lines[:401]) + "\n")
    held_out = np.array([float(r["response"]) for r in rows(ROOT / "examples/data/bouc_wen.csv")
                         ][400:2400])
    return ["--config", "configs/compensator.yaml", f"--data.path={short}",
            "--data.warmup=50", "--trainer.max_epochs=2"], held_out


def measured(tmp_path: Path) -> tuple[list[str], np.ndarray]:
    """As tests/test_cli.py's ferrite run: train on loops 0 and 3, hold out 1 and 2."""
    table = rows(FERRITE)
    held_out = np.array([float(r["B_T"]) for r in table if r["loop"] in ("1", "2")] * 3)
    return ["--config", "configs/measured.yaml", "--data.path", str(FERRITE),
            "--data.input_column", "B_T", "--data.target_column", "H_Apm",
            "--data.time_column", "null", "--data.run_column", "loop", "--data.warmup", "0",
            "--data.split_by", "recording", "--data.train_recordings", "[0, 3]",
            "--data.val_recordings", "[]", "--data.test_recordings", "[1, 2]",
            "--data.repeat", "3"], held_out


@pytest.mark.skipif(CC is None, reason=NO_CC)
@pytest.mark.parametrize("config", [
    pytest.param(compensator, id="compensator"),
    pytest.param(measured, id="measured", marks=pytest.mark.slow),
])
def test_a_fitted_config_in_c_and_onnx_equals_torchscript(config, tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch,
                                                          capsys) -> None:
    args, held_out = config(tmp_path)
    monkeypatch.chdir(ROOT)  # the configs name their example files relative to the repository
    cli(monkeypatch, "fit", *args, f"--trainer.default_root_dir={tmp_path / 'run'}",
        "--trainer.enable_progress_bar=false")
    ckpt = tmp_path / "run/logs/version_0/checkpoints/last.ckpt"
    out = {"torchscript": tmp_path / "comp.pt", "c": tmp_path, "onnx": tmp_path / "comp.onnx"}
    for fmt, path in out.items():
        assert export_main(["--ckpt", str(ckpt), "--format", fmt, "--out", str(path)]) == 0
    capsys.readouterr()
    scripted = load_torchscript(out["torchscript"])
    x = np.concatenate([held_out, record(float(scripted.in_low), float(scripted.in_high),
                                         n=2000, seed=5)])
    ts = stepped(scripted, x, torch.float64)
    header = (tmp_path / "torchhys_comp.h").read_text()
    if config is measured:  # the model the docs call the B-H compensator
        assert "operators [StopPrandtlIshlinskii, PreisachInverse]" in header, header[:600]
    c = run_c(compile_harness(tmp_path, state=ts["state"]), x, ts["state"])
    gaps = {"c": assert_equal_runs(c, ts, FLOAT64_RTOL)}
    if importlib.util.find_spec("fmpy") is not None:  # the fmu extra
        from test_export_fmu import run_fmu

        fmu = tmp_path / "comp.fmu"
        assert export_main(["--ckpt", str(ckpt), "--format", "fmu", "--out", str(fmu)]) == 0
        gaps["fmu"] = assert_equal_runs(run_fmu(fmu, x), ts, FLOAT64_RTOL)
    if importlib.util.find_spec("casadi") is not None:  # the casadi extra
        from torchhys.deploy.export_casadi import flatten, load_casadi

        path = tmp_path / "comp.casadi"
        assert export_main(["--ckpt", str(ckpt), "--format", "casadi", "--out", str(path)]) == 0
        fn, flat, u = load_casadi(path), np.zeros(len(flatten(ts["state"]))), []
        for v in x:
            command, flat = fn(float(v), flat)
            u.append(float(command))
        gaps["casadi"] = max(gap(np.array(u), ts["u"]),
                             gap(np.asarray(flat).reshape(-1), flatten(ts["state"])))
        assert gaps["casadi"] <= FLOAT64_RTOL, gaps
    capsys.readouterr()
    pytest.importorskip("onnxruntime", reason='no onnxruntime: pip install "torchhys[onnx]"')
    from torchhys.deploy.export_onnx import load_onnx

    gaps["onnx"] = assert_equal_runs(stepped(load_onnx(out["onnx"]), x, torch.float64), ts,
                                     FLOAT64_RTOL)
    assert ts["nonfinite"] == int((~np.isfinite(x)).sum()) and ts["out_of_range"] > 0
    print(f"largest gaps against TorchScript: {gaps}")
