"""Writes the C files of a small composed model and the reference sequence header.

    python deploy/c/example_composed.py OUT_DIR [--dtype float32|float64]
                                        [--prefix NAME] [--samples N] [--epochs N]

The model is a plain ``nn.Module`` (:class:`PlaysGRU`): 4 learnable play operators of the
input beside the input itself, into an ``nn.GRU`` of 8 units, an ``nn.Linear`` read-out
(weights seeded, torch's own init), trained briefly (``--epochs`` Adam steps, float64) on
the loop of ``example_comp.py`` (x -> y = x + 0.2 cos t), then made deployable with
``torchhys.compose.compose(module, x=, y=)`` (the training data's ranges recorded) and
exported with ``torchhys.deploy.c.to_c``. Writes ``OUT_DIR/NAME.h``, ``OUT_DIR/NAME.c`` and
``OUT_DIR/ref.h``: the reference sequence of ``example_comp.py`` over the recorded input range
(nested turning points, ties, an excursion beyond the range, one NaN), the sequence
``mcu_main.c`` steps; and ``OUT_DIR/torch64.txt``: the float64 ``StreamingCompensator``'s
commands on that sequence (the export's options, one a line), the torch reference of the
float32 C. Prints the paths.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from example_comp import loop_data, reference  # deploy/c/, this file's folder
from torch import Tensor, nn

from torchhys import Backlash
from torchhys.compose import Composed, compose
from torchhys.deploy.c import to_c
from torchhys.deploy.streaming import StreamingCompensator


class PlaysGRU(nn.Module):
    """``plays`` learnable play operators of x beside x, into a GRU of ``hidden`` units, a
    linear read-out: x (batch, time) -> y (batch, time)."""

    def __init__(self, plays: int = 4, hidden: int = 8, width: float = 0.15) -> None:
        super().__init__()
        self.plays = Backlash([width * (k + 1) for k in range(plays)], learnable=True)
        self.gru = nn.GRU(1 + plays, hidden, batch_first=True)
        self.out = nn.Linear(hidden, 1)

    def forward(self, x: Tensor) -> Tensor:
        p = self.plays(x)[0]
        h = self.gru(torch.cat([x.unsqueeze(-1), p], -1))[0]
        return self.out(h).squeeze(-1)


def example_composed(epochs: int = 150, seed: int = 0) -> Composed:
    """:class:`PlaysGRU` (seed ``seed``) trained ``epochs`` Adam steps on ``loop_data``, in
    float64, composed with the loop's ranges recorded."""
    torch.manual_seed(seed)
    x, y = loop_data()
    model = compose(PlaysGRU().double(), x=x, y=y)
    opt = torch.optim.Adam(model.parameters(), lr=0.02)
    for _ in range(epochs):
        opt.zero_grad()
        loss = (model(x) - y).square().mean()
        loss.backward()
        opt.step()
    model.check()  # the per-sample check again, on the trained weights
    return model


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("out_dir", type=Path)
    p.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    p.add_argument("--prefix", default="torchhys_comp")
    p.add_argument("--samples", type=int, default=256)
    p.add_argument("--epochs", type=int, default=150)
    a = p.parse_args()
    torch.set_num_threads(1)
    a.out_dir.mkdir(parents=True, exist_ok=True)
    model = example_composed(a.epochs)
    to_c(model, a.out_dir, prefix=a.prefix, dtype=getattr(torch, a.dtype))
    x = reference(float(model.in_min), float(model.in_max), a.samples)
    lines = ",\n".join("    " + ("NAN" if np.isnan(v) else repr(float(v))) for v in x)
    (a.out_dir / "ref.h").write_text(
        "/* The reference sequence of mcu_main.c (deploy/c/example_composed.py). */\n"
        "#include <math.h> /* NAN */\n"
        f"#define REF_N {len(x)}\n"
        f"static const {a.prefix}_real ref[REF_N] = {{\n{lines}\n}};\n")
    comp = StreamingCompensator(model).eval()  # to_c's defaults, float64
    with torch.no_grad():
        u = [float(comp.step(torch.tensor([v], dtype=torch.float64))) for v in x]
    (a.out_dir / "torch64.txt").write_text("".join(f"{i} {v:.17g}\n" for i, v in enumerate(u)))
    for name in (f"{a.prefix}.h", f"{a.prefix}.c", "ref.h", "torch64.txt"):
        print(a.out_dir / name)


if __name__ == "__main__":
    main()
