"""One protocol's rows: every model by name (:data:`MODELS`) fitted and scored, and the
``selected`` row."""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

from .baselines import line, poly
from .datasets import Split
from .default_row import CONFIG, default
from .families import (
    eiho_net,
    generalized_pi,
    jiles_atherton,
    pi_constrained,
    pi_ls,
    preisach,
    stop_pi,
    stop_pi_drift,
)
from .scoring import Budget, Fitted, NotApplicable, test_rmse

COLUMNS = ("dataset", "model", "rmse", "ratio", "n_train", "n_test", "choice")


MODELS: dict[str, Callable[..., Fitted]] = {
    "line": line,
    "poly": poly,
    "pi_constrained": pi_constrained,
    "pi_ls": pi_ls,
    "generalized_pi": generalized_pi,
    "preisach": preisach,
    "stop_pi": stop_pi,
    "stop_pi_drift": stop_pi_drift,
    "jiles_atherton": jiles_atherton,
    "eiho_net": eiho_net,
    "default": default,
}
"""The models by name, in table order; ``selected`` follows them."""


def evaluate(name: str, split: Split, budget: Budget, log: list[str], *,
             config: Path = CONFIG, models: Sequence[str] = tuple(MODELS)) -> list[dict]:
    """One row per model of ``models`` (held-out RMSE, ratio to the best memoryless
    baseline, choice; the line and the polynomial always), then ``selected``: the model with
    the least hold-out RMSE among them."""
    rows = []
    n_train = split.y[:, split.warmup:].numel()
    for model, run in MODELS.items():
        if model not in models and model not in ("line", "poly"):
            continue
        start = time.perf_counter()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                fitted = run(split, budget, config) if model == "default" else run(split, budget)
            rmse, n_test = test_rmse(fitted.predict, split)
            choice, score = f"{fitted.choice}; hold-out {fitted.holdout:.4g}", fitted.holdout
        except NotApplicable as err:
            rmse, n_test, choice, score = math.nan, 0, f"n/a: {err}", math.inf
        except (ValueError, RuntimeError, FloatingPointError) as err:
            rmse, n_test, choice, score = math.nan, 0, f"failed: {err}", math.inf
        rows.append({"dataset": name, "model": model, "rmse": rmse, "n_train": n_train,
                     "n_test": n_test, "choice": choice, "holdout": score})
        log.append(f"{name:24s} {model:15s} {time.perf_counter() - start:6.1f} s")
    best = min(rows, key=lambda r: r["holdout"] if math.isfinite(r["holdout"]) else math.inf)
    rows.append({**best, "model": "selected", "choice": f"{best['model']}: {best['choice']}"})
    base = min(r["rmse"] for r in rows if r["model"] in ("line", "poly"))
    for r in rows:
        r["ratio"] = r["rmse"] / base
    return [{k: r[k] for k in COLUMNS} for r in rows]
