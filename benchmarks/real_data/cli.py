"""Held-out accuracy of hysteresis models on measured recordings (see docs/real-data.md).

The command line of ``python -m benchmarks.real_data`` (the package's docstring says what
it measures).
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

from .datasets import FERRITE, PIEZO, QUAD, ROOT
from .default_row import CONFIG
from .protocols import DATASETS, Files
from .report import markdown, read_tables, targets
from .rows import COLUMNS, MODELS, evaluate
from .scoring import FULL, QUICK


def run_in_processes(args: argparse.Namespace, jobs: int) -> tuple[list[dict], list[str]]:
    """Each protocol of ``args.data`` in a process of its own (``python -m
    benchmarks.real_data`` with the same options and ``--data NAME``), ``jobs`` at a time;
    their tables read back in the order of ``args.data``, and their logs.

    Raises:
        RuntimeError: a protocol's process failed (its name and the end of its output).
    """
    common = ["--ferrite", str(args.ferrite), "--piezo", str(args.piezo), "--quad",
              str(args.quad), "--config", str(args.config), "--models", *args.models]
    if args.quick:
        common.append("--quick")
    path = os.environ.get("PYTHONPATH")  # the checkout's root first: benchmarks is in it
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), *([path] if path else [])])}
    with tempfile.TemporaryDirectory() as tmp:
        def one(name: str) -> tuple[str, str]:
            out = Path(tmp) / f"{name}.csv"
            done = subprocess.run([sys.executable, "-m", "benchmarks.real_data", "--data",
                                   name, "--out", str(out), *common],
                                  capture_output=True, text=True, env=env)
            if done.returncode != 0:
                raise RuntimeError(f"{name}: its process failed ({done.returncode}):\n"
                                   + (done.stdout + done.stderr)[-2000:])
            return str(out), done.stdout

        with ThreadPoolExecutor(max_workers=jobs) as pool:
            results = list(pool.map(one, args.data))
        rows = read_tables([Path(out) for out, _ in results])
    logs = [text.split("\ntotal ", 1)[0].strip() for _, text in results]
    return rows, logs


def main(argv: list[str] | None = None) -> list[dict]:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.real_data",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--data", nargs="+", choices=list(DATASETS), default=list(DATASETS),
                        metavar="NAME", help=f"data sets (default: all): {', '.join(DATASETS)}")
    parser.add_argument("--out", type=Path, default=None, help="write the table to this CSV")
    parser.add_argument("--quick", action="store_true", help="small grids (smoke test)")
    parser.add_argument("--ferrite", type=Path, default=FERRITE,
                        help="the MnZn ferrite loops (default: ../shared/data/...)")
    parser.add_argument("--piezo", type=Path, default=PIEZO,
                        help="the SmartHysteresis piezo record as published (not shipped; "
                        "default: examples/data/external/hysteresis_v_150_1hz.csv)")
    parser.add_argument("--quad", type=Path, default=QUAD,
                        help="folder of the SLAC quadrupole runs strdat.ru3..ru8 as published "
                        "(not shipped; default: examples/data/external/slac_quad_4194)")
    parser.add_argument("--config", type=Path, default=CONFIG,
                        help="torchhys fit config of the 'default' row")
    parser.add_argument("--jobs", type=int, default=1,
                        help="protocols run at a time, each in a process of its own with one "
                        "thread (default 1: all in this process)")
    parser.add_argument("--tables", type=Path, nargs="+", default=None, metavar="CSV",
                        help="fit nothing: print the table and the targets' tally of tables "
                        "saved with --out (e.g. one per protocol)")
    parser.add_argument("--models", nargs="+", choices=list(MODELS), default=list(MODELS),
                        metavar="MODEL", help="rows to fit (default: all; the line and the "
                        f"polynomial always): {', '.join(MODELS)}")
    args = parser.parse_args(argv)
    if args.tables is not None:
        rows = read_tables(args.tables)
        print(markdown(rows) + "\n\n" + targets(rows))
        return rows
    if args.jobs < 1:
        parser.error(f"--jobs must be at least 1, got {args.jobs}")
    torch.set_num_threads(1)
    budget = QUICK if args.quick else FULL
    rows: list[dict] = []
    log: list[str] = []
    start = time.perf_counter()
    files = Files(args.ferrite, args.piezo, args.quad)
    if args.jobs > 1 and len(args.data) > 1:
        rows, log = run_in_processes(args, args.jobs)
    else:
        for name in args.data:
            protocol, build, need = DATASETS[name]
            missing = [] if need is None else files.missing(need)
            if missing:
                print(f"skipping {name}: {missing[0]} not found (--{need})")
                continue
            log.append(f"{name}: {protocol}")
            rows += evaluate(name, build(files), budget, log, config=args.config,
                             models=args.models)
    print("\n".join(log))
    print(f"\ntotal {time.perf_counter() - start:.0f} s\n")
    print(markdown(rows))
    print("\n" + targets(rows))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with open(args.out, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=COLUMNS)
            writer.writeheader()
            writer.writerows(rows)
    return rows
