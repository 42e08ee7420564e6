"""What the package's layout costs: what an import loads, and the walk of ``torchhys fit``.

(a) For each of ``import torchhys``, ``import torchhys.selection`` and the table reader
(``tables`` of ``torchhys.data``, or of ``torchhys.training`` before it moved): the
torchhys modules it loads, all the modules it loads (``len(sys.modules)`` after it, the
interpreter's own included), the median wall seconds of the import over ``--repeats`` fresh
interpreters, and whether it loaded Lightning. A module that does not exist prints
``absent``.

(b) The walk of ``torchhys fit --config configs/measured.yaml --model.select_jobs 1`` (one
process, so that every call is seen) with ``--trainer.default_root_dir`` a temporary folder
and ``--trainer.max_epochs 5`` (the fit of the chosen candidate stops at the first
validation, epoch 5 of the config's 10; the selection, the candidates, the folds and the
final fit run as in a full run). It runs under :func:`sys.setprofile` (and
:func:`threading.setprofile`) in a subprocess. Counted:

- the torchhys files whose functions are called (a module's top-level code, run when it is
  imported, is not counted as a function), those of them called from inside model selection
  (with a frame of selection below them, or in selection itself), and those of the top
  floor (:func:`_top_floor`: not the maths, the operators, their protocol or the families'
  fits, which any fit walks);
- the returns to a room already left: a call into a torchhys file ``F`` when the torchhys
  frames below it hold ``F`` lower on the stack with a frame of another torchhys file
  between (frames of other libraries, e.g. Lightning or torch, are looked through). Each is
  recorded once as the pair (``F``, via): via is the nearest torchhys file below the call
  (the one that called back into ``F``, directly or through other libraries);
- whether a frame of the command line (``cli.py`` of ``torchhys/training/`` before the
  command line moved, or anything under ``torchhys/cli/``) is called from inside a frame
  of model selection (``selection.py``, ``jobs.py``, ``folds.py`` or ``readout.py`` of
  ``torchhys/training/``, or anything under ``torchhys/selection/``).

Run from the repository (or pass ``--root`` a checkout of another commit: its ``torchhys``
must be the one imported, which the script checks)::

    python benchmarks/layout_cost.py [--repeats 5] [--root .] [--no-walk | --no-imports] [--list]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

IMPORTS = {
    "torchhys": ["torchhys"],
    "torchhys.selection": ["torchhys.selection"],
    "tables": [f"{package}.tables" for package in ("torchhys.data", "torchhys.training")],
}
"""Row name -> the module paths tried, in order (the first that exists is measured)."""

LIGHTNING = ("lightning", "pytorch_lightning")

_PRELUDE = r"""
import sys
# an editable install's finder would fill a module missing from --root with the installed one
sys.meta_path[:] = [f for f in sys.meta_path
                    if not str(getattr(f, "__module__", "")).startswith("__editable__")]
"""

_IMPORT_PROBE = _PRELUDE + r"""
import importlib, json, time
name = sys.argv[1]
t0 = time.perf_counter()
try:
    importlib.import_module(name)
except ModuleNotFoundError as exc:
    if exc.name is None or not name.startswith(exc.name):
        raise
    print(json.dumps({"absent": True}))
    raise SystemExit(0)
dt = time.perf_counter() - t0
import torchhys
print(json.dumps({
    "absent": False,
    "seconds": dt,
    "torchhys_modules": sum(1 for m in sys.modules if m == "torchhys" or m.startswith("torchhys.")),
    "modules": len(sys.modules),
    "lightning": any(m in sys.modules for m in sys.argv[2:]),
    "file": torchhys.__file__,
}))
"""


def _env(root: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(root), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.setdefault("OMP_NUM_THREADS", "1")
    return env


def _check_file(root: Path, file: str) -> None:
    if not Path(file).resolve().is_relative_to(root.resolve()):
        raise SystemExit(f"layout_cost: torchhys was imported from {file}, not from --root {root}")


def measure_import(root: Path, candidates: list[str], repeats: int) -> dict:
    """The row of one import: the first of ``candidates`` that exists, measured ``repeats``
    times in fresh interpreters (the counts from the first)."""
    for name in candidates:
        runs = []
        for _ in range(repeats):
            out = subprocess.run([sys.executable, "-c", _IMPORT_PROBE, name, *LIGHTNING], cwd=root,
                                 env=_env(root), capture_output=True, text=True, check=True)
            runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
            if runs[-1]["absent"]:
                break
        if runs[0]["absent"]:
            continue
        _check_file(root, runs[0]["file"])
        row = dict(runs[0], module=name)
        row["seconds"] = statistics.median(r["seconds"] for r in runs)
        return row
    return {"absent": True, "module": " / ".join(candidates)}


_WALK_PROBE = _PRELUDE + r"""
import json, os, threading
root = os.path.realpath(sys.argv[1]) + os.sep
pkg = root + "torchhys" + os.sep
argv = json.loads(sys.argv[2])
# the paths before and after the moves, built from their parts
TRAINING = "/".join(("torchhys", "training", ""))
CLI = (TRAINING + "cli.py", "torchhys/cli/")
SELECTION = tuple(TRAINING + n + ".py" for n in ("selection", "jobs", "folds", "readout")) \
    + ("torchhys/selection/",)
rel = {}
def relname(code):
    f = code.co_filename
    r = rel.get(f)
    if r is None:
        real = os.path.realpath(f)
        r = real[len(root):] if real.startswith(pkg) else ""
        rel[f] = r
    return r
files = set()
in_selection = set()
returns = set()
cli_in_selection = []
def profile(frame, event, arg):
    if event != "call":
        return
    code = frame.f_code
    here = relname(code)
    if not here or code.co_name == "<module>":
        return
    files.add(here)
    below = []  # torchhys files below, nearest first (consecutive repeats folded)
    f = frame.f_back
    while f is not None:
        r = relname(f.f_code)
        if r and (not below or below[-1] != r):
            below.append(r)
        f = f.f_back
    if below and below[0] != here and here in below[1:]:
        returns.add((here, below[0]))
    inside = any(b.startswith(SELECTION) for b in below)
    if inside or here.startswith(SELECTION):
        in_selection.add(here)
    if here.startswith(CLI) and inside:
        cli_in_selection.append((here, code.co_name))
sys.argv = ["torchhys"] + argv
try:  # the console script's entry point (torchhys._command before the command line's move)
    from torchhys.cli.main import main
except ModuleNotFoundError:
    from torchhys._command import main
threading.setprofile(profile)
sys.setprofile(profile)
try:
    main(argv)
except SystemExit as exc:
    if exc.code not in (None, 0):
        raise
finally:
    sys.setprofile(None)
    threading.setprofile(None)
import torchhys
with open(os.environ["LAYOUT_COST_OUT"], "w") as out:
    json.dump({"files": sorted(files), "in_selection": sorted(in_selection),
               "returns": sorted(returns),
               "cli_in_selection": sorted(set(cli_in_selection)),
               "file": torchhys.__file__}, out)
"""


def measure_walk(root: Path) -> dict:
    """The walk of ``torchhys fit`` on configs/measured.yaml (see the module's docstring)."""
    with tempfile.TemporaryDirectory() as tmp:
        argv = ["fit", "--config", "configs/measured.yaml", "--model.select_jobs", "1",
                "--trainer.default_root_dir", str(Path(tmp) / "run"),
                "--trainer.max_epochs", "5"]
        out_file = Path(tmp) / "walk.json"
        env = dict(_env(root), LAYOUT_COST_OUT=str(out_file))
        done = subprocess.run([sys.executable, "-c", _WALK_PROBE, str(root), json.dumps(argv)],
                              cwd=root, env=env, capture_output=True, text=True)
        if done.returncode != 0 or not out_file.exists():
            raise SystemExit(f"layout_cost: the walk failed ({done.returncode}):\n"
                             f"{done.stderr[-4000:]}")
        walk = json.loads(out_file.read_text())
    _check_file(root, walk["file"])
    walk["argv"] = argv
    return walk


GROUND_FLOORS = ("torchhys/functional/", "torchhys/operators/", "torchhys/optim/",
                 "torchhys/dynamics/", "torchhys/_checks.py", "torchhys/_memory.py",
                 "torchhys/constraints.py", "torchhys/operator.py", "torchhys/step.py",
                 "torchhys/registry.py", "torchhys/protocols.py", "torchhys/__init__.py")
"""The maths, the operators and their protocol: the files the top floor builds on."""
FITS = ("fitting.py", "_nnls.py", "stop_pi.py", "preisach.py", "generalized_pi.py",
        "drift.py", "jiles_atherton.py", "prandtl_ishlinskii.py")
"""The family fits of ``torchhys/identification/`` (the ground floor of identification)."""


def _top_floor(files: list[str]) -> list[str]:
    """The files of the walk above the ground floors: neither the maths, the operators,
    their protocol, nor the families' fits."""
    return [f for f in files if not f.startswith(GROUND_FLOORS)
            and not (f.startswith("torchhys/identification/") and f.rsplit("/", 1)[1] in FITS)]


def _yes(flag: bool) -> str:
    return "yes" if flag else "no"


def report(rows: dict[str, dict], walk: dict | None, *, list_files: bool) -> str:
    """The tables, as markdown."""
    lines = ["| import | torchhys modules | all modules | median s | loads Lightning |",
             "|---|---:|---:|---:|---|"] if rows else []
    for row in rows.values():
        if row["absent"]:
            lines.append(f"| `{row['module']}` | absent | | | |")
        else:
            lines.append(f"| `{row['module']}` | {row['torchhys_modules']} | {row['modules']} | "
                         f"{row['seconds']:.2f} | {_yes(row['lightning'])} |")
    if walk is not None:
        shown = ["TMP/run" if a.endswith(os.sep + "run") else a for a in walk["argv"]]
        lines += [""] * bool(lines) + [
                  f"`torchhys {' '.join(shown)}` under `sys.setprofile`:", "",
                  "| torchhys files called | of them from inside selection | top-floor files "
                  "| returns to a room already left | command line called from inside "
                  "selection |",
                  "|---:|---:|---:|---:|---|",
                  f"| {len(walk['files'])} | {len(walk['in_selection'])} | "
                  f"{len(_top_floor(walk['files']))} | {len(walk['returns'])} | "
                  f"{_yes(bool(walk['cli_in_selection']))} |", "",
                  "Returns (file called back, via):", ""]
        lines += [f"- `{here}` via `{via}`" for here, via in walk["returns"]]
        if walk["cli_in_selection"]:
            lines += ["", "Command-line frames called from inside selection:", ""]
            lines += [f"- `{f}`: `{name}`" for f, name in walk["cli_in_selection"]]
        if list_files:
            lines += ["", "Files called (T: top floor, S: called from inside selection):", ""]
            top, sel = set(_top_floor(walk["files"])), set(walk["in_selection"])
            lines += [f"- `{f}` {'T' if f in top else ''}{'S' if f in sel else ''}".rstrip()
                      for f in walk["files"]]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1],
                        help="the checkout whose torchhys is measured (default: this one)")
    parser.add_argument("--repeats", type=int, default=5,
                        help="fresh interpreters per import (the median time is printed)")
    parser.add_argument("--no-walk", action="store_true", help="skip the walk of torchhys fit")
    parser.add_argument("--no-imports", action="store_true",
                        help="skip the imports' table: the walk of torchhys fit only")
    parser.add_argument("--list", action="store_true", help="also list the files the walk calls")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be at least 1, got {args.repeats}")
    if args.no_walk and args.no_imports:
        parser.error("--no-walk and --no-imports together measure nothing: give one")
    root = args.root.resolve()
    rows = {} if args.no_imports else {
        key: measure_import(root, names, args.repeats) for key, names in IMPORTS.items()}
    walk = None if args.no_walk else measure_walk(root)
    print(report(rows, walk, list_files=args.list))


if __name__ == "__main__":
    main()
