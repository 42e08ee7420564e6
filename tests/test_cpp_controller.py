"""The C++ controller (deploy/cpp) runs the exported compensator like Python does."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from torchhys import EIHO, Backlash, InverseHysteresisNet
from torchhys.deploy.export import load_torchscript, to_aoti, to_torchscript

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [ROOT / "deploy" / "cpp" / "controller.cpp", ROOT / "deploy" / "cpp" / "build.sh"]


def compiler() -> str | None:
    return shutil.which(os.environ.get("CXX", "g++"))


def controller_binary() -> Path:
    """Build once per source/torch version; later runs reuse build/cpp-test/<hash>."""
    if compiler() is None:
        reason = "no C++ compiler found (set CXX or install g++): C++ controller not tested"
        print(reason)
        pytest.skip(reason)
    h = hashlib.sha256(torch.__version__.encode())
    for src in SOURCES:
        h.update(src.read_bytes())
    out = ROOT / "build" / "cpp-test" / h.hexdigest()[:16]
    binary = out / "controller"
    if not binary.exists():
        env = dict(os.environ, PYTHON=sys.executable)
        res = subprocess.run(["bash", str(SOURCES[1]), str(out)], env=env, capture_output=True,
                             text=True, timeout=600)
        assert res.returncode == 0, res.stderr[-4000:]
    return binary


def trained_like_net(deployed: bool = False) -> InverseHysteresisNet:
    """A dominant-rule EIHO network (the general step), or the deployed configuration:
    the threshold-0 re-based recent-rule EIHO with its own short step."""
    torch.manual_seed(0)
    t = torch.linspace(0, 30, 800)
    x = 3 * torch.sin(t) + torch.sin(2.3 * t)
    eiho = EIHO(a=0.8, rule="recent", output="branch") if deployed else \
        EIHO(a=1.0, rule="dominant", threshold=0.05)
    net = InverseHysteresisNet([eiho, Backlash(torch.linspace(0.0, 2.0, 6))], hidden=16)
    net.fit_normalization(x, 0.8 * x)
    return net


def reference(tmp_path: Path) -> tuple[Path, torch.Tensor]:
    t = torch.linspace(0, 40, 1500)
    y = (2.5 * torch.sin(t) + 0.7 * torch.sin(3.7 * t)).float()
    y[700] = float("nan")
    path = tmp_path / "ref.csv"
    with open(path, "w") as f:
        f.write("y_ref\n")
        for v in y.tolist():
            f.write(f"{v:.9g}\n")
    return path, y


def run_controller(binary: Path, model: Path, ref: Path, out: Path) -> tuple[str, torch.Tensor]:
    res = subprocess.run([str(binary), str(model), str(ref), str(out), "--rate", "0"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    rows = out.read_text().splitlines()[1:]
    u = torch.tensor([float(r.split(",")[1]) for r in rows], dtype=torch.float64)
    return res.stdout, u


def check_summary(stdout: str, n: int) -> None:
    fields = stdout.split()
    values = dict(zip(fields[::2], fields[1::2], strict=False))
    assert int(values["samples"]) == n
    assert int(values["nonfinite"]) == 1
    assert float(values["median_us"]) > 0 and float(values["p99_us"]) >= float(values["median_us"])


@pytest.mark.parametrize("deployed", [False, True])
def test_cpp_torchscript_controller_matches_python(tmp_path: Path, deployed: bool) -> None:
    binary = controller_binary()
    model = tmp_path / "comp.pt"
    to_torchscript(trained_like_net(deployed), model, limits=(-4.0, 4.0))
    ref, y = reference(tmp_path)
    stdout, u = run_controller(binary, model, ref, tmp_path / "out.csv")
    expected = load_torchscript(model)(y).double()
    torch.testing.assert_close(u, expected, rtol=0, atol=1e-6)
    assert torch.isfinite(u).all()
    check_summary(stdout, y.numel())


def test_controller_rejects_bad_arguments(tmp_path: Path) -> None:
    binary = controller_binary()
    res = subprocess.run([str(binary)], capture_output=True, text=True)
    assert res.returncode == 2 and "usage" in res.stderr
    res = subprocess.run([str(binary), str(tmp_path / "missing.pt"), "a.csv", "b.csv"],
                         capture_output=True, text=True)
    assert res.returncode == 1 and "error" in res.stderr


@pytest.mark.slow
def test_cpp_aoti_controller_matches_python(tmp_path: Path) -> None:
    binary = controller_binary()
    model = tmp_path / "comp.pt2"
    net = trained_like_net()
    to_aoti(net, model, limits=(-4.0, 4.0))
    ref, y = reference(tmp_path)
    stdout, u = run_controller(binary, model, ref, tmp_path / "out.csv")
    expected = to_torchscript(net, tmp_path / "comp.pt", limits=(-4.0, 4.0))(y).double()
    torch.testing.assert_close(u, expected, rtol=0, atol=1e-6)
    check_summary(stdout, y.numel())


@pytest.mark.slow
def test_cmake_build_runs_like_python(tmp_path: Path) -> None:
    """deploy/cpp/CMakeLists.txt builds the same controller (skipped without cmake)."""
    cmake = shutil.which("cmake")
    if cmake is None or compiler() is None:
        reason = "cmake or a C++ compiler not found: CMake build not tested"
        print(reason)
        pytest.skip(reason)
    build = tmp_path / "build"
    prefix = torch.utils.cmake_prefix_path
    for cmd in ([cmake, "-S", str(ROOT / "deploy" / "cpp"), "-B", str(build),
                 f"-DCMAKE_PREFIX_PATH={prefix}"], [cmake, "--build", str(build)]):
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    model = tmp_path / "comp.pt"
    to_torchscript(trained_like_net(deployed=True), model, limits=(-4.0, 4.0))
    ref, y = reference(tmp_path)
    stdout, u = run_controller(build / "controller", model, ref, tmp_path / "out.csv")
    torch.testing.assert_close(u, load_torchscript(model)(y).double(), rtol=0, atol=1e-6)
    check_summary(stdout, y.numel())
