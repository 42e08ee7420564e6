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

A third plant is rate-dependent: a piezo stage (:class:`torchhys.plants.PiezoStage`, the
Prandtl-Ishlinskii hysteresis of ``default_stage_hysteresis`` then a second-order stage,
``f_n = 8 Hz``, ``zeta = 0.07``, sampled at 160 Hz with a zero-order hold). Its training
record is the same 1x record at 160 Hz (its highest frequency, the chirp's end, 2.5 rad/s =
0.40 Hz: the training bandwidth, so ``f_n`` is 20x the training bandwidth) plus a 20 s
small-amplitude sweep up to 100 rad/s that excites the stage. The references are the same
shapes at 1x, 10x and 50x the rate (the same samples per second, 10x and 50x fewer samples).
Methods: no compensation; the EIHO network (rate-independent) trained on the 1x record;
the rate-dependent compensator: the stage identified from the whole record (``f_n``,
``zeta`` and a Prandtl-Ishlinskii model, output error), the model-matching filter
``F = G_ref / G_hat`` of :func:`stage_prefilter` (an FIR), and the same EIHO network on
``F y`` (``[F, Cascade(F, EIHO), Cascade(F, plays)]``, its weights on the raw input held at 0),
trained on the same 1x record. ``--plants stage`` runs that section alone.
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
from scipy.optimize import minimize, nnls
from scipy.signal import lfilter
from torch import nn

from torchhys import (
    EIHO,
    Backlash,
    Cascade,
    InverseHysteresisNet,
    PrandtlIshlinskii,
    ZhaoTanOperator,
)
from torchhys.cli.train import read_config
from torchhys.deploy.export import load_torchscript, to_torchscript
from torchhys.dynamics import TransferFunction
from torchhys.functional import backlash
from torchhys.identification.fitting import FitResult, fit_full_batch
from torchhys.identification.specs import build_operators, fit_data_dependent
from torchhys.init import initialize
from torchhys.plants import PiezoStage, bouc_wen, paper_plant_widths
from torchhys.signals import chirp, decaying_sine, multisine, to_range

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
#: ``--plants`` names (and figure names) of the rate-independent plants
PLANT_KEYS = {"paper": "paper backlash plant", "bouc_wen": "Bouc-Wen plant"}


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
    """The ``model:`` section of a ``torchhys fit`` config (``configs/compensator.yaml``),
    read as the command reads it."""
    return read_config(path)["model"]


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


def trained_compensator(
    make: Callable[[], InverseHysteresisNet], y: torch.Tensor, u: torch.Tensor,
    epochs: tuple[int, int], path: Path, limits: tuple[float, float],
) -> tuple[Callable[[torch.Tensor], torch.Tensor], FitResult, float]:
    """The network ``make()`` (seed 0) fitted full-batch to (y -> u), exported to TorchScript
    at ``path`` with ``limits`` and loaded back; with its fit and the seconds all that took."""
    torch.manual_seed(0)
    net = make()
    start = time.perf_counter()
    fit = fit_full_batch(net, y, u, adam_epochs=epochs[0], lbfgs_epochs=epochs[1])
    to_torchscript(net, path, limits=limits)
    return load_torchscript(path), fit, time.perf_counter() - start


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
        comp, fit, seconds = trained_compensator(make, y_tr, u_tr, epochs,
                                                 tmp / f"{name[:5]}-{len(commands)}.pt", limits)
        commands[label] = {s: comp(r) for s, r in refs.items()}
        log.append(f"{name}: {label} trained in {seconds:.1f} s, "
                   f"train mse {fit.mse:.3e} (u range {float(u_tr.max() - u_tr.min()):.2f})")
    outputs = {m: {s: plant(u) for s, u in cmd.items()} for m, cmd in commands.items()}
    return refs, outputs


# --- the piezo stage: hysteresis, then lightly damped dynamics (a rate-dependent plant) --------

STAGE_FN, STAGE_ZETA, STAGE_FS = 8.0, 0.07, 160.0
#: the 1x record's samples per part (60 s at 160 Hz) and the rates of the references
STAGE_N, RATES = 9601, (1, 10, 50)
STAGE = PiezoStage(STAGE_FN, STAGE_ZETA)
RATE_DEPENDENT = "rate-dependent: stage prefilter F + EIHO network"


def stage_plant(u: torch.Tensor) -> torch.Tensor:
    return STAGE(u.double(), fs=STAGE_FS).to(u.dtype)


def stage_training_input(n: int = STAGE_N) -> tuple[torch.Tensor, int]:
    """The 1x record (:func:`training_input` at 160 Hz), then a 20 s logarithmic sweep from
    2.5 to 100 rad/s of amplitude 1 (faded in) that excites the stage: (u, 1x samples)."""
    t = torch.arange(int(20 * STAGE_FS), dtype=torch.float64) / STAGE_FS
    sweep = chirp(t, omega0=2.5, omega1=100.0, sweep="logarithmic", amplitude=1.0)
    u = training_input(6.0, n)
    return torch.cat([u, fade_in(sweep, t).to(DTYPE)]), u.shape[0]


def identify_stage(u: torch.Tensor, y: torch.Tensor, fs: float) -> tuple[float, float]:
    """``(f_n, zeta)`` of ``y ~ G(w0 u + sum_i w_i play_i(u) + c)`` by output error.

    For fixed ``(f_n, zeta)`` the sampled stage G is linear, so the weights (20 plays over
    the input's span, as :func:`identify_pi`) solve a least-squares problem on the filtered
    plays (variable projection); ``(log f_n, log zeta)`` are searched on a grid, then by
    Nelder-Mead.
    """
    span = float(u.max() - u.min())
    widths = torch.linspace(span / 40, span / 2, 20, dtype=torch.float64)
    u64, y64 = u.double(), y.double().numpy()
    phi = np.column_stack([u64.numpy(), backlash(u64, widths).numpy(), np.ones(len(u64))])

    def mse(p: np.ndarray) -> float:
        b, a = (c.numpy() for c in PiezoStage(math.exp(p[0]), math.exp(p[1])).coefficients(fs))
        psi = lfilter(b, a, phi, axis=0)
        w, *_ = np.linalg.lstsq(psi, y64, rcond=None)
        return float(np.mean((psi @ w - y64) ** 2))

    grid = [np.log([f, z]) for f in np.geomspace(1.0, 0.4 * fs, 12) for z in (0.03, 0.1, 0.3)]
    start = min(grid, key=mse)
    res = minimize(mse, start, method="Nelder-Mead",
                   options={"xatol": 1e-7, "fatol": 1e-15, "maxiter": 400})
    return math.exp(res.x[0]), math.exp(res.x[1])


def stage_prefilter(fn: float, zeta: float, fs: float, *, order: int = 2) -> TransferFunction:
    """The model-matching filter ``F = G_ref / G_hat`` of a sampled stage, an FIR.

    The sampled stage is ``G(z) = G(1) d(z) / a(z)`` with ``d = (b1 z^-1 + b2 z^-2) / G(1)``:
    its poles (``a``, lightly damped) and its delay (one sample and the sampling zero's
    ``b2 / (b1 + b2)``, about half a sample). ``G_ref = d(z) e(z)`` with ``e`` the FIR of
    ``order + 1`` taps for which ``G_ref(e^{jw}) = 1 + O(w^(order + 1))`` (``sum_k
    g_k k^q = [q = 0]`` for ``q <= order``: a polynomial extrapolation that takes the delay
    back); ``F = a(z) e(z) / G(1)`` (``order + 3`` taps) is then causal and stable, and
    ``G F = G_ref``. Its gain grows with frequency (``|F(-1)|`` = 437 for the benchmark's
    stage): references must be smooth.
    """
    b, a = (c.numpy() for c in PiezoStage(fn, zeta).coefficients(fs))
    d = np.array([0.0, b[1], b[2]]) / (b[1] + b[2])
    k = np.arange(len(d) + order)
    moments = np.zeros((order + 1, order + 1))
    for j in range(order + 1):  # column j: the moments of d delayed by j samples
        g = np.zeros(len(k))
        g[j:j + len(d)] = d
        moments[:, j] = [np.sum(g * k**q) for q in range(order + 1)]
    e = np.linalg.solve(moments, np.eye(order + 1)[:, 0])
    block = TransferFunction.from_coefficients(np.convolve(a, e) / (b[1] + b[2]), [1.0])
    return block.to(DTYPE).requires_grad_(False)


def ignore_raw_input(net: InverseHysteresisNet) -> InverseHysteresisNet:
    """Hold the network's weights on its raw input (feature 0) at 0 through training."""
    with torch.no_grad():
        net.hidden.weight[:, 0] = 0.0
    mask = torch.ones_like(net.hidden.weight)
    mask[:, 0] = 0.0
    net.hidden.weight.register_hook(lambda g: g * mask)
    return net


def run_stage(n: int, epochs: tuple[int, int], tmp: Path, log: list[str]
              ) -> dict[int, tuple[dict, dict]]:
    """The piezo stage at each rate of :data:`RATES`: ``{rate: (refs, outputs)}``."""
    u_all, n1 = stage_training_input(n)
    y_all = stage_plant(u_all)
    u_tr, y_tr = u_all[:n1], y_all[:n1]
    start = time.perf_counter()
    fn, zeta = identify_stage(u_all, y_all, STAGE_FS)
    log.append(f"piezo stage: identified f_n = {fn:.4f} Hz, zeta = {zeta:.5f} (true "
               f"{STAGE_FN}, {STAGE_ZETA}) in {time.perf_counter() - start:.1f} s")
    model = load_model_config()
    ops = config_operators(model, y_tr, u_tr)

    def rate_dependent() -> InverseHysteresisNet:
        blocks = [stage_prefilter(fn, zeta, STAGE_FS)]
        blocks += [Cascade(stage_prefilter(fn, zeta, STAGE_FS), copy.deepcopy(op)) for op in ops]
        net = InverseHysteresisNet(blocks, hidden=model["hidden"],
                                   activation=model["activation"])
        initialize(net, model.get("init", "nguyen_widrow"))
        return ignore_raw_input(net)

    k, c = static_line(u_tr, y_tr)
    limits = (float(u_tr.min()) * 1.05, float(u_tr.max()) * 1.05)
    comps: dict[str, Callable[[torch.Tensor], torch.Tensor]] = {}
    for label, make in ((OUTPUT_ROW[1], make_networks(y_tr, u_tr, model)[OUTPUT_ROW[1]]),
                        (RATE_DEPENDENT, rate_dependent)):
        comps[label], fit, seconds = trained_compensator(make, y_tr, u_tr, epochs,
                                                         tmp / f"stage-{len(comps)}.pt", limits)
        log.append(f"piezo stage: {label} trained in {seconds:.1f} s, "
                   f"train mse {fit.mse:.3e}")
    results = {}
    for rate in RATES:
        refs = test_references(float(y_tr.min()), float(y_tr.max()), (n - 1) // rate + 1)
        commands = {"no compensation": {s: (r - c) / k for s, r in refs.items()}}
        commands |= {m: {s: comp(r) for s, r in refs.items()} for m, comp in comps.items()}
        outputs = {m: {s: stage_plant(u) for s, u in cmd.items()} for m, cmd in commands.items()}
        results[rate] = (refs, outputs)
    return results


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
    parser.add_argument("--plants", nargs="+", choices=list(PLANT_KEYS) + ["stage"],
                        default=list(PLANT_KEYS) + ["stage"], help="plants to run (default all)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    n_train, n_test = (600, 300) if args.quick else (2000, 1500)
    epochs = (200, 100) if args.quick else (1500, 1500)
    log: list[str] = []
    rows = []
    start = time.perf_counter()
    if not args.quick:
        args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        for slug, name in PLANT_KEYS.items():
            if slug not in args.plants:
                continue
            refs, outputs = run_plant(name, n_train, n_test, epochs, Path(tmp), log)
            if not args.quick:
                plot(name, refs, outputs, args.out / f"compensation_{slug}.png")
            rows += table_rows(name, refs, outputs)
        if "stage" in args.plants:
            for rate, (refs, outputs) in run_stage(STAGE_N, epochs, Path(tmp), log).items():
                rows += table_rows(f"piezo stage, {rate}x", refs, outputs)
    print("\n".join(log))
    sigs = list(refs)
    print(f"\ntotal {time.perf_counter() - start:.0f} s\n")
    print("| plant | method | " + " | ".join(f"{s} (%)" for s in sigs) + " | all (%) |")
    print("|---|---|" + "---|" * (len(sigs) + 1))
    for name, m, *errs in rows:
        print(f"| {name} | {m} | " + " | ".join(f"{e:.3f}" for e in errs) + " |")


def table_rows(name: str, refs: dict, outputs: dict) -> list[tuple]:
    """``(plant, method, RMSE per reference..., pooled)`` in % of range, one per method."""
    rows = []
    for m, outs in outputs.items():
        errs = [rmse_pct(outs[s], refs[s]) for s in refs]
        rows.append((name, m, *errs, math.sqrt(sum(e * e for e in errs) / len(errs))))
    return rows


if __name__ == "__main__":
    main()
