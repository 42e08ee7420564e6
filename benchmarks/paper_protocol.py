"""The paper's simulation protocol (Section 5.2) and a causal generalization check.

Part 1 (paper protocol): the inverse model maps the plant output h = H[x] back to x on
the paper's signal, with the paper's per-segment a_i (Eq. (18) with the square-root
formula, non-causal: they use the target's extrema), a 168-unit sigmoid network;
Zhao-Tan's operator and a plain network of h alone as baselines. MSE on the training
signal, as in the paper (1.737e-3 for EIHO-NN, 3.867e-3 for Ref. [8]).

Part 2 (causal): configurations that need no targets at run time, trained on the paper's signal and
tested on two signals of the same range through the same plant: a decaying multisine (nested minor
loops) and a steady multisine. The least-squares Prandtl-Ishlinskii model of h
(:func:`torchhys.identification.fitting.fit_prandtl_ishlinskii`, linear in the outputs of 30 play
operators of h on a cubic width grid) is the causal inverse, alone or as the network's operator.

Prints markdown tables. Usage: ``python benchmarks/paper_protocol.py [--quick]``.
"""

from __future__ import annotations

import argparse
import time
import warnings

import torch

from torchhys import EIHO, Backlash, InverseHysteresisNet
from torchhys.functional import NonCausalWarning, prandtl_ishlinskii, segment_coefficients
from torchhys.identification.fitting import fit_full_batch, fit_prandtl_ishlinskii, play_width_grid
from torchhys.plants import paper_plant_widths, paper_simulation
from torchhys.signals import exponential_decay, multisine, to_range


def test_signal(
    t: torch.Tensor, x: torch.Tensor, *, decay: bool = True, seed: int = 1
) -> tuple[torch.Tensor, torch.Tensor]:
    """Multisine with the range of ``x`` (decaying by default), and its plant output."""
    raw = multisine(t, band=(0.2, 3.0), n_tones=8, seed=seed)
    if decay:
        raw = exponential_decay(raw, t, time_constant=float(t[-1]) / 2)
    xs = to_range(raw, x.min(), x.max())
    widths = paper_plant_widths(torch.float64)
    return xs, prandtl_ishlinskii(xs, widths, torch.ones_like(widths))


def h_play_widths(n: int = 15) -> torch.Tensor:
    """Play widths in units of h: how far h moves after a reversal of x by each plant width."""
    d = paper_plant_widths(torch.float64)
    return torch.stack([torch.relu(dj - d).sum() for dj in d])[-n:].clamp(min=0.25)


def mse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(torch.mean((a - b) ** 2))


def paper_rows(x, h, adam: int, lbfgs: int, seed: int = 0) -> list[tuple]:
    rows = []
    configs = [
        ("EIHO-NN", "eiho_segment", {}, "per-segment sqrt a_i (non-causal)"),
        ("Zhao-Tan NN", "zhao_tan", {"scale": float(h.std()) / 5}, "-"),
        ("plain NN (x only)", None, {}, "-"),
    ]
    for name, op, kw, mode in configs:
        torch.manual_seed(seed)
        net = InverseHysteresisNet(op, 168, operator_kwargs=kw).double()
        r = fit_full_batch(net, h, x, adam_epochs=adam, lbfgs_epochs=lbfgs)
        rows.append((name, mode, 168, r.epochs, r.seconds, r.mse))
    return rows


def causal_models(x, h) -> list[tuple[str, str, torch.nn.Module]]:
    a_med = float(segment_coefficients(h, x).median())  # one constant: causal once fitted
    widths = h_play_widths()
    grid = play_width_grid(h, 30)  # span(h) (k/30)^3
    return [
        ("EIHO-NN", f"fixed a={a_med:.3f} (median a_i), dominant",
         InverseHysteresisNet(EIHO(a=a_med, rule="dominant"), 168)),
        ("EIHO-NN", "anchored a (learned function of x_e), dominant",
         InverseHysteresisNet(EIHO(a="anchored", rule="dominant", a_init=a_med,
                                   anchor_center=float(h.mean()), anchor_scale=float(h.std())),
                              168)),
        ("EIHO + plays NN", f"fixed a={a_med:.3f}, dominant; 15 plays of h",
         InverseHysteresisNet([EIHO(a=a_med, rule="dominant"), Backlash(widths)], 168)),
        ("plays NN", "15 plays of h", InverseHysteresisNet(Backlash(widths), 168)),
        ("plays NN", "30 plays of h, cubic grid", InverseHysteresisNet(Backlash(grid), 168)),
        ("plain NN (x only)", "-", InverseHysteresisNet(None, 168)),
        ("least-squares PI of h (no network)", "30 plays of h, cubic grid", None),
        ("PI-NN", "operator: least-squares PI of h (30 plays, cubic grid)",
         InverseHysteresisNet([fit_prandtl_ishlinskii(h, x, grid)], 168)),
    ]


def causal_rows(t, x, h, adam: int, lbfgs: int, seed: int = 0) -> list[tuple]:
    tests = [test_signal(t, x), test_signal(t, x, decay=False, seed=2)]
    rows = []
    for name, mode, net in causal_models(x, h):
        torch.manual_seed(seed)
        if net is None:  # the least-squares model alone
            start = time.perf_counter()
            net = fit_prandtl_ishlinskii(h, x, play_width_grid(h, 30))
            epochs, seconds = 0, time.perf_counter() - start
            with torch.no_grad():
                train = mse(net(h)[0], x)
        else:
            net = net.double()
            r = fit_full_batch(net, h, x, adam_epochs=adam, lbfgs_epochs=lbfgs)
            epochs, seconds, train = r.epochs, r.seconds, r.mse
        with torch.no_grad():
            test = [mse(net(hs)[0], xs) for xs, hs in tests]
        hidden = getattr(getattr(net, "hidden", None), "out_features", "-")
        rows.append((name, mode, hidden, epochs, seconds, train, *test))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small budget (smoke run)")
    parser.add_argument("--part", choices=["paper", "causal", "both"], default="both")
    args = parser.parse_args()
    torch.set_num_threads(1)
    warnings.simplefilter("ignore", NonCausalWarning)
    adam, lbfgs = (300, 200) if args.quick else (2000, 10000)
    t, x, h = paper_simulation(dtype=torch.float64)
    if args.part in ("paper", "both"):
        print("| model | a mode | hidden | epochs | seconds | mse |")
        print("|---|---|---|---|---|---|")
        for row in paper_rows(x, h, adam, lbfgs):
            print("| {} | {} | {} | {} | {:.1f} | {:.3e} |".format(*row), flush=True)
    if args.part in ("causal", "both"):
        print(
            "\n| model | configuration | hidden | epochs | seconds | train mse "
            "| test mse (decaying multisine) | test mse (multisine) |"
        )
        print("|---|---|---|---|---|---|---|---|")
        for row in causal_rows(t, x, h, adam // 2, lbfgs // 10):
            print(
                "| {} | {} | {} | {} | {:.1f} | {:.3e} | {:.3e} | {:.3e} |".format(*row),
                flush=True,
            )


if __name__ == "__main__":
    main()
