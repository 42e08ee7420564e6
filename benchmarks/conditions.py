"""When an operating-condition input pays: unconditioned, per-condition and conditioned models.

    python benchmarks/conditions.py [--datasets NAME ...] [--quick]

On the shipped MR damper (coil voltage), the pneumatic cylinder's seals (supply pressure) and
a simulated piezo stage whose hysteresis width and gain vary with temperature, three models
read the *same* operator features of the input (plays, :class:`torchhys.Backlash`, of widths
:func:`~torchhys.identification.fitting.play_width_grid` over the input's training range):

- ``unconditioned``: one affine readout fitted on every training condition
  (:class:`~torchhys.networks.InverseHysteresisNet`, identity activation, ``hidden=1``,
  solved by :func:`~torchhys.selection.candidates.solve_readout`);
- ``per-condition``: that readout fitted on each training condition alone (the oracle at a
  seen condition; at the held-out condition the nearest training condition's readout);
- ``conditioned``: :class:`~torchhys.conditions.ScheduledReadout`, the readout's weights
  Legendre polynomials of degree ``degree`` in the condition;
- ``fit``: the model ``torchhys fit --config configs/conditions.yaml`` builds on the
  training recordings (:func:`config_selection`: :func:`torchhys.selection.select` over that
  config's ``model.select`` candidates, leaving one condition out), and ``fit,
  unconditioned``, the same selection over its candidates that do not take the condition.
  These read their own features (the config's line and fitted stop models), not the plays.

The plays' number and grid power and the conditioned model's degree are chosen by
leave-one-condition-out cross-validation over the training conditions only (pooled RMSE of
the left-out condition's training recordings, each fold's plays over its own training
input; a degree is a candidate only where every fold
still has ``degree + 1`` conditions to fit it). The baseline is the best memoryless model that
sees the same inputs: a tensor-product Legendre polynomial in the input (degree 1..7) and the
condition (degree 0..2 under the same rule), chosen by the same cross-validation.

Each model is fitted once on the training part and scored once on two protocols: the
held-out recordings at the training conditions ("seen conditions") and the same part of the
recordings at a held-out condition ("held-out condition"). Reported: RMSE in the target's
units, in brackets its ratio to the baseline's; ``ratio``: conditioned / unconditioned
(held-out condition, target <= 0.6) or conditioned / per-condition (seen conditions, target
<= 1.2); ``fit ratio``: fit / fit, unconditioned, or fit / per-condition, the same
targets. ``own / unconditioned``: a reference that no choice sees, the readout fitted on the
held-out condition's own training part over the unconditioned model, at the held-out
condition: the ratio a conditioned model that matched the per-condition oracle would reach.
Float64 throughout; progress on stderr. A model row is one function of :data:`MODELS`
(``fit(case, choice) -> predict(x, c)``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a file: the checkout

from benchmarks.real_data import SEALS, mr_damper, pneumatic  # noqa: E402
from torchhys import Backlash  # noqa: E402
from torchhys.conditions import ScheduledReadout  # noqa: E402
from torchhys.identification.fitting import play_width_grid  # noqa: E402
from torchhys.networks import InverseHysteresisNet  # noqa: E402
from torchhys.selection import select  # noqa: E402
from torchhys.selection.candidates import model_base, solve_readout  # noqa: E402
from torchhys.selection.folds import Batch  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "conditions.yaml"
"""The config whose ``model.select`` the ``torchhys fit`` rows choose among."""

F64 = torch.float64
Predict = Callable[[Tensor, float], Tensor]
"""A fitted model: ``predict(x (time,), condition) -> y (time,)``, from a zero state."""


class Recording(NamedTuple):
    """One recording at one condition: x, y (time,) float64; the first ``warmup`` samples
    only run the states (neither fitted nor scored)."""

    x: Tensor
    y: Tensor
    c: float
    warmup: int


class Case(NamedTuple):
    """A data set's protocol: training recordings at the training conditions, the held-out
    recordings at those conditions, and recordings at the held-out condition; ``own``: the
    training part at the held-out condition, fitted only for the reference the table prints
    beside the nearest condition's model (no choice uses it)."""

    name: str
    unit: str
    train: list[Recording]
    seen: list[Recording]
    held: list[Recording]
    own: list[Recording]


class Choice(NamedTuple):
    """The operator options (plays' count and grid power) and the conditioned degree."""

    n: int
    power: float
    degree: int


# --- the data ------------------------------------------------------------------------------

MR_VOLTS = (0.0, 0.8712, 1.98, 3.212)
PNEUMATIC_BAR = (1.0, 3.0, 5.0, 7.0)


def mr_case(hold: float = 1.98) -> Case:
    """Position (mm) -> force (N) of the MR damper at its four coil voltages
    (``benchmarks.real_data.mr_damper``: even recordings train, odd are held out, scored
    from t = 5 s); the voltage ``hold`` is held out (its odd recordings scored)."""
    train, seen, held, own = [], [], [], []
    for v in MR_VOLTS:
        s = mr_damper(v)
        rows = [Recording(x, y, v, s.warmup) for x, y in zip(s.x, s.y, strict=True)]
        test = [Recording(x, y, v, w) for x, y, w in s.test]
        if v == hold:
            held, own = held + test, own + rows
        else:
            train += rows
            seen += test
    return Case("mr_damper", "V", train, seen, held, own)


def pneumatic_case(seal: str | None = None, hold: float = 5.0) -> Case:
    """Position (mm) -> seal friction (N) at the four supply pressures
    (``benchmarks.real_data.pneumatic``; its 7 bar record cut to the 1 bar record's length):
    each record's first half trains, the whole record run from rest is scored on its second
    half; the pressure ``hold`` (bar) is held out (its second half scored)."""
    s = pneumatic(seal)
    records = {1.0: (s.x[0], s.y[0]), 7.0: (s.x[1], s.y[1]),
               3.0: s.test[0][:2], 5.0: s.test[1][:2]}
    train, seen, held, own = [], [], [], []
    for bar in PNEUMATIC_BAR:
        x, y = records[bar]
        cut = x.numel() // 2
        first, test = Recording(x[:cut], y[:cut], bar, 0), Recording(x, y, bar, cut)
        if bar == hold:
            held.append(test)
            own.append(first)
        else:
            train.append(first)
            seen.append(test)
    return Case(f"pneumatic_{seal or 'oring'}", "bar", train, seen, held, own)


PIEZO_TEMPS = (20.0, 30.0, 40.0, 50.0, 60.0)


def piezo_stage(x: np.ndarray, temp: float) -> np.ndarray:
    """A simulated piezo stage (drive V -> displacement um) at temperature ``temp`` (C): a
    Prandtl-Ishlinskii plant whose play half-widths and gain grow with temperature,

        y = g(T) (k0 x + sum_i w_i p[r_i s(T)](x)),   g(T) = 1 + 0.01 (T - 20),
        s(T) = 1 + 0.02 (T - 20),   r_i = 2.5 i V,   w_i = 0.1 exp(-(i - 1) / 4) um/V,

    ``i = 1..8``, ``k0 = 0.05`` um/V, each play ``p[r](t) = max(x(t) - r, min(x(t) + r,
    p(t - 1)))`` from ``p = 0`` (a plain loop, independent of torchhys): between 20 and
    60 C the loops widen 1.8 times and the gain rises 1.4 times."""
    r = 2.5 * np.arange(1, 9) * (1 + 0.02 * (temp - 20))
    w = 0.1 * np.exp(-np.arange(8) / 4)
    p, out = np.zeros(8), np.empty(len(x))
    for t, xt in enumerate(x):
        p = np.maximum(xt - r, np.minimum(xt + r, p))
        out[t] = 0.05 * xt + w @ p
    return (1 + 0.01 * (temp - 20)) * out


def piezo_drive(n: int, seed: int) -> np.ndarray:
    """A drive from rest over 0..100 V: two sines (about 0.5 and 1.7 Hz at 100 Hz sampling)
    under a slowly varying envelope, so the record holds major and minor loops."""
    g = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    f1, f2 = 0.5 * g.uniform(0.8, 1.2), 1.7 * g.uniform(0.8, 1.2)
    env = 0.6 + 0.4 * np.sin(2 * np.pi * 0.05 * t + g.uniform(0, 2 * np.pi))
    s = 0.65 * np.sin(2 * np.pi * f1 * t) + 0.35 * np.sin(2 * np.pi * f2 * t + g.uniform(0, 6))
    ramp = np.minimum(1.0, t / 2.0)  # from rest
    return np.clip(50 + 50 * ramp * env * s, 0, 100)


def piezo_case(hold: float = 40.0, n: int = 3000, noise: float = 0.01) -> Case:
    """The simulated stage at 20..60 C (:func:`piezo_stage`): a training drive and another
    held-out drive at every temperature (seeded), ``noise`` um of Gaussian sensor noise,
    the first 200 samples (2 s, the ramp from rest) only running the states; ``hold`` (C)
    held out (its held-out drive scored)."""
    g = np.random.default_rng(47)
    train, seen, held, own = [], [], [], []
    for k, temp in enumerate(PIEZO_TEMPS):
        recs = []
        for seed in (2 * k, 2 * k + 1):
            x = piezo_drive(n, seed)
            y = piezo_stage(x, temp) + noise * g.standard_normal(n)
            recs.append(Recording(torch.tensor(x, dtype=F64), torch.tensor(y, dtype=F64),
                                  temp, 200))
        if temp == hold:
            held.append(recs[1])
            own.append(recs[0])
        else:
            train.append(recs[0])
            seen.append(recs[1])
    return Case("piezo_sim" if hold == 40.0 else f"piezo_sim_{hold:g}C", "C", train, seen,
                held, own)


DATASETS: dict[str, Callable[[bool], Case]] = {
    "mr_damper": lambda quick: mr_case(),
    "pneumatic_oring": lambda quick: pneumatic_case(None),
    **{f"pneumatic_{k}": (lambda quick, k=k: pneumatic_case(k)) for k in SEALS},
    "piezo_sim": lambda quick: piezo_case(40.0, n=1500 if quick else 3000),
    "piezo_sim_60C": lambda quick: piezo_case(60.0, n=1500 if quick else 3000),
}


# --- fitting helpers -----------------------------------------------------------------------

def batch(recs: list[Recording]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """x, y (rows, time), conditions (rows, time, 1) and the fitted samples' mask of
    recordings of any lengths (a shorter row padded with its last sample, masked out)."""
    T = max(r.x.numel() for r in recs)

    def pad(v: Tensor) -> Tensor:
        return torch.cat([v, v[-1:].expand(T - v.numel())])

    x = torch.stack([pad(r.x) for r in recs])
    y = torch.stack([pad(r.y) for r in recs])
    c = torch.stack([torch.full((T,), r.c, dtype=F64) for r in recs])[..., None]
    idx = torch.arange(T)
    m = torch.stack([(idx >= r.warmup) & (idx < r.x.numel()) for r in recs])
    return x, y, c, m


def plays(recs: list[Recording], choice: Choice) -> list[Backlash]:
    """The plays of ``choice`` over the input's range in ``recs`` (fresh modules)."""
    x = torch.cat([r.x for r in recs])
    return [Backlash(play_width_grid(x, choice.n, power=choice.power))]


def rmse(predict: Predict, recs: list[Recording]) -> float:
    """The RMSE of ``predict`` pooled over the scored samples of ``recs``."""
    se, n = 0.0, 0
    for r in recs:
        with torch.no_grad():
            e = (predict(r.x, r.c) - r.y)[r.warmup:]
        se, n = se + float(e.square().sum()), n + e.numel()
    return math.sqrt(se / n)


def affine(recs: list[Recording], choice: Choice, case: Case) -> Predict:
    """The affine least-squares readout of the plays (over the training input's range) and
    x fitted on ``recs``."""
    net = InverseHysteresisNet(plays(case.train, choice), hidden=1,
                               activation="identity").double()
    x, y, _, m = batch(recs)
    net.fit_normalization(x, y, mask=m)
    with torch.no_grad():
        solve_readout(net, Batch(x, y, m))
    return lambda xt, c: net(xt)[0]


# --- the model rows ------------------------------------------------------------------------

def unconditioned(case: Case, choice: Choice) -> Predict:
    """(a) One affine readout fitted on every training condition."""
    return affine(case.train, choice, case)


def per_condition(case: Case, choice: Choice) -> Predict:
    """(b) An affine readout per training condition; at another condition the nearest
    training condition's."""
    conds = sorted({r.c for r in case.train})
    fits = {c: affine([r for r in case.train if r.c == c], choice, case) for c in conds}
    return lambda xt, c: fits[min(conds, key=lambda k: abs(k - c))](xt, c)


def conditioned(case: Case, choice: Choice, train: list[Recording] | None = None) -> Predict:
    """(c) The scheduled readout: weights Legendre polynomials of ``choice.degree`` in the
    condition, fitted on ``train`` (default: the training recordings; a fold's in the
    cross-validation), the plays over its input's range."""
    recs = case.train if train is None else train
    model = ScheduledReadout(plays(recs, choice), 1, degree=choice.degree)
    x, y, c, m = batch(recs)
    model.fit(x, c, y, mask=m)
    return lambda xt, cv: model(xt, torch.full((xt.numel(), 1), cv, dtype=F64))


def legendre_poly(recs: list[Recording], dx: int, dc: int, box: tuple) -> Predict:
    """The memoryless baseline: least squares on ``P_i(x~) P_j(c~)``, i <= dx, j <= dc
    (x and c scaled to [-1, 1] over ``box = (x_lo, x_hi, c_lo, c_hi)``), numpy float64."""
    x0, x1, c0, c1 = box

    def design(x: np.ndarray, c: np.ndarray) -> np.ndarray:
        vx = np.polynomial.legendre.legvander(2 * (x - x0) / (x1 - x0) - 1, dx)
        vc = np.polynomial.legendre.legvander(2 * (c - c0) / (c1 - c0) - 1, dc)
        return (vx[:, :, None] * vc[:, None, :]).reshape(len(x), -1)

    xs = np.concatenate([r.x[r.warmup:].numpy() for r in recs])
    cs = np.concatenate([np.full(r.x.numel() - r.warmup, r.c) for r in recs])
    ys = np.concatenate([r.y[r.warmup:].numpy() for r in recs])
    coef = np.linalg.lstsq(design(xs, cs), ys, rcond=None)[0]
    return lambda xt, c: torch.as_tensor(
        design(xt.numpy(), np.full(xt.numel(), c)) @ coef, dtype=F64)


def config_selection(case: Case, conditions: bool = True) -> Predict:
    """The model ``torchhys fit --config configs/conditions.yaml`` builds on the case's
    training recordings: :func:`torchhys.selection.select` over the config's
    ``model.select`` candidates (read from :data:`CONFIG`) from its model section, with its
    ``select_cv`` (leave one condition out), ``select_rule``, seed and epochs. With
    ``conditions=False``, its unconditioned counterpart: the same selection over the
    candidates without ``condition_degree`` only (on the same folds: none of them sees the
    conditions). The predictor's ``chosen`` names the chosen candidate."""
    import yaml

    cfg = yaml.safe_load(CONFIG.read_text())
    model = cfg["model"]
    cands = [c for c in model["select"] if conditions or c.get("condition_degree") is None]
    x, y, c, m = batch(case.train)
    res = select(cands, x, y, base=model_base(model), warmup=[r.warmup for r in case.train],
                 mask=m, cv=model["select_cv"], rule=model["select_rule"],
                 seed=cfg["seed_everything"], epochs=cfg["trainer"]["max_epochs"],
                 conditions=c, source=case.name, warn_coverage=False)
    net = res.fit()
    ops, degree = res.chosen.overrides.get("operator"), res.chosen.overrides.get(
        "condition_degree")
    name = "line" if ops is None else (
        f"{ops[0]['n_widths']} stops, {ops[0]['segments']} seg" if ops[0]["fit"] == "stop_pi"
        else f"{ops[0].get('n', '')} {ops[0]['fit']}")
    name += f", degree {degree}" if degree else ""

    def predict(xt: Tensor, cv: float) -> Tensor:
        if not net.n_conditions:
            return net(xt)[0]
        return net(xt, conditions=torch.full((xt.numel(), 1), cv, dtype=F64))[0]

    predict.chosen = name  # type: ignore[attr-defined]
    return predict


MODELS: dict[str, Callable[[Case, Choice], Predict]] = {
    "unconditioned": unconditioned,
    "per-condition": per_condition,
    "conditioned": conditioned,
    "fit": lambda case, choice: config_selection(case, True),
    "fit, unconditioned": lambda case, choice: config_selection(case, False),
}
"""The model rows: ``fit(case, choice) -> predict``; a new row is one more entry."""


# --- the choices by leave-one-condition-out CV ---------------------------------------------

def folds(case: Case) -> list[tuple[list[Recording], list[Recording]]]:
    """(training, left-out) recordings of each training condition left out in turn."""
    conds = sorted({r.c for r in case.train})
    return [([r for r in case.train if r.c != c], [r for r in case.train if r.c == c])
            for c in conds]


def loco(fit: Callable[[list[Recording]], Predict], case: Case) -> float:
    """The RMSE pooled over every left-out condition's scored training samples."""
    se, n = 0.0, 0
    for fitted, left in folds(case):
        e = rmse(fit(fitted), left)
        k = sum(r.x.numel() - r.warmup for r in left)
        se, n = se + e * e * k, n + k
    return math.sqrt(se / n)


def degrees(case: Case, top: int) -> list[int]:
    """Condition degrees 1..top every fold can fit (each fold keeps ``n - 1`` conditions)."""
    n = len({r.c for r in case.train})
    return [d for d in range(1, top + 1) if d <= n - 2] or [1]


def choose(case: Case, quick: bool) -> tuple[Choice, float]:
    """The conditioned model's plays and degree of least leave-one-condition-out RMSE."""
    grid = [Choice(n, p, d) for n in ((8,) if quick else (6, 12, 24, 48))
            for p in ((1.0,) if quick else (1.0, 2.0, 3.0)) for d in degrees(case, 2)]
    scores = [(loco(lambda recs, ch=ch: conditioned(case, ch, recs), case), ch) for ch in grid]
    best = min(scores, key=lambda s: s[0])
    return best[1], best[0]


def baseline(case: Case) -> tuple[Predict, str]:
    """The memoryless polynomial in x and c whose degrees have the least
    leave-one-condition-out RMSE, refitted on the training recordings."""
    xs = torch.cat([r.x for r in case.train])
    cs = [r.c for r in case.train]
    box = (float(xs.min()), float(xs.max()), min(cs), max(cs))
    grid = [(dx, dc) for dx in range(1, 8) for dc in [0, *degrees(case, 2)]]
    best = min(grid, key=lambda g: loco(lambda recs: legendre_poly(recs, *g, box), case))
    return legendre_poly(case.train, *best, box), f"x^{best[0]} c^{best[1]}"


# --- the table -----------------------------------------------------------------------------

COLUMNS = ["dataset", "protocol", "baseline RMSE", "unconditioned", "per-condition",
           "conditioned", "ratio", "target", "met", "own / unconditioned", "fit",
           "fit, unconditioned", "fit ratio", "fit met", "choice"]
TARGETS = {"held-out condition": ("conditioned", "unconditioned", 0.6),
           "seen conditions": ("conditioned", "per-condition", 1.2)}
FIT_TARGETS = {"held-out condition": ("fit", "fit, unconditioned"),
               "seen conditions": ("fit", "per-condition")}
"""The ``torchhys fit`` rows' ratio: over their own unconditioned counterpart at the held-out
condition, over the per-condition oracle at the seen ones (the targets of :data:`TARGETS`)."""


def evaluate(case: Case, quick: bool) -> list[dict[str, str]]:
    """The two rows (held-out condition, seen conditions) of one case."""
    start = time.perf_counter()
    choice, cv = choose(case, quick)
    base, base_choice = baseline(case)
    fitted = {name: fit(case, choice) for name, fit in MODELS.items()}
    held_c = case.held[0].c
    near = min({r.c for r in case.train}, key=lambda k: abs(k - held_c))
    out = []
    for protocol, recs in (("held-out condition", case.held), ("seen conditions", case.seen)):
        b = rmse(base, recs)
        errs = {name: rmse(p, recs) for name, p in fitted.items()}
        cells = {name: f"{e:.3g} ({e / b:.2f})" for name, e in errs.items()}
        bound = "n/a"
        if protocol == "held-out condition":
            e = rmse(affine(case.own, choice, case), recs)
            cells["per-condition"] += (f" nearest {near:.3g} {case.unit}; own {e:.3g} "
                                       f"({e / b:.2f})")
            bound = f"{e / errs['unconditioned']:.2f}"
        num, den, target = TARGETS[protocol]
        ratio = errs[num] / errs[den]
        fnum, fden = FIT_TARGETS[protocol]
        fit_ratio = errs[fnum] / errs[fden]
        out.append({"dataset": f"{case.name} ({held_c:.3g} {case.unit} held out)"
                    if protocol == "held-out condition" else case.name,
                    "protocol": protocol, "baseline RMSE": f"{b:.3g}", **cells,
                    "ratio": f"{ratio:.3f}", "target": f"<= {target}",
                    "met": "PASS" if ratio <= target else "MISS", "own / unconditioned": bound,
                    "fit ratio": f"{fit_ratio:.3f}",
                    "fit met": "PASS" if fit_ratio <= target else "MISS",
                    "choice": f"{choice.n} plays p={choice.power:g}, degree {choice.degree} "
                              f"(CV {cv:.3g}); baseline {base_choice}; fit "
                              f"{fitted['fit'].chosen}; unconditioned "
                              f"{fitted['fit, unconditioned'].chosen}"})
    print(f"{case.name}: {time.perf_counter() - start:.1f} s", file=sys.stderr)
    return out


def markdown(rows: list[dict[str, str]]) -> str:
    """The rows as a markdown table of :data:`COLUMNS`."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(r[c] for c in COLUMNS) + " |" for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict[str, str]]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", nargs="+", choices=list(DATASETS), default=list(DATASETS),
                        metavar="NAME", help=f"default: all of {', '.join(DATASETS)}")
    parser.add_argument("--quick", action="store_true",
                        help="a small grid and shorter simulated records (smoke test)")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    rows = []
    for name in args.datasets:
        print(f"{name} ...", file=sys.stderr)
        rows += evaluate(DATASETS[name](args.quick), args.quick)
    print(markdown(rows))
    return rows


if __name__ == "__main__":
    main()
