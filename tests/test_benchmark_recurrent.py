"""benchmarks/recurrent (``python -m benchmarks.recurrent``): the smoke modes of its two parts,
the models' sizes against their formulas, the C steps against the torch modules, and the
RTNeural driver against the torch modules where an RTNeural checkout is given
(``RTNEURAL_DIR``)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from benchmarks.recurrent import accuracy, cli, latency

ROOT = Path(__file__).resolve().parents[1]
CC = shutil.which("cc") or shutil.which("gcc")
RTNEURAL = os.environ.get("RTNEURAL_DIR")


def run(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "benchmarks.recurrent", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=600, env=env)


def rows(out: str, header: str) -> dict[str, list[str]]:
    """The rows of the markdown table whose header starts ``| header``, by first cell."""
    table, inside = {}, False
    for line in out.splitlines():
        if line.startswith(f"| {header}"):
            inside = True
        elif line.startswith("|---"):
            continue
        elif inside and line.startswith("|"):
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            table[cells[0]] = cells[1:]
        elif inside:
            inside = False
    return table


def test_parameter_counts_follow_the_layer_formulas() -> None:
    # GRU: 3 (in h + h h + 2 h); LSTM: 4 (...); read-out h + 1; plays: one width each
    def gru(i, h): return 3 * (i * h + h * h + 2 * h)
    def lstm(i, h): return 4 * (i * h + h * h + 2 * h)
    assert accuracy.n_params(accuracy.PlaysGRU(8, 8)) == 8 + gru(9, 8) + 9
    assert accuracy.n_params(accuracy.Recurrent("gru", 16)) == gru(1, 16) + 17
    assert accuracy.n_params(accuracy.Recurrent("lstm", 16)) == lstm(1, 16) + 17
    with pytest.raises(ValueError, match="kind must be 'gru' or 'lstm'"):
        accuracy.Recurrent("rnn", 4)


def test_models_are_causal_and_map_batch_time_to_batch_time() -> None:
    torch.manual_seed(0)
    x = torch.randn(3, 40)
    for make in accuracy.MODELS.values():
        m = make()
        y = m(x)
        assert y.shape == x.shape
        x2 = x.clone()
        x2[:, 25:] += 1.0  # a change after sample 24 leaves the outputs before it
        assert torch.equal(m(x2)[:, :25], y[:, :25])


def test_tasks_split_training_from_validation_as_their_protocols_do() -> None:
    t = accuracy.task("mr_damper_3.21V")
    assert t.warmup < t.cut < t.x.shape[1]
    assert t.cut - t.warmup == pytest.approx(0.75 * (t.x.shape[1] - t.warmup), abs=1)
    b = accuracy.bouc_wen()
    assert b.cut == b.x.shape[1] - accuracy.PERIOD  # the 5th period validates
    ms = b.tests["multisine"][0]
    assert ms[2] == len(ms[0]) // 2  # two periods run, the second scored
    with pytest.raises(ValueError, match="--data: expected 'bouc_wen'"):
        accuracy.task("nope")


@pytest.mark.slow  # a subprocess that imports torch and trains (about 5 s)
def test_accuracy_quick_prints_every_row() -> None:
    p = run("accuracy", "--quick", "--data", "mr_damper_3.21V", "--models",
            "8 plays + GRU 8", "GRU 8")
    assert p.returncode == 0, p.stderr
    table = rows(p.stdout, "mr_damper_3.21V model")
    assert list(table) == ["line", "poly", "8 plays + GRU 8", "GRU 8"]
    assert table["8 plays + GRU 8"][0] == str(8 + 3 * (9 * 8 + 64 + 16) + 9)
    for cells in table.values():
        rmse = float(cells[2].split()[0])
        assert 0 < rmse < 1e4  # force in N; the line scores about 610


def test_bad_data_name_is_one_line_error(capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as err:
        cli.main(["accuracy", "--data", "nope"])
    assert err.value.code == 2
    assert "--data: expected 'bouc_wen'" in capsys.readouterr().err.splitlines()[-1]


@pytest.mark.slow  # three exports to C and compiles
@pytest.mark.skipif(CC is None, reason="no C compiler (cc or gcc) on PATH")
def test_latency_quick_without_rtneural_times_the_c_steps() -> None:
    env = {k: v for k, v in os.environ.items() if k != "RTNEURAL_DIR"}
    p = run("latency", "--quick", env=env)
    assert p.returncode == 0, p.stderr
    assert "RTNeural columns skipped: no --rtneural DIR and no RTNEURAL_DIR" in p.stdout
    table = rows(p.stdout, "model")
    assert list(table) == ["LSTM 16", "GRU 16", "8 plays + GRU 8 + linear"]
    for cells in table.values():
        assert float(cells[0]) > 0
        assert float(cells[-1]) < 1e-12  # the C step equals the torch module (float64)


def test_rtneural_dir_names_what_is_missing(tmp_path: Path) -> None:
    assert latency.rtneural_dir(tmp_path)[0] is None
    assert "holds no RTNeural/RTNeural.h" in latency.rtneural_dir(tmp_path)[1]


@pytest.mark.slow  # C++ compiles of RTNeural
@pytest.mark.skipif(not RTNEURAL or shutil.which("c++") is None,
                    reason="no RTNEURAL_DIR (an RTNeural checkout) or no c++ on PATH")
@pytest.mark.parametrize("kind", ["lstm", "gru"])
def test_rtneural_driver_computes_the_torch_module(kind: str, tmp_path: Path) -> None:
    torch.manual_seed(1)
    m = accuracy.Recurrent(kind, 8).double().eval()
    exe = latency.build_rtneural(m.rnn, m.out, Path(RTNEURAL), tmp_path, ("-O2",), False)
    got = latency.outputs(exe, 300)
    assert (got - latency.reference(m, 300)).abs().max() < 1e-12
