"""How long the default config for recorded data takes to fit, as a user runs it.

``torchhys fit --config configs/measured.yaml`` on the piezo micromanipulator's records
(``examples/data/real/piezo_micromanipulator.csv``: displacement in, voltage out, a
compensator), tiled to each size, as one record and as five recordings (a run column), each
fit a command of its own (the config's ``select_jobs: auto``: candidates in one process per
usable core, one torch thread each). Printed per run: the wall time, the seconds of each
candidate (from the command's progress lines: measured in the process that scored it), the
largest candidate, and the peak memory (the largest maximum resident set of the command's
processes). Then the same fit two and three at a time against one alone (each run's wall time
over the alone run's), the thrashing of oversubscribed threads that the command's one-thread
default avoids. ``--threads`` passes a thread count to every fit (``torchhys fit --threads``),
to measure that thrashing; ``--jobs`` passes ``--model.select_jobs`` (1: every candidate in
the command's process); ``--candidates`` prints every candidate's seconds under each run;
``--profile N`` then fits N samples in one process under cProfile and prints the seconds of
each stage (start-up, reading, the families' least-squares moments, solves and nonlinear
fits, the operators' outputs, Lightning's runs, the final fit)::

    python benchmarks/fit_speed.py [--sizes 1000 10000 100000] [--concurrent 10000]
                                   [--profile 100000]
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SOURCE = ROOT / "examples" / "data" / "real" / "piezo_micromanipulator.csv"
CONFIG = ROOT / "configs" / "measured.yaml"
CANDIDATE = re.compile(r"^candidate (\d+) \(\d+ of \d+\): val_mse \S+.*?, ([\d.]+) s: (.*)$")


def write_record(path: Path, n: int, recordings: int) -> None:
    """``n`` rows of the micromanipulator's (displacement, voltage), its records one after
    another and tiled to length, cut into ``recordings`` runs of equal length."""
    with SOURCE.open() as fh:
        rows = [r for r in csv.DictReader(line for line in fh if not line.startswith("#"))]
    x = np.array([float(r["displacement_um"]) for r in rows])
    y = np.array([float(r["voltage_V"]) for r in rows])
    reps = -(-n // x.size)
    x, y = np.tile(x, reps)[:n], np.tile(y, reps)[:n]
    run = np.repeat(np.arange(recordings), -(-n // recordings))[:n]
    np.savetxt(path, np.column_stack([run, x, y]), delimiter=",", comments="",
               header="recording,displacement_um,voltage_V", fmt=["%d", "%.9g", "%.9g"])


def command(data: Path, root: Path, recordings: int, threads: int | None,
            jobs: int | None = None) -> list[str]:
    args = [sys.executable, "-m", "torchhys", "fit", "--config", str(CONFIG),
            f"--data.path={data}", "--data.input_column=displacement_um",
            "--data.target_column=voltage_V", "--data.time_column=null", "--data.warmup=0",
            f"--trainer.default_root_dir={root}", "--trainer.enable_progress_bar=false"]
    if recordings > 1:
        args.append("--data.run_column=recording")
    if threads is not None:
        args.append(f"--threads={threads}")
    if jobs is not None:
        args.append(f"--model.select_jobs={jobs}")
    return args


def start(data: Path, root: Path, recordings: int, threads: int | None,
          jobs: int | None = None) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k not in ("TORCHHYS_THREADS", "OMP_NUM_THREADS")}
    return subprocess.Popen(command(data, root, recordings, threads, jobs), cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(proc: subprocess.Popen, began: float) -> dict:
    """Wait for the run: its wall time, peak memory (MiB) and candidates' seconds."""
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - began
    proc.returncode = os.waitstatus_to_exitcode(status)
    out, err = proc.stdout.read(), proc.stderr.read()
    if proc.returncode != 0:
        raise RuntimeError(f"fit failed ({proc.returncode}): {err.strip().splitlines()[-1:]}")
    seconds = {}
    for line in out.splitlines():
        m = CANDIDATE.match(line)
        if m:
            seconds[int(m.group(1))] = (float(m.group(2)), m.group(3))
    return {"wall": wall, "peak_mib": usage.ru_maxrss / 1024, "candidates": seconds}


def run_one(n: int, recordings: int, tmp: Path, threads: int | None,
            jobs: int | None = None) -> dict:
    data = tmp / f"rec_{n}_{recordings}.csv"
    write_record(data, n, recordings)
    began = time.perf_counter()
    return finish(start(data, tmp / f"run_{n}_{recordings}", recordings, threads, jobs), began)


def concurrent(n: int, k: int, tmp: Path, threads: int | None,
               jobs: int | None = None) -> list[float]:
    """Wall times of ``k`` identical fits started at once."""
    data = tmp / f"rec_{n}_1.csv"
    write_record(data, n, 1)
    began = time.perf_counter()
    procs = [start(data, tmp / f"conc_{k}_{i}", 1, threads, jobs) for i in range(k)]
    return [finish(p, began)["wall"] for p in procs]


STAGES = [
    # (stage, file suffix, function): cumulative seconds of the function under cProfile
    ("start-up: the interpreter and the imports", "", "<start-up>"),
    ("reading the data file", "torchhys/data/files.py", "read_recordings"),
    ("model selection (all candidates)", "torchhys/selection/run.py", "select"),
    ("  families fitted on each fold", "torchhys/identification/specs.py",
     "fit_data_dependent"),
    ("    least-squares moments: Preisach relays", "identification/preisach.py",
     "_normal_equations"),
    ("    least-squares moments: stops", "identification/stop_pi.py", "_moments"),
    ("    least-squares moments: plays", "identification/fitting.py", "_pi_segments"),
    ("    non-negative solves", "identification/_nnls.py", "nnls_gram"),
    ("    nonlinear fits: generalized PI (L-BFGS)", "identification/fitting.py",
     "fit_full_batch"),
    ("    nonlinear fits: drift", "identification/drift.py", "fit_drift"),
    ("    families' checks against a line", "torchhys/identification/errors.py", "_checked"),
    ("  operators' outputs for the readouts", "torchhys/networks.py", "features"),
    ("  readouts solved (least squares)", "torchhys/selection/candidates.py",
     "solve_readout"),
    ("the chosen candidate fitted once", "torchhys/selection/run.py", "fit_record"),
    ("its run's logs and checkpoints (Trainer.fit)", "lightning/pytorch/trainer/trainer.py",
     "fit"),
]


def profile(n: int, tmp: Path) -> None:
    """One fit of ``n`` samples (one record) in one process under cProfile: the cumulative
    seconds of each stage of :data:`STAGES` (nested: a stage's time includes those indented
    under it)."""
    import pstats

    data = tmp / f"rec_{n}_1.csv"
    write_record(data, n, 1)
    out = tmp / "fit.prof"
    args = command(data, tmp / "profiled", 1, None, 1)
    env = {k: v for k, v in os.environ.items() if k not in ("TORCHHYS_THREADS", "OMP_NUM_THREADS")}
    began = time.perf_counter()
    subprocess.run([args[0], "-m", "cProfile", "-o", str(out), *args[1:]], cwd=ROOT, env=env,
                   check=True, capture_output=True, text=True)
    wall = time.perf_counter() - began
    stats = pstats.Stats(str(out)).stats  # type: ignore[attr-defined]
    print(f"\n{n} samples, one record, one process (select_jobs 1) under cProfile: "
          f"{wall:.1f} s wall (the profiler adds about 10 %)")
    print("| stage | cumulative s |")
    print("|---|---|")
    def cumulative(suffix: str, func: str) -> float:
        return max((v[3] for (f, _, fn), v in stats.items()
                    if f.endswith(suffix) and fn == func), default=0.0)

    total = max(v[3] for v in stats.values())
    for name, suffix, func in STAGES:
        if func == "<start-up>":  # everything before the command's main()
            seconds = total - cumulative("torchhys/cli/main.py", "main")
        else:
            seconds = cumulative(suffix, func)
        print(f"| {name} | {seconds:.1f} |")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1000, 10_000, 100_000])
    parser.add_argument("--recordings", type=int, nargs="+", default=[1, 5],
                        help="runs of each record (1: one record)")
    parser.add_argument("--concurrent", type=int, default=10_000,
                        help="samples of the fits run two and three at a time (0: none)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads of every fit (default: the command's, one)")
    parser.add_argument("--jobs", type=int, default=None,
                        help="model.select_jobs of every fit (default: the config's, auto)")
    parser.add_argument("--candidates", action="store_true",
                        help="print every candidate's seconds under each run")
    parser.add_argument("--profile", type=int, default=None, metavar="N",
                        help="then one fit of N samples in one process under cProfile: the "
                             "seconds of each stage")
    args = parser.parse_args(argv)
    print(f"{os.cpu_count()} cores; torchhys fit --config configs/measured.yaml; "
          f"threads {args.threads or 'default (1)'}; "
          f"select_jobs {args.jobs or 'the config (auto)'}; "
          f"load average {os.getloadavg()[0]:.2f}")
    print("| samples | recordings | wall s | peak MiB | slowest candidate |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        tmp_path = Path(tmp)
        for n in args.sizes:
            for r in args.recordings:
                res = run_one(n, r, tmp_path, args.threads, args.jobs)
                slow = max(res["candidates"].items(), key=lambda kv: kv[1][0], default=None)
                what = f"{slow[1][0]:.1f} s: {slow[1][1]}" if slow else "n/a"
                print(f"| {n} | {r} | {res['wall']:.1f} | {res['peak_mib']:.0f} | {what} |",
                      flush=True)
                if args.candidates:
                    for i, (sec, config) in sorted(res["candidates"].items()):
                        print(f"|   | candidate {i} | {sec:.1f} |   | {config} |", flush=True)
        if args.concurrent:
            alone = concurrent(args.concurrent, 1, tmp_path, args.threads, args.jobs)[0]
            print(f"\n{args.concurrent} samples, one fit alone: {alone:.1f} s")
            print("| fits at once | wall s of each | each over alone (median) |")
            print("|---|---|---|")
            for k in (2, 3):
                walls = concurrent(args.concurrent, k, tmp_path, args.threads, args.jobs)
                ratio = float(np.median(walls)) / alone
                print(f"| {k} | {', '.join(f'{w:.1f}' for w in walls)} | {ratio:.2f} |",
                      flush=True)
        if args.profile:
            profile(args.profile, tmp_path)


if __name__ == "__main__":
    main()
    print(f"load average at the end {os.getloadavg()[0]:.2f}")
