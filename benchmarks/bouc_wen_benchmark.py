"""The Bouc-Wen nonlinear system identification benchmark (Noel and Schoukens, 2016).

Trains on ``train_u, train_y`` only (40960 samples, 5 periods of one multisine; the first 4
periods train, the 5th validates: early stopping and the choice of the linear order) and
reports the free-run simulation RMSE of y (m) on the two test sets, beside published results:

    python benchmarks/bouc_wen_benchmark.py [--quick] [--save DIR] [--models ...]
    python benchmarks/bouc_wen_benchmark.py --evaluate DIR_OR_FILE

Models (``torchhys.models``):
    * linear: the best linear model, a transfer function fitted by ARX then output error;
      order 2, 3 or 4 chosen on the validation period.
    * feedback-duhem (black box, block-oriented): ``y = G_u u + G_z H[y]`` with second-order
      transfer functions and a Duhem hysteresis ``H`` (slopes affine in z and |z| per
      direction), started as the linear model of order 2 with half its static stiffness in the
      loop, then the simulation error by windows of 256 samples with carried states (L-BFGS).
    * feedback-duhem-net (black box, on request): the same with 8 tanh units of z added to
      each slope (a Duhem operator with a learned slope function).
    * feedback-plays (black box): the same loop with a generalised Prandtl-Ishlinskii element
      (8 learnable plays, torchhys.Backlash widths, and 16 tanh units) instead of the Duhem.
    * grey box (not comparable: it knows the equations): the Bouc-Wen oscillator with all 6
      coefficients learnable, RK4 with 2 substeps a sample and a causal cubic input, started
      from the order-2 linear model (mass, damping, stiffness split in half, shape 0).

Metric. Free-run simulation from the model's rest state. The multisine test record is one
period of the periodic steady state (its output does not start at rest); ``multisine`` runs
the model over two periods of the (periodic) test input and scores the second, ``from rest``
scores the first (even the true system scores 4.6e-5 m there: the transient). The sine sweep
starts at rest and is scored from rest. Published multisine-test results (RMSE, m; arXiv
2507.09646 Table 1 and the dynoNet paper) are listed for comparison.

``--save DIR`` writes one file a model (state dict, config, training time and its results;
``torch.load(..., weights_only=True)`` loads it); ``--evaluate`` rebuilds the models from such
files and prints their rows again without training.
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np
import torch

from torchhys.models import (
    BoucWenOscillator,
    HysteresisFeedback,
    LinearModel,
    fit_linear,
    fit_windows,
    grey_box_start,
    init_from_linear,
    simulate,
)

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "bouc_wen_benchmark.npz"
PUBLISHED = {"gr-SS-NN": 7.53e-6, "improved SS-NN": 8.91e-6, "PNLSS": 1.34e-5,
             "input-affine Koopman": 1.43e-5, "SS-NN": 2.65e-5, "dynoNet": 4.52e-5,
             "linear Koopman": 1.60e-4}
KINDS = {"linear": LinearModel, "feedback": HysteresisFeedback, "grey_box": BoucWenOscillator}
MODELS = ("linear", "feedback-duhem", "feedback-plays", "grey-box")
EXTRA = ("feedback-duhem-net",)  # run on request (--models)
PERIOD = 8192
PLAY_WIDTHS = [0.375 * k for k in range(1, 9)]  # in units of y / std(y)

# iterations (L-BFGS steps of up to 10 evaluations): full / --quick
BUDGET = {"feedback-duhem": (40, 4), "feedback-duhem-net": (40, 2), "feedback-plays": (100, 2),
          "grey-box": (20, 2)}


def load(path: Path) -> dict[str, torch.Tensor]:
    data = np.load(path)
    return {k: torch.from_numpy(np.asarray(data[k], dtype=np.float64)) for k in data.files}


def rmse(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a - b).square().mean().sqrt())


def evaluate(model: torch.nn.Module, d: dict[str, torch.Tensor], fs: float) -> dict[str, float]:
    """Test RMSEs (m): multisine (periodic steady state), multisine from rest, sine sweep."""
    u_ms, y_ms = d["test_multisine_u"], d["test_multisine_y"]
    return {"multisine": rmse(simulate(model, u_ms, fs=fs, periods=2), y_ms),
            "multisine_from_rest": rmse(simulate(model, u_ms, fs=fs), y_ms),
            "sinesweep": rmse(simulate(model, d["test_sinesweep_u"], fs=fs),
                              d["test_sinesweep_y"])}


def validation_rmse(model: torch.nn.Module, u: torch.Tensor, y: torch.Tensor, fs: float) -> float:
    return rmse(simulate(model, u, fs=fs)[-PERIOD:], y[-PERIOD:])


def train(name: str, d: dict[str, torch.Tensor], fs: float, quick: bool,
          log) -> tuple[str, torch.nn.Module, float]:
    """Train one model on the training record; returns (kind, model, seconds)."""
    u, y = d["train_u"], d["train_y"]
    u_fit, y_fit = u[:-PERIOD], y[:-PERIOD]
    start = time.perf_counter()
    if name == "linear":
        fits = [fit_linear(u_fit, y_fit, order=n, fs=fs) for n in ((2,) if quick else (2, 3, 4))]
        scores = [validation_rmse(m, u, y, fs) for m in fits]
        for m, s in zip(fits, scores, strict=True):
            log(f"  linear order {m.order}: validation rmse {s:.4g}")
        return "linear", fits[int(np.argmin(scores))], time.perf_counter() - start
    lin = fit_linear(u_fit, y_fit, order=2, fs=fs)
    iterations = BUDGET[name][quick]
    if name == "grey-box":
        coef = grey_box_start(lin.G, u_scale=float(lin.u_scale), y_scale=float(lin.y_scale),
                              fs=fs)
        model: torch.nn.Module = BoucWenOscillator(**coef, fs=fs, substeps=2)
        kind, window = "grey_box", 128
    else:
        element = {"feedback-duhem": {"name": "duhem", "hidden": 0},
                   "feedback-duhem-net": {"name": "duhem", "hidden": 8},
                   "feedback-plays": {"name": "play_hysteresis", "widths": PLAY_WIDTHS,
                                      "hidden": 16}}[name]
        torch.manual_seed(0)
        model = HysteresisFeedback(2, element, fs=fs, u_scale=float(lin.u_scale),
                                   y_scale=float(lin.y_scale))
        init_from_linear(model, lin.G, fraction=0.5)
        kind, window = "feedback", 256
    fit = fit_windows(model, u, y, fs=fs, window=window, iterations=iterations,
                      validation=PERIOD, lr=1.0, optimizer="lbfgs", eval_every=10, log=log)
    log(f"  {name}: {fit.iterations} iterations, validation rmse {fit.val_rmse:.4g}")
    return kind, model, time.perf_counter() - start


def build(saved: dict) -> torch.nn.Module:
    """A model from a saved file's dict."""
    model = KINDS[saved["kind"]](**saved["config"])
    model.load_state_dict(saved["state_dict"])
    return model


def fmt(x: float | None) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{x:.2e}"


def table(rows: list[dict]) -> str:
    lines = ["| model | multisine RMSE (m) | multisine from rest (m) | sine sweep RMSE (m) "
             "| training time (s) |", "|---|---|---|---|---|"]
    for r in rows:
        res = r["results"]
        lines.append(f"| {r['label']} | {fmt(res['multisine'])} | "
                     f"{fmt(res['multisine_from_rest'])} | {fmt(res['sinesweep'])} | "
                     f"{r['seconds']:.0f} |")
    for name, value in PUBLISHED.items():
        lines.append(f"| {name} (published) | {value:.2e} | | | |")
    return "\n".join(lines)


LABELS = {"feedback-duhem": "feedback, Duhem element (black box)",
          "feedback-duhem-net": "feedback, Duhem element, slopes + 8 tanh units (black box)",
          "feedback-plays": "feedback, 8 plays + MLP (black box)",
          "grey-box": "Bouc-Wen oscillator (grey box, not comparable)"}


def _order(path: Path) -> tuple[int, str]:
    names = ("linear", "feedback-duhem", "feedback-duhem-net", "feedback-plays", "grey-box")
    return (names.index(path.stem) if path.stem in names else len(names), path.stem)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--quick", action="store_true", help="small budget (smoke test)")
    parser.add_argument("--models", nargs="+", choices=MODELS + EXTRA, default=list(MODELS))
    parser.add_argument("--save", type=Path, help="directory for the trained models")
    parser.add_argument("--evaluate", type=Path,
                        help="a saved model file, or a directory of them: evaluate, no training")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)  # the loops are latency-bound: threads only add contention
    d = load(args.data)
    fs = float(d["fs"])
    rows = []
    if args.evaluate is not None:
        files = (sorted(args.evaluate.glob("*.pt"), key=_order) if args.evaluate.is_dir()
                 else [args.evaluate])
        if not files:
            raise SystemExit(f"no saved models (*.pt) in {args.evaluate}")
        for path in files:
            saved = torch.load(path, weights_only=True)
            results = evaluate(build(saved), d, fs)
            rows.append({"label": saved["label"], "results": results,
                         "seconds": saved["seconds"]})
    else:
        for name in args.models:
            print(f"training {name} ...", flush=True)
            kind, model, seconds = train(name, d, fs, args.quick,
                                         lambda s: print(s, flush=True))
            results = evaluate(model, d, fs)
            label = f"linear (order {model.order})" if kind == "linear" else LABELS[name]
            row = {"label": label, "results": results, "seconds": seconds}
            rows.append(row)
            print(f"  {results}", flush=True)
            if args.save is not None:
                args.save.mkdir(parents=True, exist_ok=True)
                torch.save({"kind": kind, "config": model.config(),
                            "state_dict": model.state_dict(), **row},
                           args.save / f"{name}.pt")
    print(table(rows))
    return rows


if __name__ == "__main__":
    main()
