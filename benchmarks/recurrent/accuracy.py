"""Held-out accuracy of recurrent models with and without hysteresis features.

Every model is a plain ``nn.Module`` (``forward(x (batch, time)) -> y (batch, time)``),
trained the same way: Adam on random windows of the fitting part (the first ``burn``
samples of each window only run the states), the validation RMSE (a free run of the whole
training rows from rest, scored after the fitting part) every ``every`` steps, the best
state kept, stopped after ``patience`` evaluations without improvement; each of the seeds
trains once and the seed of least validation RMSE is kept. The held-out recordings are
scored once, by that model. Models see the input and target standardized on the fitting
part.
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from benchmarks.real_data import DATASETS, QUICK, Files, Split, holdout, line, poly
from benchmarks.real_data.datasets import ROOT
from torchhys import Backlash

BOUC_WEN = ROOT.parent / "shared" / "data" / "bouc_wen_benchmark.npz"
PERIOD = 8192
"""Samples in one period of the Bouc-Wen multisines (the training record holds 5)."""
REAL = ("mr_damper_3.21V", "pneumatic_oring")
"""The shipped recordings scored by default (their protocols of benchmarks/real_data)."""


# --- models ------------------------------------------------------------------------------


class PlaysGRU(nn.Module):
    """``plays`` learnable play operators of the input beside the input itself, into a GRU of
    ``hidden`` units, a linear read-out: x (batch, time) -> y (batch, time)."""

    def __init__(self, plays: int = 8, hidden: int = 8, width: float = 0.25) -> None:
        super().__init__()
        self.plays = Backlash([width * (k + 1) for k in range(plays)], learnable=True)
        self.gru = nn.GRU(1 + plays, hidden, batch_first=True)
        self.out = nn.Linear(hidden, 1)

    def forward(self, x: Tensor) -> Tensor:
        p = self.plays(x)[0]
        h = self.gru(torch.cat([x.unsqueeze(-1), p], -1))[0]
        return self.out(h).squeeze(-1)


class Recurrent(nn.Module):
    """One ``nn.GRU`` or ``nn.LSTM`` layer of ``hidden`` units on the input, a linear read-out:
    x (batch, time) -> y (batch, time)."""

    def __init__(self, kind: str, hidden: int) -> None:
        super().__init__()
        layers = {"gru": nn.GRU, "lstm": nn.LSTM}
        if kind not in layers:
            raise ValueError(f"Recurrent: kind must be 'gru' or 'lstm', got {kind!r}")
        self.rnn = layers[kind](1, hidden, batch_first=True)
        self.out = nn.Linear(hidden, 1)

    def forward(self, x: Tensor) -> Tensor:
        return self.out(self.rnn(x.unsqueeze(-1))[0]).squeeze(-1)


MODELS: dict[str, Callable[[], nn.Module]] = {
    "8 plays + GRU 8": lambda: PlaysGRU(8, 8),
    "GRU 8": lambda: Recurrent("gru", 8),
    "GRU 16": lambda: Recurrent("gru", 16),
    "LSTM 16": lambda: Recurrent("lstm", 16),
}
"""The trained models by row label."""


def n_params(model: nn.Module) -> int:
    """The number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


# --- the data ----------------------------------------------------------------------------

Recording = tuple[Tensor, Tensor, int]
"""A held-out recording ``(x, y, warmup)``: run from rest, scored from ``warmup``."""


class Task(NamedTuple):
    """A data set's training rows, its validation cut and its held-out recordings."""

    name: str
    x: Tensor
    """Training input, (rows, time), physical units, float64."""
    y: Tensor
    warmup: int
    """Leading samples of each training row that are neither fitted nor validated."""
    cut: int
    """First validation sample of each training row (the fitting part lies before it)."""
    tests: dict[str, list[Recording]]
    """Held-out recordings by column name."""
    window: int
    """Training window length (samples)."""


def bouc_wen(path=BOUC_WEN) -> Task:
    """The Bouc-Wen benchmark as benchmarks/bouc_wen_benchmark.py runs it: the first 4
    periods of the training multisine fit, the 5th validates; held out: the multisine test
    (two periods of its input from rest, the second scored) and the sine sweep (from rest)."""
    d = np.load(path)
    t = {k: torch.as_tensor(np.asarray(d[k], dtype=float)) for k in d.files}
    u, y = t["test_multisine_u"], t["test_multisine_y"]
    tests = {"multisine": [(u.repeat(2), y.repeat(2), len(u))],
             "sine sweep": [(t["test_sinesweep_u"], t["test_sinesweep_y"], 0)]}
    x = t["train_u"][None]
    return Task("bouc_wen", x, t["train_y"][None], 0, x.shape[1] - PERIOD, tests, 512)


def real(name: str) -> Task:
    """A protocol of benchmarks/real_data: its training rows, the hold-out inside them
    (:func:`benchmarks.real_data.holdout`: the last quarter of each row's scored samples)
    and its held-out recordings."""
    s = DATASETS[name].build(Files())
    return Task(name, s.x, s.y, s.warmup, holdout(s.x.shape[1], s.warmup),
                {"held-out": s.test}, 256)


def task(name: str) -> Task:
    """``bouc_wen`` or the name of a protocol of benchmarks/real_data."""
    if name == "bouc_wen":
        return bouc_wen()
    if name not in DATASETS:
        raise ValueError(f"--data: expected 'bouc_wen' or one of {sorted(DATASETS)}, got "
                         f"{name!r}")
    return real(name)


# --- training ----------------------------------------------------------------------------


class Budget(NamedTuple):
    """How every model trains."""

    steps: int
    """Adam steps at most."""
    seeds: tuple[int, ...]
    batch: int = 32
    lr: float = 1e-2
    burn: int = 64
    """Leading samples of a window that only run the states."""
    every: int = 25
    """Steps between validations."""
    patience: int = 6
    """Validations without improvement before stopping."""
    window: int | None = None
    """Window length (None: the task's)."""


FULL = Budget(steps=600, seeds=(0, 1))
QUICK_BUDGET = Budget(steps=4, seeds=(0,), batch=4, burn=8, every=2, patience=1, window=48)


class Scale(NamedTuple):
    mx: float
    sx: float
    my: float
    sy: float


def scale_of(t: Task) -> Scale:
    x, y = t.x[:, t.warmup:t.cut], t.y[:, t.warmup:t.cut]
    return Scale(float(x.mean()), float(x.std()), float(y.mean()), float(y.std()))


def predictor(model: nn.Module, s: Scale) -> Callable[[Tensor], Tensor]:
    """Physical units in and out, float64 out; rows (rows, time)."""
    def predict(x: Tensor) -> Tensor:
        with torch.no_grad():
            xs = ((x - s.mx) / s.sx).to(torch.float32)
            return model(xs).to(torch.float64) * s.sy + s.my
    return predict


def validation_rmse(predict: Callable[[Tensor], Tensor], t: Task) -> float:
    """RMSE of a free run of the training rows from rest, after the cut."""
    return _rmse(predict(t.x)[:, t.cut:], t.y[:, t.cut:])


def _rmse(a: Tensor, b: Tensor) -> float:
    return float((a - b).square().mean().sqrt())


def train_once(make: Callable[[], nn.Module], t: Task, b: Budget, seed: int
               ) -> tuple[nn.Module, float, int]:
    """One seed: (the model of least validation RMSE, that RMSE, the steps run)."""
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    model = make()
    s = scale_of(t)
    xs = ((t.x - s.mx) / s.sx).to(torch.float32)
    ys = ((t.y - s.my) / s.sy).to(torch.float32)
    L = min(b.window or t.window, t.cut)
    weight = torch.zeros(t.x.shape[1])
    weight[t.warmup:t.cut] = 1.0
    opt = torch.optim.Adam(model.parameters(), lr=b.lr)
    best, state, since, step = math.inf, copy.deepcopy(model.state_dict()), 0, 0
    predict = predictor(model, s)
    for step in range(1, b.steps + 1):
        rows = torch.randint(0, t.x.shape[0], (b.batch,), generator=gen)
        starts = torch.randint(0, t.cut - L + 1, (b.batch,), generator=gen)
        idx = starts[:, None] + torch.arange(L)
        w = weight[idx]
        w[:, :b.burn] = 0.0
        err = model(xs[rows[:, None], idx]) - ys[rows[:, None], idx]
        loss = (err.square() * w).sum() / w.sum().clamp(min=1.0)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % b.every == 0 or step == b.steps:
            v = validation_rmse(predict, t)
            if v < best:
                best, state, since = v, copy.deepcopy(model.state_dict()), 0
            else:
                since += 1
                if since >= b.patience:
                    break
    model.load_state_dict(state)
    return model, best, step


class Row(NamedTuple):
    label: str
    params: int | None
    validation: float
    held_out: dict[str, float]
    choice: str
    seconds: float


def held_out(predict: Callable[[Tensor], Tensor], t: Task) -> dict[str, float]:
    """RMSE over the scored samples of each column's held-out recordings."""
    out = {}
    for col, recs in t.tests.items():
        e = torch.cat([(predict(x[None])[0] - y)[w:] for x, y, w in recs])
        out[col] = float(e.square().mean().sqrt())
    return out


def train_row(label: str, t: Task, b: Budget, log: Callable[[str], None]) -> Row:
    """Train ``MODELS[label]`` with every seed, keep the best on validation, score it once."""
    start = time.perf_counter()
    runs = []
    for seed in b.seeds:
        model, v, steps = train_once(MODELS[label], t, b, seed)
        log(f"  {t.name} {label} seed {seed}: {steps} steps, validation {v:.4g}")
        runs.append((v, seed, steps, model))
    v, seed, steps, model = min(runs, key=lambda r: r[0])
    res = held_out(predictor(model, scale_of(t)), t)
    return Row(label, n_params(model), v, res, f"seed {seed}, {steps} steps",
               time.perf_counter() - start)


def baseline_rows(t: Task) -> list[Row]:
    """The memoryless line and polynomial of benchmarks/real_data/baselines.py, fitted on
    the training rows (their own hold-out: the last quarter of the scored samples)."""
    split = Split(t.x, t.y, t.warmup, [r for recs in t.tests.values() for r in recs])
    rows = []
    for label, fit in (("line", line), ("poly", poly)):
        start = time.perf_counter()
        f = fit(split, QUICK)
        rows.append(Row(label, None, validation_rmse(f.predict, t), held_out(f.predict, t),
                        f.choice, time.perf_counter() - start))
    return rows


def run(names: Sequence[str], b: Budget, labels: Sequence[str] = tuple(MODELS),
        log: Callable[[str], None] = print) -> dict[str, list[Row]]:
    """The rows of every data set."""
    out = {}
    for name in names:
        t = task(name)
        rows = baseline_rows(t)
        for label in labels:
            rows.append(train_row(label, t, b, log))
        out[name] = rows
    return out


def markdown(name: str, rows: list[Row]) -> str:
    """One data set's table; ``ratio``: held-out RMSE / the better memoryless baseline's."""
    cols = list(rows[0].held_out)
    base = {c: min(r.held_out[c] for r in rows if r.params is None) for c in cols}
    head = " | ".join(f"{c} RMSE (ratio)" for c in cols)
    lines = [f"| {name} model | parameters | validation RMSE | {head} | choice | time (s) |",
             "|---" * (5 + len(cols)) + "|"]
    for r in rows:
        cells = " | ".join(f"{r.held_out[c]:.3g} ({r.held_out[c] / base[c]:.2f})"
                           for c in cols)
        lines.append(f"| {r.label} | {r.params if r.params is not None else '-'} | "
                     f"{r.validation:.3g} | {cells} | {r.choice} | {r.seconds:.0f} |")
    return "\n".join(lines)
