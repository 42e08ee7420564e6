"""What the exported compensator's input clamp and direction guard cost on measured data.

For each protocol of the real-data benchmark (``benchmarks.real_data``) whose files are
present, the model that ``configs/measured.yaml`` chooses (the ``default`` row, trained once)
is scored on the held-out recordings four ways:

- ``saturated``: the network's output saturated to the training target range (the
  ``default`` row of the real-data table);
- ``clamp``: through :class:`~torchhys.deploy.streaming.StreamingCompensator` with the input clamp
  only (``direction="none"``: the input clamped to the training input range widened by 5 %);
- ``guard``: with the direction guard only (``input_margin=None``);
- ``both``: as ``torchhys export`` deploys it by default (the clamp, and the guard where the
  training data have a clear trend, :data:`~torchhys.deploy.ranges.MIN_TREND`);
- ``forced guard``: the guard alone forced on in the direction of the trend's sign, however
  weak the trend (``--direction increasing`` or ``decreasing``).

Each is given as the ratio of its RMSE to the better memoryless baseline's (a straight line
or a polynomial, as in the real-data table). One process per protocol, ``--jobs`` at a
time, one torch thread each::

    python -m benchmarks.deploy_safety --jobs 2 [--data NAME ...] [--out deploy_safety.csv]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

from benchmarks import real_data as rd
from torchhys.deploy.ranges import default_limits
from torchhys.deploy.streaming import StreamingCompensator

VARIANTS = {"clamp": {"direction": "none"}, "guard": {"input_margin": None}, "both": {}}
"""The compensator's options of each scored variant beside ``saturated``."""
COLUMNS = ("dataset", "line", "poly", "saturated", "clamp", "guard", "both", "forced_guard",
           "trend", "guarded", "choice")


def score(name: str) -> dict:
    """The held-out RMSE of the line, the polynomial and the four variants of ``default``."""
    torch.set_num_threads(1)
    split = rd.DATASETS[name].build(rd.Files())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        net, choice, _ = rd.default_net(split, rd.FULL)
    dtype = next(net.parameters()).dtype
    low, high = default_limits(net)
    f64 = torch.float64
    row = {"dataset": name, "choice": choice,
           "line": rd.test_rmse(rd.line(split, rd.FULL).predict, split)[0],
           "poly": rd.test_rmse(rd.poly(split, rd.FULL).predict, split)[0],
           "saturated": rd.test_rmse(
               lambda v: net(v.to(dtype))[0].to(f64).clamp(low, high), split)[0]}
    for label, options in VARIANTS.items():
        comp = StreamingCompensator(net, **options).eval()
        row[label] = rd.test_rmse(lambda v, c=comp: c(v.to(dtype)).to(f64), split)[0]
    # the guard forced on, in the direction of the trend's sign however weak it is
    forced = "increasing" if float(net.trend) >= 0 else "decreasing"
    comp = StreamingCompensator(net, input_margin=None, direction=forced).eval()
    row["forced_guard"] = rd.test_rmse(lambda v: comp(v.to(dtype)).to(f64), split)[0]
    row["trend"] = float(net.trend)
    row["guarded"] = int(StreamingCompensator(net).guard)
    return row


def available() -> list[str]:
    """The protocols whose files are present."""
    files = rd.Files()
    return [n for n, p in rd.DATASETS.items() if not (p.needs and files.missing(p.needs))]


def _one(name: str) -> dict:
    path = os.environ.get("PYTHONPATH")  # the checkout's root first: benchmarks is in it
    root = os.pathsep.join([str(rd.ROOT), *([path] if path else [])])
    run = subprocess.run([sys.executable, "-m", "benchmarks.deploy_safety", "--one", name],
                         capture_output=True, text=True,
                         env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": root})
    if run.returncode != 0:
        return {"dataset": name, "choice": f"failed: {run.stderr.strip().splitlines()[-1:]}"}
    return json.loads(run.stdout.strip().splitlines()[-1])


def table(rows: list[dict]) -> str:
    """Markdown: each variant's ratio to the better memoryless baseline."""
    lines = ["| dataset | trend r | saturated | clamp | guard | exported (clamp, guard where "
             "\\|r\\| >= 0.5) | forced guard |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "saturated" not in r:
            lines.append(f"| {r['dataset']} | {r['choice']} | | | | | |")
            continue
        base = min(r["line"], r["poly"])
        cells = " | ".join(f"{r[k] / base:.3f}" for k in ("saturated", "clamp", "guard", "both",
                                                         "forced_guard"))
        lines.append(f"| {r['dataset']} | {r['trend']:+.2f} | {cells} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", default=None, help="protocols (default: all "
                        "whose files are present)")
    parser.add_argument("--jobs", type=int, default=1, help="protocols run at once")
    parser.add_argument("--out", type=Path, default=None, help="write the rows to this CSV")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one is not None:
        print(json.dumps(score(args.one)), flush=True)
        return []
    names = args.data or available()
    unknown = sorted(set(names) - set(rd.DATASETS))
    if unknown:
        parser.error(f"--data: unknown protocol(s) {unknown}; valid: {sorted(rd.DATASETS)}")
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        rows = list(pool.map(_one, names))
    print(table(rows))
    if args.out is not None:
        with args.out.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, COLUMNS, extrasaction="ignore")
            writer.writeheader()
            writer.writerows(rows)
    return rows


if __name__ == "__main__":
    main()
