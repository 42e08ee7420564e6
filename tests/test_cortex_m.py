"""deploy/c/cortex_m4.sh: the generated float32 C cross-compiled for a Cortex-M4 with hardware
float, run under QEMU (mps2-an386, semihosting through newlib's rdimon) and compared with the
same files built by the host's cc: the commands within 1e-4 of their scale (the float32 bound
of docs/deployment.md), the counters and the state's size equal; for the paper's compensator
(the default) and for a composed model (``--model composed``: plays -> nn.GRU(8) -> nn.Linear,
also against the float64 torch compensator). Slow; skipped
without the cross tools (apt-get install -y gcc-arm-none-eabi libnewlib-arm-none-eabi
qemu-system-arm) or a host C compiler."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "deploy" / "c" / "cortex_m4.sh"
MISSING = [t for t in ("arm-none-eabi-gcc", "arm-none-eabi-size", "qemu-system-arm")
           if shutil.which(t) is None]
CC = shutil.which("cc") or shutil.which("gcc")
needs_tools = pytest.mark.skipif(
    bool(MISSING), reason=f"no {', '.join(MISSING)} on PATH: apt-get install -y "
    "gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm")
needs_cc = pytest.mark.skipif(CC is None, reason="no host C compiler (cc or gcc) on PATH")


def run_script(out: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHON": sys.executable, "CC": CC or "cc", "OMP_NUM_THREADS": "1"}
    return subprocess.run(["bash", str(SCRIPT), str(out), *args], capture_output=True,
                          text=True, env=env, timeout=600)


@pytest.mark.slow
@needs_tools
@needs_cc
def test_the_compensator_on_a_cortex_m4_under_qemu_equals_the_host(tmp_path: Path) -> None:
    done = run_script(tmp_path)
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    flash = re.search(r"compensator \(torchhys_comp.o\): flash (\d+) B", out)
    image = re.search(r"image \(mcu.elf, [^)]*\): flash (\d+) B, RAM (\d+) B", out)
    assert flash and image, out
    assert 0 < int(flash.group(1)) < 64 * 1024  # code and weights of the small network
    assert int(image.group(1)) < 256 * 1024 and int(image.group(2)) < 64 * 1024
    assert "state 104 B" in out  # float32: 21 floats, 2 int64 counters, the started flag
    match = re.search(r"QEMU against host cc: (\d+) commands, (\d+) bit-equal, largest "
                      r"difference (\S+) of the scale .*: agree", out)
    assert match, out
    assert int(match.group(1)) == 256 and float(match.group(3)) <= 1e-4
    # the QEMU run printed every command (semihosting worked), the NaN sample was held
    qemu = (tmp_path / "qemu.txt").read_text().splitlines()
    assert qemu[0] == "state_bytes 104" and len(qemu) == 258
    assert qemu[-1].startswith("nonfinite 1 ")


@pytest.mark.slow
@needs_tools
@needs_cc
def test_a_composed_plays_gru_model_on_a_cortex_m4_under_qemu_equals_the_host_and_torch(
        tmp_path: Path) -> None:
    done = run_script(tmp_path, "--model", "composed")
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    flash = re.search(r"compensator \(torchhys_comp.o\): flash (\d+) B \(text \d+, data (\d+)\), "
                      r"RAM (\d+) B; state (\d+) B", out)
    image = re.search(r"image \(mcu.elf, [^)]*\): flash (\d+) B, RAM (\d+) B", out)
    assert flash and image, out
    # code and weights: 4 plays, a GRU of 5 inputs and 8 units (360 floats), a read-out
    assert 1440 < int(flash.group(1)) < 16 * 1024
    assert int(flash.group(2)) == 0 and int(flash.group(3)) == 0  # weights const, no globals
    # float32: held command, 4 plays, 8 GRU units, the guard's last input (14 floats),
    # 2 int64 counters, the started flag and its padding
    assert int(flash.group(4)) == 14 * 4 + 2 * 8 + 8 == 80
    assert int(image.group(1)) < 256 * 1024 and int(image.group(2)) < 64 * 1024
    match = re.search(r"QEMU against host cc: (\d+) commands, (\d+) bit-equal, largest "
                      r"difference (\S+) of the scale .*: agree", out)
    assert match, out
    assert int(match.group(1)) == 256 and float(match.group(3)) <= 1e-4
    torch64 = re.search(r"QEMU against torch float64: (\d+) commands, largest difference "
                        r"(\S+) of the scale \(bound 1e-4\): agree", out)
    assert torch64, out
    assert int(torch64.group(1)) == 256 and float(torch64.group(2)) <= 1e-4
    qemu = (tmp_path / "qemu.txt").read_text().splitlines()
    assert qemu[0] == "state_bytes 80" and len(qemu) == 258
    # the NaN sample (170 of 256) held the last command, and was counted
    assert qemu[1 + 170].split()[1] == qemu[170].split()[1]
    assert qemu[-1].startswith("nonfinite 1 ")
    # the composed model, not the paper's network, was exported
    header = (tmp_path / "gen" / "torchhys_comp.h").read_text()
    assert "model: Composed" in header and "gru.h" in header
    assert "torchhys_comp_real F[14];" in header  # the 14 floats of the state


@needs_tools
def test_the_script_refuses_a_bad_model_in_one_line(tmp_path: Path) -> None:
    done = run_script(tmp_path, "--model", "lstm")
    assert done.returncode == 2
    assert done.stderr.strip() == "cortex_m4.sh: --model must be paper or composed, got 'lstm'"


@pytest.mark.slow
@needs_tools
@needs_cc
def test_the_nlms_adaptive_step_on_a_cortex_m4_under_qemu_equals_the_host(tmp_path: Path
                                                                          ) -> None:
    """--adapt nlms: the paper network's adaptive step (a pair at every sample) bit-equal
    on QEMU and the host, the adaptive counters equal, the step's instruction count
    printed."""
    done = run_script(tmp_path, "--adapt", "nlms")
    assert done.returncode == 0, done.stdout + done.stderr
    out = done.stdout
    match = re.search(r"QEMU against host cc: (\d+) commands, (\d+) bit-equal, .*updates "
                      r"(\d+) skipped (\d+) refused (\d+) \(host: .*: agree", out)
    assert match, out
    assert int(match.group(1)) == 256 and int(match.group(3)) > 100  # it adapted
    steps = re.search(r"step: (\d+) instructions on average over 256 steps", out)
    assert steps and 1000 < int(steps.group(1)) < 1_000_000, out
    header = (tmp_path / "gen" / "torchhys_comp.h").read_text()
    assert "torchhys_comp_step_adapt" in header and "torchhys_comp_real P[" not in header
