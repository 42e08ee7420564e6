"""Writes the C files of a small example compensator and a reference sequence header.

    python deploy/c/example_comp.py OUT_DIR [--ckpt CKPT] [--dtype float32|float64]
                                    [--prefix NAME] [--samples N] [--adapt nlms|rls]

Without ``--ckpt``: the network of ``configs/compensator.yaml`` (a re-based EIHO and 16 plays,
64 sigmoid units), its normalization fitted with ``fit_normalization`` on a loop and its
output layer the ridge least-squares fit of the loop's target
(``torchhys.init.least_squares_output``), so that it follows the loop (no training run).
With ``--ckpt``: the checkpoint, exported as ``torchhys export --format c`` does. Writes
``OUT_DIR/NAME.h``, ``OUT_DIR/NAME.c`` (``torchhys.deploy.c.to_c``) and ``OUT_DIR/ref.h``:
``static const NAME_real ref[]`` (``REF_N`` samples around the training range: nested turning
points, ties, excursions beyond the range, one NaN), the reference sequence ``mcu_main.c``
steps. Prints the paths.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from torchhys import EIHO, Backlash, InverseHysteresisNet
from torchhys.deploy.c import to_c
from torchhys.init import least_squares_output


def loop_data(T: int = 600) -> tuple[torch.Tensor, torch.Tensor]:
    """The training loop: x = sin(t) (1 + 0.1 t), y = x + 0.2 cos t, t in [0, 2 pi]."""
    t = torch.linspace(0.0, 2 * torch.pi, T, dtype=torch.float64)
    x = torch.sin(t) * (1 + 0.1 * t)
    return x[None], (x + 0.2 * torch.cos(t))[None]


def example_network() -> InverseHysteresisNet:
    """The network of configs/compensator.yaml on ``loop_data``, output layer fitted."""
    torch.manual_seed(0)
    x, y = loop_data()
    span = float(x.max() - x.min())
    plays = Backlash(0.4 * span * torch.arange(1, 17, dtype=torch.float64) / 16)
    eiho = EIHO(a=1.0, rule="recent", output="branch", threshold=0.0)
    net = InverseHysteresisNet([eiho, plays], hidden=64, activation="sigmoid").double()
    net.fit_normalization(x, y)
    least_squares_output(net, x, y)
    return net


def reference(low: float, high: float, n: int) -> np.ndarray:
    """``n`` samples: a decaying, growing sine (nested turning points) over the range, a run
    of repeated samples, an excursion 30 % beyond the range and one NaN (held, counted)."""
    t = np.arange(n)
    c, h = (low + high) / 2, (high - low) / 2
    x = c + 0.95 * h * np.sin(2 * np.pi * t / 50) * (0.55 + 0.45 * np.cos(2 * np.pi * t / 170))
    x[n // 3:n // 3 + 6] = x[n // 3]
    k = n // 2
    x[k:k + 20] = c + 1.3 * h * np.sin(np.linspace(0, np.pi, 20))
    x[(2 * n) // 3] = np.nan
    return x


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("out_dir", type=Path)
    p.add_argument("--ckpt", help="a checkpoint of the torchhys command (default: the example)")
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--prefix", default="torchhys_comp")
    p.add_argument("--samples", type=int, default=256)
    p.add_argument("--adapt", default="none", choices=["none", "rls", "nlms"],
                   help="the adaptive step (to_c's adapt; the example network only)")
    a = p.parse_args()
    a.out_dir.mkdir(parents=True, exist_ok=True)
    dtype = getattr(torch, a.dtype)
    if a.ckpt and a.adapt != "none":
        p.error("--adapt takes the example network (no --ckpt)")
    if a.ckpt:
        subprocess.run([sys.executable, "-m", "torchhys", "export", "--ckpt", a.ckpt,
                        "--format", "c", "--out", str(a.out_dir), "--dtype", a.dtype,
                        "--prefix", a.prefix, "--force"], check=True)  # rewrites OUT_DIR
        net = None
    else:
        net = example_network()
        to_c(net, a.out_dir, prefix=a.prefix, dtype=dtype, adapt=a.adapt)
    # the reference covers the training input range the header states
    text = (a.out_dir / f"{a.prefix}.h").read_text()
    low, high = training_input_range(text, net)
    x = reference(low, high, a.samples)
    lines = ",\n".join("    " + ("NAN" if np.isnan(v) else repr(float(v))) for v in x)
    (a.out_dir / "ref.h").write_text(
        "/* The reference sequence of mcu_main.c (deploy/c/example_comp.py). */\n"
        "#include <math.h> /* NAN */\n"
        f"#define REF_N {len(x)}\n"
        f"static const {a.prefix}_real ref[REF_N] = {{\n{lines}\n}};\n")
    for name in (f"{a.prefix}.h", f"{a.prefix}.c", "ref.h"):
        print(a.out_dir / name)


def training_input_range(header: str, net: InverseHysteresisNet | None) -> tuple[float, float]:
    if net is not None:
        return float(net.in_min), float(net.in_max)
    m = re.search(r"input[^\n]*?\[\s*([-+0-9.eE]+)\s*,\s*([-+0-9.eE]+)\s*\]", header)
    if m is None:
        raise SystemExit(f"cannot find the training input range in the header:\n{header[:800]}")
    return float(m.group(1)), float(m.group(2))


if __name__ == "__main__":
    main()
