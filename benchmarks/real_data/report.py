"""The markdown table, the targets' tally, and tables saved with ``--out`` read back."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path

from .rows import COLUMNS, MODELS


def markdown(rows: list[dict]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in rows:
        lines.append(f"| {r['dataset']} | {r['model']} | {r['rmse']:.4g} | {r['ratio']:.3f} | "
                     f"{r['n_train']} | {r['n_test']} | {r['choice']} |")
    return "\n".join(lines)


TARGET = 0.5
"""The target ratio: at most half the error of the better memoryless baseline."""
FAMILIES = tuple(m for m in MODELS if m not in ("line", "poly", "default"))
"""The hysteresis model families (the rows that a "best family" is chosen among)."""


def targets(rows: Sequence[dict]) -> str:
    """The targets' tally over the protocols of ``rows`` (a table, as :func:`evaluate` or a
    saved CSV gives it): the default's ratio at most :data:`TARGET` and its RMSE no worse
    than the line's, and the best family row's ratio at most :data:`TARGET`; each with the
    protocols that miss it. A protocol without a ``default`` row (``--models``) counts
    for the families only."""
    by: dict[str, dict[str, dict]] = {}
    for r in rows:
        by.setdefault(r["dataset"], {})[r["model"]] = r
    n = len(by)
    with_default = {d: m for d, m in by.items() if "default" in m}
    ratio = {d: float(m["default"]["ratio"]) for d, m in with_default.items()}
    misses = [f"{d} {v:.2f}" for d, v in ratio.items() if not v <= TARGET]
    worse = [d for d, m in with_default.items()
             if not float(m["default"]["rmse"]) <= float(m["line"]["rmse"])]
    best = {}
    for d, m in by.items():
        scores = [(float(m[f]["ratio"]), f) for f in FAMILIES
                  if f in m and math.isfinite(float(m[f]["ratio"]))]
        if scores:
            best[d] = min(scores)
    fam_misses = [f"{d} {v:.2f} ({f})" for d, (v, f) in best.items() if not v <= TARGET]
    k = len(with_default)
    lines = [f"targets over {n} protocol{'s' * (n != 1)} (ratio <= {TARGET}; the default no "
             "worse than the line):"]
    if k:
        lines.append(f"  default: ratio <= {TARGET} on {k - len(misses)} of {k}"
                     + (f"; misses: {', '.join(misses)}" if misses else ""))
        lines.append(f"  default: no worse than the line on {k - len(worse)} of {k}"
                     + (f"; worse: {', '.join(worse)}" if worse else ""))
    if best:
        lines.append(f"  best family: ratio <= {TARGET} on {len(best) - len(fam_misses)} of "
                     f"{len(best)}" + (f"; misses: {', '.join(fam_misses)}" if fam_misses
                                       else ""))
    return "\n".join(lines)


def read_tables(paths: Sequence[Path]) -> list[dict]:
    """The rows of tables saved with ``--out`` (the numbers as floats).

    Raises:
        ValueError: a file without the table's columns (naming it).
    """
    rows = []
    for path in paths:
        with open(path, newline="") as f:
            reader = csv.DictReader(f)
            if tuple(reader.fieldnames or ()) != COLUMNS:
                raise ValueError(f"--tables {path}: expected the columns {', '.join(COLUMNS)}, "
                                 f"got {reader.fieldnames}")
            rows += [{**r, "rmse": float(r["rmse"]), "ratio": float(r["ratio"]),
                      "n_train": int(r["n_train"]), "n_test": int(r["n_test"])}
                     for r in reader]
    return rows
