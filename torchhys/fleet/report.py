"""The fleet report: outliers by a robust rule (:func:`flag_outliers`), ``fleet.csv``
(:func:`write_csv`), the picture of every device's loop (:func:`plot_loops`) and the summary
printed at the end (:func:`summary`).

The rule, over the devices identified (status ``ok``): a device is an outlier when its loop
width, its gain or its held-out ratio lies more than :data:`K` scaled median absolute
deviations from the fleet's median (``|v - median| > K * 1.4826 * MAD``; the 1.4826 makes
the MAD the standard deviation of normal data), or when its chosen family differs from the
fleet's most common one (only with at least three devices, the mode held by more than half
of them). The scale is at least :data:`FLOOR` (3 %) of the median's magnitude: a fleet of
nearly identical devices does not flag its noise; a spread of zero flags nothing. The
reason names each rule the device breaks, with its value and the fleet's median.
"""

from __future__ import annotations

import csv
import math
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["COLUMNS", "FLOOR", "K", "MAD_SCALE", "flag_outliers", "plot_loops", "summary",
           "write_csv"]

K = 3.5
"""Scaled MADs beyond which a device's width, gain or ratio is an outlier."""
MAD_SCALE = 1.4826
"""The MAD's factor to the standard deviation of normal data."""
FLOOR = 0.03
"""The least scale, a fraction of the median's magnitude: in a fleet of nearly identical
devices the MAD is tiny and noise would be flagged; with it, a quantity within
``K * FLOOR`` (10.5 %) of the median is never an outlier."""

COLUMNS = ("device", "status", "candidate", "family", "ratio", "width", "gain", "fit_s",
           "outlier", "outlier_reason", "reason", "run_dir", "config")
"""The columns of ``fleet.csv``."""

_QUANTITIES = (("width", "loop width"), ("gain", "gain"), ("ratio", "held-out ratio"))


def flag_outliers(rows: Sequence[dict[str, Any]], k: float = K) -> list[dict[str, Any]]:
    """``rows`` with ``outlier`` (bool) and ``outlier_reason`` set by the module's rule
    (failed devices: False, their failure is their ``reason``); new dicts, same order."""
    out = [{**r, "outlier": False, "outlier_reason": ""} for r in rows]
    ok = [r for r in out if r.get("status") == "ok"]
    reasons: dict[int, list[str]] = {id(r): [] for r in ok}
    for key, label in _QUANTITIES:
        values = np.array([float(r.get(key, math.nan)) for r in ok], dtype=np.float64)
        finite = values[np.isfinite(values)]
        if finite.size < 3:
            continue
        med = float(np.median(finite))
        scale = max(MAD_SCALE * float(np.median(np.abs(finite - med))), FLOOR * abs(med))
        if scale <= 0:
            continue
        for r, v in zip(ok, values, strict=True):
            if math.isfinite(v) and abs(v - med) > k * scale:
                reasons[id(r)].append(f"{label} {v:.4g} vs median {med:.4g} "
                                      f"({abs(v - med) / scale:.1f} scaled MADs)")
    families = Counter(r.get("family", "") for r in ok)
    if len(ok) >= 3 and families:
        mode, count = families.most_common(1)[0]
        if count * 2 > len(ok):
            for r in ok:
                if r.get("family", "") != mode:
                    reasons[id(r)].append(f"family {r.get('family')} vs the fleet's {mode} "
                                          f"({count} of {len(ok)})")
    for r in ok:
        if reasons[id(r)]:
            r["outlier"], r["outlier_reason"] = True, "; ".join(reasons[id(r)])
    return out


def _cell(value: Any) -> Any:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, float):
        return repr(value)
    return "" if value is None else value


def write_csv(rows: Sequence[dict[str, Any]], path: str | Path) -> Path:
    """``fleet.csv``: one row per device, the :data:`COLUMNS` (``outlier`` 0/1)."""
    path = Path(path)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(COLUMNS)
        for r in rows:
            w.writerow([_cell(r.get(c, "")) for c in COLUMNS])
    return path


def plot_loops(rows: Sequence[dict[str, Any]], path: str | Path) -> Path | None:
    """Every identified device's loop on the standard sweep (:mod:`torchhys.fleet.loops`),
    the good ones thin and grey, the outliers thick, coloured and named; a PNG (Agg
    backend). None when matplotlib is missing or no device has a loop."""
    try:
        import matplotlib

        matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    loops = [r for r in rows if r.get("loop")]
    if not loops:
        return None
    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    for r in loops:
        if not r.get("outlier"):
            ax.plot(r["loop"]["x"], r["loop"]["y"], color="0.6", lw=0.8, alpha=0.7)
    colours = plt.get_cmap("tab10")
    for i, r in enumerate(x for x in loops if x.get("outlier")):
        ax.plot(r["loop"]["x"], r["loop"]["y"], color=colours(i % 10), lw=2.0,
                label=f"{r['device']} (outlier)")
    bad = sum(1 for r in loops if r.get("outlier"))
    ax.set_title(f"{len(loops)} devices' fitted loops on the standard sweep, {bad} outliers")
    ax.set_xlabel("model input")
    ax.set_ylabel("model output")
    if bad:
        ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def _spread(values: list[float]) -> str:
    v = np.array([x for x in values if math.isfinite(x)], dtype=np.float64)
    if v.size == 0:
        return "n/a"
    return (f"median {np.median(v):.4g}, MAD {MAD_SCALE * np.median(np.abs(v - np.median(v))):.3g}"
            f" (scaled), range {v.min():.4g}..{v.max():.4g}")


def summary(rows: Sequence[dict[str, Any]], folder: str | Path, seconds: float) -> str:
    """The lines printed at the end of a fleet run: counts, the fleet's distribution of
    each quantity, its families, each outlier and each failure with its reason."""
    ok = [r for r in rows if r.get("status") == "ok"]
    failed = [r for r in rows if r.get("status") != "ok"]
    resumed = sum(1 for r in rows if r.get("resumed"))
    lines = [f"fleet {folder}: {len(rows)} devices, {len(ok)} identified "
             f"({resumed} from an earlier run), {len(failed)} failed, "
             f"{sum(1 for r in ok if r.get('outlier'))} outliers; {seconds:.1f} s"]
    for key, label in (*_QUANTITIES, ("fit_s", "fit seconds")):
        lines.append(f"  {label}: {_spread([float(r.get(key, math.nan)) for r in ok])}")
    families = Counter(r.get("family", "") for r in ok)
    if families:
        lines.append("  families: " + ", ".join(f"{f} {n}" for f, n in families.most_common()))
    for r in ok:
        if r.get("outlier"):
            lines.append(f"  outlier {r['device']}: {r['outlier_reason']}")
    for r in failed:
        lines.append(f"  failed {r['device']}: {r.get('reason', '')}")
    return "\n".join(lines)
