"""deploy/c/controller.c: the fixed-rate C controller over a generated compensator.

deploy/c/build.sh builds it with the float64 C files of the example compensator
(deploy/c/example_comp.py: the network of configs/compensator.yaml, normalization and output
layer fitted on a loop); it runs 1000 samples unpaced and 200 at --rate 1000 (sleeping, and
spinning), and its CSV (``y_ref,u``) equals the Python compensator
(``torchhys.deploy.streaming.StreamingCompensator``) within 1e-12 of the commands' scale, the
counters equal; the latency (and, paced, the jitter) lines are printed. Skipped without a C
compiler.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from torchhys.deploy.streaming import StreamingCompensator

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy" / "c"
CC = shutil.which("cc") or shutil.which("gcc")
pytestmark = pytest.mark.skipif(CC is None or shutil.which("bash") is None,
                                reason="no C compiler (cc or gcc) or bash on PATH")


def example_comp():
    spec = importlib.util.spec_from_file_location("example_comp", DEPLOY / "example_comp.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory):
    """(the controller, the example network), the C files float64 with the prefix ``comp``."""
    from torchhys.deploy.c import to_c

    folder = tmp_path_factory.mktemp("controller_c")
    net = example_comp().example_network()
    to_c(net, folder, prefix="comp")
    done = subprocess.run(["bash", str(DEPLOY / "build.sh"), str(folder), str(folder), "comp"],
                          capture_output=True, text=True, env={**os.environ, "CC": CC})
    assert done.returncode == 0, done.stderr
    return folder / "controller", net


def reference(net, n: int) -> np.ndarray:
    low, high = float(net.in_min), float(net.in_max)
    x = example_comp().reference(low, high, n)  # turning points, ties, an excursion, a NaN
    x[n // 5] = np.inf
    x[n // 4] = -np.inf
    return x


def run(exe: Path, x: np.ndarray, folder: Path, *options: str) -> tuple[np.ndarray, str]:
    src, dst = folder / "ref.csv", folder / "u.csv"
    src.write_text("y_ref\n" + "".join(f"{v!r}\n" for v in x.tolist()))
    done = subprocess.run([str(exe), str(src), str(dst), *options], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    table = np.loadtxt(dst, delimiter=",", skiprows=1, ndmin=2)
    assert dst.read_text().splitlines()[0] == "y_ref,u"
    np.testing.assert_array_equal(table[:, 0], x)  # the reference read back exactly
    return table[:, 1], done.stdout


def python_commands(net, x: np.ndarray) -> tuple[np.ndarray, int, int]:
    """The commands of the Python compensator's step, sample by sample, and its counters."""
    comp = StreamingCompensator(net)
    xt = torch.tensor(x, dtype=torch.float64)
    with torch.no_grad():
        u = np.array([float(comp.step(xt[i:i + 1])) for i in range(len(x))])
    return u, int(comp.nonfinite_count()), int(comp.out_of_range_count())


def check(report: str, paced: bool) -> None:
    latency = re.search(r"^latency median_us ([0-9.]+) p99_us ([0-9.]+) max_us ([0-9.]+)$",
                        report, re.M)
    assert latency, report
    median, p99, top = map(float, latency.groups())
    assert 0 < median <= p99 <= top
    assert bool(re.search(r"^jitter median_us -?[0-9.]+ p99_us", report, re.M)) == paced


@pytest.mark.parametrize(("n", "options"), [
    (1000, ()),
    (200, ("--rate", "1000")),
    (200, ("--rate", "1000", "--spin")),
])
def test_the_controller_equals_the_python_compensator(built, n: int, options: tuple,
                                                      tmp_path: Path) -> None:
    exe, net = built
    x = reference(net, n)
    u, report = run(exe, x, tmp_path, *options)
    expected, nonfinite, out_of_range = python_commands(net, x)
    assert np.isfinite(u).all()
    assert np.max(np.abs(u - expected)) <= 1e-12 * max(1.0, np.max(np.abs(expected)))
    assert f"nonfinite {nonfinite} out_of_range {out_of_range}" in report
    assert nonfinite == 3 and out_of_range > 0
    assert f"samples {n} " in report
    check(report, paced=bool(options))


def test_bad_options_are_refused(built, tmp_path: Path) -> None:
    exe, _ = built
    for options, message in [(["--rate", "fast"], "--rate"), (["--cpu", "x"], "--cpu"),
                              (["--bogus"], "unknown option")]:
        done = subprocess.run([str(exe), "-", str(tmp_path / "u.csv"), *options], input="",
                              capture_output=True, text=True)
        assert done.returncode == 2 and message in done.stderr, done.stderr
    done = subprocess.run([str(exe), str(tmp_path / "missing.csv"), str(tmp_path / "u.csv")],
                          capture_output=True, text=True)
    assert done.returncode == 1 and "REF.csv" in done.stderr
