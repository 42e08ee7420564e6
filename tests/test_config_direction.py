"""Every shipped config's model, fitted and exported as a compensator, keeps its direction
over 100 times its training range.

Each config is fitted as a user would run it (``torchhys fit --config``), on a short record
(the first 400 rows of its own data file; the paper's simulation for the simulation
configs) with few epochs: what is tested is the exported command's direction far outside
the training range, whatever the fit. The exported file (``torchhys export``, TorchScript)
is swept from the top of the training range to 100 times it, down to -100 times the range's
largest magnitude and back: the command never moves against the input's direction
(``torchhys.deploy.streaming``: the input clamp and the direction guard) and each ramp ends on its
side of the command range (a rising compensator at the top of what it commanded on the
ramp up, the bottom on the ramp down). ``preisach_forward.yaml`` is a forward model (field
to flux density), exported all the same; ``paper_simulation_eiho.yaml`` reproduces the
paper's per-segment EIHO, which reads the target (not causal): its export is refused with a
one-line error, checked here. ``conditions.yaml`` (the MR damper's force against its
position, at the middle of its coil voltages) has no clear trend and so no direction guard:
its command is checked to be finite, within its limits and constant wherever the clamp gives
the model one input.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import yaml

from torchhys.deploy.export import load_torchscript

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = sorted((ROOT / "configs").glob("*.yaml"))


def _short_copy(path: Path, out: Path, rows: int = 400) -> Path:
    """The first ``rows`` data rows of a CSV file (with its header and comment lines)."""
    lines = path.read_text().splitlines()
    head = 0
    while lines[head].lstrip().startswith("#"):
        head += 1
    out.write_text("\n".join(lines[: head + 1 + rows]) + "\n")
    return out


def _torchhys(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, "-m", "torchhys", *args], cwd=ROOT,
                          capture_output=True, text=True, timeout=900, env=env)


@pytest.mark.slow
@pytest.mark.parametrize("config", CONFIGS, ids=[c.stem for c in CONFIGS])
def test_exported_config_model_keeps_its_direction(config: Path, tmp_path: Path) -> None:
    cfg = yaml.safe_load(config.read_text())
    args = ["fit", "--config", str(config), f"--trainer.default_root_dir={tmp_path}",
            "--trainer.max_epochs=3", "--trainer.enable_progress_bar=false"]
    data = cfg.get("data") or {}
    if data.get("run_column") is not None:  # recordings chosen by id: the file as it is
        args.append(f"--data.path={ROOT / data['path']}")
    elif data.get("path"):
        args.append(f"--data.path={_short_copy(ROOT / data['path'], tmp_path / 'short.csv')}")
        args.append(f"--data.warmup={min(int(data.get('warmup') or 0), 50)}")
    else:
        args.append("--data.t_end=12.6")
    fit = _torchhys(*args)
    assert fit.returncode == 0, fit.stderr[-3000:]
    ckpt = next(tmp_path.glob("logs/version_*/checkpoints/last.ckpt"))
    out = tmp_path / "comp.pt"
    export = _torchhys("export", "--ckpt", str(ckpt), "--format", "torchscript",
                       "--out", str(out))
    segment = any(isinstance(op, dict) and op.get("name") == "eiho_segment"
                  for op in (cfg["model"].get("operator") or []))
    segment |= cfg["model"].get("operator") == "eiho_segment"
    if segment:  # the paper's per-segment EIHO reads the target: no compensator, refused
        assert export.returncode == 2
        assert "cannot be deployed" in export.stderr.strip().splitlines()[-1]
        return
    assert export.returncode == 0, export.stderr[-3000:]
    m = load_torchscript(out)
    meta = m.torchhys_metadata
    d = int(meta["direction"])
    n_cond = int(meta.get("n_conditions", "0"))
    # the MR damper's force against its position has no clear trend (MIN_TREND): no guard
    assert d in (1, -1) or (config.stem == "conditions" and d == 0)
    low, high = float(meta["low"]), float(meta["high"])
    lo_in, hi_in = float(meta["input_low"]), float(meta["input_high"])
    big = 100.0 * max(abs(lo_in), abs(hi_in))
    f64 = {"dtype": torch.float64}
    up1 = torch.linspace(hi_in, big, 500, **f64)
    down = torch.linspace(big, -big, 2000, **f64)
    up2 = torch.linspace(-big, big, 2000, **f64)
    x = torch.cat([up1, down, up2])
    with torch.no_grad():
        if n_cond:  # at the middle of the conditions' clamp bounds
            mid = [(float(a) + float(b)) / 2 for a, b in zip(
                meta["condition_low"].split(","), meta["condition_high"].split(","),
                strict=True)]
            u = m(x, torch.tensor(mid, **f64).expand(x.numel(), n_cond))
        else:
            u = m(x)
    assert bool(torch.isfinite(u).all()) and bool(((u >= low) & (u <= high)).all())
    du, dx = u.diff(), x.diff()
    if d == 0:  # no guard: beyond the clamp the model sees one input, its command stays
        beyond = (x[1:] > hi_in) & (x[:-1] > hi_in) | (x[1:] < lo_in) & (x[:-1] < lo_in)
        assert bool(beyond.any()) and int((du[beyond] != 0).sum()) == 0
        return
    assert int(((d * du * dx) < 0).sum()) == 0
    assert int(((dx == 0) & (du != 0)).sum()) == 0
    n2 = up1.numel() + down.numel()
    # 100x below the range the command is at the low side of where 100x above it ends (with
    # hysteresis the first visit of a level, from a fresh state, may differ from later ones:
    # the ramps after the first are compared)
    top, bottom = (u[-1], u[n2 - 1]) if d > 0 else (u[n2 - 1], u[-1])
    assert float(top) >= float(bottom)
    assert int(m.out_of_range_count()) == 0  # forward() does not touch the stored state
