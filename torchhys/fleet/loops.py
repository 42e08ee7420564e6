"""A fitted device's loop on a standard sweep, its width and gain: :func:`loop_of`.

The sweep: the model's input (``data.input_column``) driven by a triangle wave between the
lowest and highest input of the device's scored training samples, three periods of
:data:`HALF` samples per ramp, from the lowest; the last period is the loop (the first two
take the model's states from zero onto it). On it, with ``y_up`` and ``y_down`` the
outputs of the rising and the falling ramp at the same inputs:

- **width** = ``max |y_up - y_down| / (max y - min y)``: the largest vertical gap of the
  loop over its output range (0: no hysteresis; the straight line's is 0);
- **gain** = the slope of the least-squares straight line of ``y`` on ``x`` over the loop
  (output units per input unit).

Both are of the fitted model as it was trained, input to target (an inverse model,
``response -> command`` as configs/measured.yaml fits it: its gain is command per
response).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

__all__ = ["HALF", "Loop", "family_name", "loop_metrics", "loop_of", "sweep"]

HALF = 200
"""Samples of each ramp of the standard sweep."""


@dataclass(frozen=True)
class Loop:
    """The loop of the sweep's last period (``x``, ``y``: float64 arrays), its width and
    gain, and the fitted model's family (its operators' ``fit`` names)."""

    x: np.ndarray
    y: np.ndarray
    width: float
    gain: float
    family: str = ""


def sweep(lo: float, hi: float, half: int = HALF, periods: int = 3) -> np.ndarray:
    """The standard sweep: ``periods`` triangle periods from ``lo`` up to ``hi`` and back,
    ``half`` samples per ramp (each ramp's samples the other's reversed)."""
    up = np.linspace(lo, hi, half, dtype=np.float64)
    return np.tile(np.concatenate([up, up[::-1]]), periods)


def loop_metrics(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """``(width, gain)`` of one triangle period ``x`` (rising ramp, then the same inputs
    falling) and its outputs ``y`` (the module docstring's definitions; width NaN for a
    constant output)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    half = x.size // 2
    up, down = y[:half], y[half:][::-1]
    span = float(y.max() - y.min())
    width = float(np.max(np.abs(up - down)) / span) if span > 0 else math.nan
    xc = x - x.mean()
    gain = float(np.dot(xc, y - y.mean()) / np.dot(xc, xc))
    return width, gain


def family_name(config: str | dict) -> str:
    """A candidate's family in a word: its operators' ``fit`` names joined by ``+`` (with
    ``(inverse)`` for an inverse direction), ``line`` for ``operator: null``, else its
    config as JSON."""
    c = json.loads(config) if isinstance(config, str) else dict(config)
    ops = c.get("operator", "?")
    if ops is None:
        return "line"
    if isinstance(ops, dict):
        ops = [ops]
    if not isinstance(ops, list):
        return str(ops)
    names = []
    for op in ops:
        if isinstance(op, dict) and "fit" in op:
            names.append(op["fit"] + ("(inverse)" if op.get("direction") == "inverse" else ""))
        else:
            names.append(json.dumps(op, sort_keys=True) if isinstance(op, dict) else str(op))
    return "+".join(names)


def _input_range(run: Path) -> tuple[float, float]:
    """The lowest and highest input of the device's scored training samples, read as the
    fit read them (its saved config's data section)."""
    from torchhys.cli.train import read_config
    from torchhys.training.data import HysteresisDataModule

    data = read_config(run / "logs" / "version_0" / "config.yaml")["data"]
    dm = HysteresisDataModule(**data)
    dm.setup("fit")
    x, _, _, mask = dm.batches("train")[0][:4]
    scored = x[mask.to(torch.bool)]
    return float(scored.min()), float(scored.max())


def loop_of(run: str | Path, ckpt: str | Path) -> Loop:
    """The loop of the model in the checkpoint ``ckpt`` of the device's run folder ``run``
    (its input range from its training split: the module docstring)."""
    from torchhys.checkpoints import read_checkpoint
    from torchhys.cli.export import build_net

    lo, hi = _input_range(Path(run))
    ck = read_checkpoint(ckpt, "--ckpt_path")
    net = build_net(ck).eval()
    dtype = next((p.dtype for p in net.state_dict().values() if p.is_floating_point()),
                 torch.float64)
    xs = sweep(lo, hi)
    with torch.no_grad():
        ys = net(torch.as_tensor(xs, dtype=dtype))[0].to(torch.float64).numpy()
    last = slice(xs.size - 2 * HALF, xs.size)
    width, gain = loop_metrics(xs[last], ys[last])
    hp = ck.get("hyper_parameters") or {}
    family = family_name({"operator": hp.get("operator")}) if "operator" in hp else ""
    return Loop(xs[last], ys[last], width, gain, family)
