"""deploy/c/cortex_m4.sh: the generated float32 C cross-compiled for a Cortex-M4 with hardware
float, run under QEMU (mps2-an386, semihosting through newlib's rdimon) and compared with the
same files built by the host's cc: the commands within 1e-4 of their scale (the float32 bound
of docs/deployment.md), the counters and the state's size equal. Slow; skipped
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


@pytest.mark.slow
@pytest.mark.skipif(bool(MISSING), reason=f"no {', '.join(MISSING)} on PATH: apt-get install -y "
                    "gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm")
@pytest.mark.skipif(CC is None, reason="no host C compiler (cc or gcc) on PATH")
def test_the_compensator_on_a_cortex_m4_under_qemu_equals_the_host(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHON": sys.executable, "CC": CC}
    done = subprocess.run(["bash", str(SCRIPT), str(tmp_path)], capture_output=True,
                          text=True, env=env, timeout=600)
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
