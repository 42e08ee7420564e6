"""Feedforward compensation benchmark: tracking error of plant(compensator(y_ref)).

For two plants (the paper's backlash plant, a Bouc-Wen plant) an inverse model is trained
on plant data from one training signal (input: plant output, target: plant input) and then
used as a compensator, through the exported TorchScript module, on reference trajectories
it never saw (a multisine, a decaying sine with nested minor loops, a chirp, each scaled to
90 % of the trained output range). Reported: tracking RMSE in % of the reference range.

    python benchmarks/compensation.py [--out docs/figures] [--quick]

Methods: no compensation (u = (y_ref - c) / k with k, c the least-squares static line
y ~ k u + c of the training data: the best static, hysteresis-free gain), the analytic
inverse of a Prandtl-Ishlinskii model identified from the training data (non-negative least
squares over a play grid, linear weight held at least 2 % of the static gain so the inverse
exists), the Zhao-Tan network and the EIHO network (both causal, deployable).

Networks (64 sigmoid units; the play grid is 16 widths 0.4 range(y) k / 16, k = 1..16):
    * EIHO network: the network of ``configs/compensator.yaml`` (its ``model:`` operators,
      hidden units, activation and initialization), ``EIHO(a=1, rule="recent",
      output="branch")`` plus the plays. The re-based EIHO ``f - f(x_e) = +/- a |x - x_e|^(1/2)``
      (distance from the last turning point, with its direction) tells the branches apart
      without the level that the plain EIHO accumulates along the history. A fixed ``a`` only
      scales that input, which the network's normalization divides out.
    * Zhao-Tan network: ``ZhaoTanOperator(rule="recent", scale=std(y)/5, output="branch")``
      plus the same plays (the same treatment of the baseline's operator).
    * Ablations: the re-based EIHO alone; the level EIHO (``rule="dominant"``, the paper's
      ``f``, same ``a``) plus the plays; the plays alone.
"""

from __future__ import annotations

import argparse
import copy
import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
import yaml
from scipy.optimize import nnls
from torch import nn

from torchhys import EIHO, Backlash, InverseHysteresisNet, PrandtlIshlinskii, ZhaoTanOperator
from torchhys.export import load_torchscript, to_torchscript
from torchhys.fitting import fit_full_batch
from torchhys.functional import backlash
from torchhys.plants import bouc_wen, paper_plant_widths
from torchhys.signals import chirp, decaying_sine, multisine, to_range
from torchhys.training.init import initialize
from torchhys.training.operators import build_operators, fit_data_dependent

DTYPE = torch.float32
#: The recommended compensator: the EIHO network's operators, hidden units, activation and
#: initialization come from its ``model:`` section.
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "compensator.yaml"


def paper_plant(u: torch.Tensor) -> torch.Tensor:
    widths = paper_plant_widths(torch.float64)
    return (backlash(u.double(), widths) @ torch.ones(15, dtype=torch.float64)).to(u.dtype)


def bouc_wen_plant(u: torch.Tensor) -> torch.Tensor:
    t = torch.arange(u.shape[-1], dtype=torch.float64)  # rate-independent: any increasing t
    return bouc_wen(u.double(), t).to(u.dtype)


PLANTS = {"paper backlash plant": (paper_plant, 6.0), "Bouc-Wen plant": (bouc_wen_plant, 6.0)}


def fade_in(x: torch.Tensor, t: torch.Tensor, mid: float = 0.0) -> torch.Tensor:
    """Start at ``mid`` (the plant at rest) and reach the full signal after 5 s."""
    return mid + (x - mid) * torch.clamp(t / 5.0, max=1.0)


def training_input(amplitude: float, n: int) -> torch.Tensor:
    """Multisine, then a decaying sine (nested loops), then a chirp: plant input u.

    Each part starts at 0, as a controller does from rest.
    """
    t = torch.linspace(0.0, 60.0, n, dtype=torch.float64)
    ms = to_range(multisine(t, band=(0.2, 2.0), n_tones=8, seed=1), -amplitude, amplitude)
    parts = [
        fade_in(ms, t),
        amplitude * decaying_sine(t, omega=1.3, time_constant=25.0),
        chirp(t, omega0=0.2, omega1=2.5, amplitude=amplitude * 0.8),
    ]
    return torch.cat(parts).to(DTYPE)


def test_references(low: float, high: float, n: int) -> dict[str, torch.Tensor]:
    """Unseen references, scaled to 90 % of the trained output range, starting at rest (0)."""
    t = torch.linspace(0.0, 60.0, n, dtype=torch.float64)
    mid, half = 0.5 * (low + high), 0.45 * (high - low)
    sigs = {
        "multisine": multisine(t, band=(0.1, 1.5), n_tones=12, seed=11),
        "decaying": decaying_sine(t, omega=0.9, time_constant=30.0, phase=0.5) + 0.05 * t / 60,
        "chirp": chirp(t, omega0=0.1, omega1=1.8, phase=0.3),
    }
    return {k: fade_in(to_range(v, mid - half, mid + half), t).to(DTYPE)
            for k, v in sigs.items()}


def static_line(u: torch.Tensor, y: torch.Tensor) -> tuple[float, float]:
    k, c = np.polyfit(u.double().numpy(), y.double().numpy(), 1)
    return float(k), float(c)


def identify_pi(u: torch.Tensor, y: torch.Tensor, k: float) -> PrandtlIshlinskii:
    """PI model y ~ w0 u + sum_i w_i play_i(u) by NNLS with w0 >= 0.02 k (invertible)."""
    span = float(u.max() - u.min())
    widths = torch.linspace(span / 40, span / 2, 20, dtype=torch.float64)
    plays = backlash(u.double(), widths).numpy()
    w0_min = 0.02 * k
    A = np.column_stack([u.double().numpy(), plays])
    w, _ = nnls(A, y.double().numpy() - w0_min * u.double().numpy())
    return PrandtlIshlinskii(widths, torch.from_numpy(w[1:]), linear_weight=w0_min + w[0])


#: Methods drawn in the figures' output row (besides the reference), and ablations left out
#: of the figures.
OUTPUT_ROW = ("no compensation", "EIHO network (re-based EIHO + 16 plays)")
ABLATIONS = ("ablation: re-based EIHO alone", "ablation: level EIHO (dominant) + 16 plays")


def load_model_config(path: Path = CONFIG) -> dict:
    """The ``model:`` section of a ``torchhys fit`` config (``configs/compensator.yaml``)."""
    with open(path) as f:
        return yaml.safe_load(f)["model"]


def config_operators(model: dict, y: torch.Tensor, u: torch.Tensor) -> list[nn.Module]:
    """The config's operators, data-dependent ones (the plays' widths) fitted on (y, u),
    as ``torchhys fit`` fits them on its training split (``warmup`` 0)."""
    ops, fitters = build_operators(model["operator"], model.get("operator_kwargs"))
    ops = nn.ModuleList(ops)
    fit_data_dependent(ops, fitters, y.reshape(1, -1), u.reshape(1, -1))
    return list(ops)


def make_networks(
    y: torch.Tensor, u: torch.Tensor, model: dict | None = None
) -> dict[str, Callable[[], InverseHysteresisNet]]:
    """Constructors of the networks (each seeded on its own by the caller).

    ``model``: the config's ``model:`` section (default: :data:`CONFIG`'s), an EIHO and play
    operators: the EIHO network as configured; the other networks swap or drop its EIHO.
    """
    model = load_model_config() if model is None else model
    ops = config_operators(model, y, u)
    eiho = [op for op in ops if isinstance(op, EIHO)]
    plays = [op for op in ops if isinstance(op, Backlash)]
    if len(eiho) != 1 or len(plays) != 1 or len(ops) != 2:
        raise ValueError(f"the compensator config: expected an EIHO and plays, got {ops}")
    a = float(eiho[0].coefficient()[0])
    th = float(eiho[0].threshold)
    threshold = "auto" if math.isnan(th) else th  # the same reversal threshold everywhere
    scale = float(y.std()) / 5

    def net(*ops: nn.Module) -> InverseHysteresisNet:
        out = InverseHysteresisNet([copy.deepcopy(op) for op in ops], hidden=model["hidden"],
                                   activation=model["activation"])
        initialize(out, model.get("init", "nguyen_widrow"))
        return out

    level = EIHO(a=a, rule="dominant", threshold=threshold)
    zhao_tan = ZhaoTanOperator(rule="recent", scale=scale, output="branch", threshold=threshold)
    return {
        "Zhao-Tan network (re-based Zhao-Tan + 16 plays)": lambda: net(zhao_tan, plays[0]),
        OUTPUT_ROW[1]: lambda: net(*ops),
        ABLATIONS[0]: lambda: net(eiho[0]),
        ABLATIONS[1]: lambda: net(level, plays[0]),
        "ablation: 16 plays, no EIHO": lambda: net(plays[0]),
    }


def rmse_pct(y: torch.Tensor, ref: torch.Tensor) -> float:
    err = (y.double() - ref.double())
    return 100.0 * float(err.pow(2).mean().sqrt()) / float(ref.max() - ref.min())


def run_plant(name: str, n_train: int, n_test: int, epochs: tuple[int, int], tmp: Path,
              log: list[str]) -> tuple[dict, dict]:
    plant, amp = PLANTS[name]
    u_tr = training_input(amp, n_train)
    y_tr = plant(u_tr)
    k, c = static_line(u_tr, y_tr)
    refs = test_references(float(y_tr.min()), float(y_tr.max()), n_test)
    limits = (float(u_tr.min()) * 1.05, float(u_tr.max()) * 1.05)
    commands: dict[str, dict[str, torch.Tensor]] = {
        "no compensation": {s: (r - c) / k for s, r in refs.items()}}
    pi = identify_pi(u_tr, y_tr, k)
    inv = pi.inverse().to(DTYPE)
    pi_path = tmp / f"{name[:5]}-pi.pt"
    to_torchscript(inv, pi_path, limits=limits)
    pi_comp = load_torchscript(pi_path)
    commands["PI inverse (identified)"] = {s: pi_comp(r) for s, r in refs.items()}
    for label, make in make_networks(y_tr, u_tr).items():
        torch.manual_seed(0)
        net = make()
        start = time.perf_counter()
        fit = fit_full_batch(net, y_tr, u_tr, adam_epochs=epochs[0], lbfgs_epochs=epochs[1])
        path = tmp / f"{name[:5]}-{len(commands)}.pt"
        to_torchscript(net, path, limits=limits)
        comp = load_torchscript(path)
        commands[label] = {s: comp(r) for s, r in refs.items()}
        log.append(f"{name}: {label} trained in {time.perf_counter() - start:.1f} s, "
                   f"train mse {fit.mse:.3e} (u range {float(u_tr.max() - u_tr.min()):.2f})")
    outputs = {m: {s: plant(u) for s, u in cmd.items()} for m, cmd in commands.items()}
    return refs, outputs


def plot(name: str, refs: dict, outputs: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, len(refs), figsize=(4.4 * len(refs), 8.4), sharex="col")
    for j, (sig, ref) in enumerate(refs.items()):
        ax, ax_e, ax_z = axes[:, j]
        ax.plot(ref, color="k", lw=1.4, label="reference")
        for i, (m, outs) in enumerate(outputs.items()):
            if m in ABLATIONS:
                continue
            style = dict(lw=0.9, alpha=0.85, color=f"C{i}")
            if m in OUTPUT_ROW:
                ax.plot(outs[sig], label=m, **style)
            ax_e.plot(outs[sig] - ref, label=m, **style)
            if m != "no compensation":
                ax_z.plot(outs[sig] - ref, label=m, **style)
        ax.set_title(f"{name}: {sig}", fontsize=9)
        ax.set_ylabel("output")
        ax_e.set_ylabel("output - reference")
        ax_z.set(xlabel="sample", ylabel="error, compensators only")
        for a in (ax, ax_e, ax_z):
            a.grid(alpha=0.3)
    for row in range(3):
        axes[row, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/figures"))
    parser.add_argument("--quick", action="store_true", help="small budget (smoke test)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    n_train, n_test = (600, 300) if args.quick else (2000, 1500)
    epochs = (200, 100) if args.quick else (1500, 1500)
    log: list[str] = []
    rows = []
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for name in PLANTS:
            refs, outputs = run_plant(name, n_train, n_test, epochs, Path(tmp), log)
            if not args.quick:
                args.out.mkdir(parents=True, exist_ok=True)
                slug = "paper" if "paper" in name else "bouc_wen"
                plot(name, refs, outputs, args.out / f"compensation_{slug}.png")
            for m, outs in outputs.items():
                errs = [rmse_pct(outs[s], refs[s]) for s in refs]
                rows.append((name, m, *errs, math.sqrt(sum(e * e for e in errs) / len(errs))))
    print("\n".join(log))
    sigs = list(refs)
    print(f"\ntotal {time.perf_counter() - start:.0f} s\n")
    print("| plant | method | " + " | ".join(f"{s} (%)" for s in sigs) + " | all (%) |")
    print("|---|---|" + "---|" * (len(sigs) + 1))
    for name, m, *errs in rows:
        print(f"| {name} | {m} | " + " | ".join(f"{e:.3f}" for e in errs) + " |")


if __name__ == "__main__":
    main()
