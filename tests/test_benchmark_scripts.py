"""The speed benchmarks run end to end on a short signal and print a row per method (their
numbers, on the full length, are in docs/models.md; here only that the scripts work)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(("script", "methods"), [
    ("preisach.py", ("chunked", "smooth", "materialised", "fit", "step")),
    ("stop_pi.py", ("forward", "backward", "loop", "fit", "step")),
])
def test_benchmark_prints_a_row_per_method(script: str, methods: tuple[str, ...]) -> None:
    out = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--length", "10000", "--repeats",
         "1", "--threads", "1"],
        check=True, capture_output=True, text=True, timeout=300,
    ).stdout
    rows = [line.strip("|").split("|") for line in out.splitlines()
            if line.startswith("| ") and not line.startswith("| method")]
    assert [r[0].split("(")[0].strip() for r in rows] == list(methods)
    for r in rows:
        seconds = float(r[1])
        assert math.isfinite(seconds) and seconds > 0, r
    assert "T=10000" in out
