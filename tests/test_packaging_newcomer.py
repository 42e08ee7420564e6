"""What a new user meets at import and in the first run: ``import torchhys`` without SciPy's
ODE solvers, one line when the compiled kernels cannot be built, and the loggers of
``torchhys fit`` by a short name (``--trainer.logger csv``, ``tensorboard``)."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

import torchhys.functional._compile as compile_
from torchhys.functional import _kernel
from torchhys.functional.backlash import backlash

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str, **env: str) -> subprocess.CompletedProcess:
    """``code`` in a fresh interpreter outside the checkout, with ``env`` added."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=Path(sys.prefix), env={**os.environ, **env}, timeout=300)


# --- lazy imports ---------------------------------------------------------------------------
def test_import_torchhys_does_not_import_scipy_integrate() -> None:
    proc = _python("import torchhys, sys; print('scipy.integrate' in sys.modules)")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "False"


def test_the_plants_load_torchdiffeq_only_for_an_adaptive_solver() -> None:
    """The default Bouc-Wen solver (RK4) needs neither torchdiffeq nor SciPy; ``dopri5``
    loads them on first use, and gives the RK4 response (the cross-check of the module)."""
    proc = _python(
        "import sys, torch\n"
        "from torchhys.plants import bouc_wen\n"
        "t = torch.linspace(0, 6.3, 60, dtype=torch.float64)\n"
        "u = torch.sin(t)\n"
        "y = bouc_wen(u, t, substeps=8)\n"
        "print('torchdiffeq' in sys.modules, 'scipy.integrate' in sys.modules)\n"
        "z = bouc_wen(u, t, method='dopri5', rtol=1e-9, atol=1e-11)\n"
        "print('torchdiffeq' in sys.modules, float((y - z).abs().max()))\n")
    assert proc.returncode == 0, proc.stderr
    first, second = proc.stdout.splitlines()
    assert first == "False False"
    loaded, gap = second.split()
    assert loaded == "True" and float(gap) < 1e-6


# --- the compiled kernels' fallback ---------------------------------------------------------
def _fallback_warnings(caught: list[warnings.WarningMessage]) -> list[str]:
    return [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]


@pytest.fixture
def fresh_kernels(monkeypatch: pytest.MonkeyPatch, tmp_path: Path):
    """The play kernel not yet loaded in this process, nothing warned, an empty kernel cache;
    the real kernel loaded again afterwards."""
    monkeypatch.setattr(compile_, "_warned", set())
    monkeypatch.setenv("TORCHHYS_CACHE", str(tmp_path))
    monkeypatch.delenv("TORCHHYS_DISABLE_KERNEL", raising=False)
    _kernel._load.cache_clear()
    yield
    _kernel._load.cache_clear()


def _play() -> torch.Tensor:
    x = torch.sin(torch.linspace(0, 12.6, 300, dtype=torch.float64)) * 2
    return backlash(x, torch.tensor([0.1, 0.5], dtype=torch.float64))


def test_no_compiler_warns_once_in_one_line_and_the_scan_gives_the_result(
        monkeypatch, fresh_kernels) -> None:
    with _kernel.kernel_enabled(False):
        reference = _play()
    monkeypatch.setattr(compile_.shutil, "which", lambda name: None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = _play()
        _play()
        compile_.build("other", "int f(void) { return 1; }", what="other kernel",
                       fallback="its torch path")
    assert torch.equal(out, reference)
    assert _kernel.kernel_unavailable_reason().startswith("no C compiler found")
    (message,) = _fallback_warnings(caught)  # once, for every kernel
    assert "\n" not in message
    assert message.startswith("no C compiler found (neither 'cc' nor 'gcc' is on the PATH): "
                              "the compiled play-operator kernel")
    assert "slower" in message and "TORCHHYS_DISABLE_KERNEL=1" in message


def test_a_failed_build_warns_once_naming_the_kernel(monkeypatch, fresh_kernels) -> None:
    def fail(compiler, name, source, lib_path):  # noqa: ANN001, ANN202
        raise subprocess.CalledProcessError(1, [compiler, f"{name}.c"], stderr=b"error:\nx")

    monkeypatch.setattr(compile_, "_compile", fail)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _play()
        _play()
    (message,) = _fallback_warnings(caught)
    assert "\n" not in message
    assert message.startswith("could not build the compiled play-operator kernel (")
    assert "the pure-torch scan runs instead (slower" in message
    assert _kernel.kernel_unavailable_reason().startswith("the kernel could not be built")


def test_the_environment_variable_chooses_the_scan_silently(monkeypatch, fresh_kernels) -> None:
    monkeypatch.setenv("TORCHHYS_DISABLE_KERNEL", "1")
    monkeypatch.setattr(compile_.shutil, "which", lambda name: None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _play()
    assert _fallback_warnings(caught) == []


def test_without_a_compiler_the_process_prints_one_warning_line(tmp_path: Path) -> None:
    """As a user sees it: a machine without ``cc``/``gcc`` on the PATH, a play operator and
    a linear filter run: stderr holds one line, the warning, and no echoed source line."""
    env = {k: v for k, v in os.environ.items() if k not in ("CC", "TORCHHYS_DISABLE_KERNEL")}
    env.update(PATH=str(tmp_path), TORCHHYS_CACHE=str(tmp_path / "cache"))
    code = ("import torch\n"
            "from torchhys.functional import backlash, lfilter\n"
            "x = torch.sin(torch.linspace(0, 6.3, 200, dtype=torch.float64))\n"
            "backlash(x, torch.tensor([0.1, 0.3], dtype=torch.float64))\n"
            "lfilter(x, torch.tensor([0.5, 0.5], dtype=torch.float64),\n"
            "        torch.tensor([1.0, -0.2], dtype=torch.float64))\n"
            "print('ran')\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, cwd=tmp_path, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "ran"
    (line,) = proc.stderr.splitlines()
    assert line.startswith("torchhys:0: RuntimeWarning: no C compiler found"), line
