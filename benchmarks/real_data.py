"""Held-out accuracy of hysteresis models on measured recordings (see docs/real-data.md).

For every measured data set (``examples/data/real/``, the MnZn ferrite loops of
``../shared/data/``, a piezo actuator's record read from ``--piezo`` and an accelerator
quadrupole's magnetic measurements read from ``--quad`` when given), with
the protocol its README suggests, each model is fitted on the training part, its settings
(size, penalty, iterations, direction) are chosen on a time-ordered hold-out inside the
training part (the last quarter of the scored samples of every training row), it is
refitted on the whole training part with those settings, and it is scored once on the
held-out recordings. Reported: RMSE in the target's units and ``ratio`` = RMSE / min(line
RMSE, poly RMSE) (below 1: better than both memoryless baselines); ``choice`` says what the
hold-out selected and the hold-out RMSE.

    python benchmarks/real_data.py [--data NAME ...] [--out table.csv] [--quick]
        [--ferrite PATH] [--piezo PATH] [--quad DIR] [--config configs/measured.yaml]
        [--models MODEL ...] [--jobs N]
    python benchmarks/real_data.py --tables table.csv ...

Models (all causal; a row starts from a zero state, its first ``warmup`` samples only run
the states and are neither fitted nor scored):

- ``line``: least-squares line of the target in the input; ``poly``: polynomial, degree
  1..9 chosen on the hold-out (both memoryless);
- ``pi_constrained``: ``fit_prandtl_ishlinskii(nonnegative=True)`` on ``play_width_grid``,
  either of the target from the input ("direct") or of the input from the target, then its
  exact inverse ("inverse of forward"), and of the target or of its negative: a
  non-negative PI model only draws loops that run anticlockwise in its (input, output)
  plane, with branches that steepen after a reversal; its inverse draws clockwise ones that
  flatten, and the negation flips either. Direction, sign, number of widths, grid power and
  ridge chosen on the hold-out;
- ``pi_ls``: the same direct fit, unconstrained (the operator of ``configs/measured.yaml``);
- ``generalized_pi``: ``fit_generalized_pi`` in either direction (the inverse: the exact
  ``.inverse()``, the output function's inverse bounded to the PI part's training range
  plus half its span on each side, as ``configs/measured.yaml``'s ``gpi``), of the target times
  the sign that makes it rise with the input, on the widths and ridge chosen for the
  non-negative PI fit of that direction and sign; direction and number of tanh units chosen
  on the hold-out (a refit that diverges passes to the next candidate);
- ``preisach``: ``fit_preisach`` on a grid over the training input range; levels,
  smoothness penalty and the sign of the target (a non-negative density draws loops of one
  orientation; its free linear term lets the negated fit draw the other) chosen on the
  hold-out;
- ``stop_pi``: ``fit_stop_pi`` (non-negative slopes) of the target or of its negative, on
  ``play_width_grid`` thresholds; their number, the grid power, the characteristic segments,
  the sign and the ridge chosen on the hold-out;
- ``stop_pi_drift``: those stops beside ``fit_drift`` (a drift of the accumulated input
  variation, free slope, the ``drift`` family's scales), an affine least-squares readout of
  the two; the stops' settings chosen on the hold-out of the whole;
- ``jiles_atherton``: ``fit_jiles_atherton`` (the inverse Jiles-Atherton model, five physical
  parameters, Levenberg-Marquardt from 8 starts) in physical units, on the B -> H records
  only (n/a elsewhere); nothing to choose, the hold-out RMSE is that of the fit before it;
- ``eiho_net``: ``InverseHysteresisNet([EIHO(a=1, rule="recent", output="branch"),
  Backlash(16 widths 0.4 span k/16)], hidden=16)``, trained full-batch with L-BFGS; the number
  of L-BFGS steps and the EIHO's reversal threshold (0 or "auto") chosen on the hold-out;
- ``default``: what ``configs/measured.yaml`` (or ``--config``) chooses: its candidates
  (``model.select``) are each scored as the config's ``model.select_cv`` says, as
  ``torchhys fit`` scores them (``measured.yaml``: 4-fold blocked cross-validation inside the
  training rows; without ``select_cv``: fitted on the part before the hold-out and scored on
  it), the config's ``select_rule`` picks one, which is built through ``build_operators`` +
  ``fit_data_dependent``, trained as the config says (its optimizer, one full-batch step per
  epoch, ``trainer.max_epochs``, the last epoch kept, capped in time) on the whole training
  part, and scored by its output saturated to the training target range
  (:func:`~torchhys.deploy.streaming.default_limits`, the exported command limits; the exported
  compensator's input clamp and direction guard on top of it: ``benchmarks/deploy_safety.py``);
- ``selected``: the row above with the least hold-out RMSE (for ``default``: its chosen
  candidate's, fitted before the hold-out; a model-family choice made on the training part
  only).

Every model but ``line``, ``poly`` and ``default`` sees the input divided by its training
standard deviation and the standardized target (training statistics), so that grids and
penalties mean the same on every data set; ``default`` sees physical units, as
``torchhys fit`` does.
"""

from __future__ import annotations

import argparse
import csv
import inspect
import math
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchhys import (
    EIHO,
    Backlash,
    Drift,
    InverseHysteresisNet,
    JilesAtherton,
    fit_drift,
    fit_generalized_pi,
    fit_jiles_atherton,
    fit_preisach,
    fit_stop_pi,
    select_penalty,
    select_stop_pi_ridge,
)
from torchhys.deploy.streaming import default_limits
from torchhys.identification._nnls import holdout_cuts
from torchhys.identification.fitting import fit_prandtl_ishlinskii, play_width_grid, select_pi_ridge
from torchhys.training.baselines import fit_polynomial
from torchhys.training.cli import read_config
from torchhys.training.families import DRIFT_SCALES, PENALTIES, VALIDATION, FitError
from torchhys.training.init import initialize
from torchhys.training.module import OPTIMIZERS, InverseHysteresisModule
from torchhys.training.operators import build_operators, fit_data_dependent
from torchhys.training.selection import (
    RECORDING,
    CandidateScore,
    best,
    fold_masks,
    standard_error,
)

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "examples" / "data" / "real"
FERRITE = ROOT.parent / "shared" / "data" / "mnzn_ferrite_bh_loops.csv"
PIEZO = ROOT / "examples" / "data" / "external" / "hysteresis_v_150_1hz.csv"
"""The piezo actuator's record, not shipped (its licence is unclear): Data/hysteresis_v_150_1hz.csv
of github chandratue/SmartHysteresis (examples/data/real/README.md)."""
QUAD = ROOT / "examples" / "data" / "external" / "slac_quad_4194"
"""The SLAC magnetic measurements of LCLS-II quadrupole 4194, not shipped (no licence):
examples/fitting/data/strdat.ru3 .. strdat.ru8 of github roussel-ryan/diff_hysteresis
(examples/data/external/README.md)."""
QUAD_RUNS = (3, 4, 5, 6, 7, 8)
"""Run 3: the major loop (training); 4-6: minor loops; 7, 8: alternating set points."""
CONFIG = ROOT / "configs" / "measured.yaml"
COLUMNS = ("dataset", "model", "rmse", "ratio", "n_train", "n_test", "choice")
F64 = torch.float64
RIDGES = PENALTIES
"""The ridge grid of every row: the config families' ``"auto"`` grid."""
SMOOTHNESS = (0.0, 1e-8, 1e-6, 1e-4, 1e-2)


class Split(NamedTuple):
    """A protocol: training rows and held-out recordings, float64, physical units."""

    x: Tensor
    """Training input, (rows, time)."""
    y: Tensor
    """Training target, (rows, time)."""
    warmup: int
    """Leading samples of each training row that only run the states."""
    test: list[tuple[Tensor, Tensor, int]]
    """Held-out recordings ``(x, y, warmup)``, x and y (time,), each from a zero state."""
    magnetic: bool = False
    """A B-H record: flux density in T -> field in A/m (the Jiles-Atherton row's units)."""


class Budget(NamedTuple):
    """Candidate grids and training budgets."""

    pi_n: tuple[int, ...]
    powers: tuple[float, ...]
    preisach_n: tuple[int, ...]
    gpi_units: tuple[int, ...]
    gpi_epochs: int
    net_steps: int
    """L-BFGS steps (of up to 20 iterations) of the EIHO network."""
    default_epochs: int | None
    """Cap on the config's ``max_epochs`` (None: as configured)."""
    seconds: float
    """Time cap of one training of the config's model."""
    ja_starts: int = 8
    ja_iterations: int = 60
    """Random starts and Levenberg-Marquardt iterations of the Jiles-Atherton fit."""
    stop_n: tuple[int, ...] = (5, 10, 20)
    stop_segments: tuple[int, ...] = (1, 2, 4, 8)
    """Thresholds and characteristic segments of the stop-type PI model."""


FULL = Budget((5, 10, 20, 40), (1.0, 2.0, 3.0), (10, 20, 30), (2, 4, 8), 1000, 40, None, 60.0)
QUICK = Budget((5, 10), (2.0,), (8,), (2,), 20, 4, 20, 5.0, 2, 5, (5,), (1, 4))


# --- data ---------------------------------------------------------------------------------
def read_csv(path: Path) -> dict[str, np.ndarray]:
    """Columns of a CSV file (lines starting with '#' skipped), numeric where possible."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
    out = {}
    for k in rows[0]:
        col = [r[k] for r in rows]
        try:
            out[k] = np.array(col, dtype=float)
        except ValueError:
            out[k] = np.array(col)
    return out


def _t(a: np.ndarray) -> Tensor:
    return torch.as_tensor(np.asarray(a, dtype=float), dtype=F64)


def _recordings(d: dict, key: str, x: str, y: np.ndarray | str) -> dict[int, tuple]:
    yv = d[y] if isinstance(y, str) else y
    return {int(r): (d[x][d[key] == r], yv[d[key] == r]) for r in np.unique(d[key])}


def loops(recs: dict, train: list[int], test: list[int], periods: int = 3) -> Split:
    """Periodic closed loops run ``periods`` times; only the last period is fitted/scored."""
    P = len(recs[train[0]][0])
    tile = [(_t(np.tile(recs[i][0], periods)), _t(np.tile(recs[i][1], periods))) for i in train]
    x, y = torch.stack([a for a, _ in tile]), torch.stack([b for _, b in tile])
    held = [(_t(np.tile(recs[i][0], periods)), _t(np.tile(recs[i][1], periods)),
             (periods - 1) * len(recs[i][0])) for i in test]
    return Split(x, y, (periods - 1) * P, held, magnetic=True)


def ferrite(path: Path, train: list[int], test: list[int]) -> Split:
    d = read_csv(path)
    return loops(_recordings(d, "loop", "B_T", "H_Apm"), train, test)


def jamodel(train: list[int], test: list[int]) -> Split:
    d = read_csv(REAL / "jamodel_bh_loops.csv")
    return loops(_recordings(d, "recording", "B_T", "H_Apm"), train, test)


def mr_damper(voltage: float) -> Split:
    """Position -> force at one coil voltage: even recordings of the group train, odd test;
    scored from t = 5 s."""
    d = read_csv(REAL / "mr_damper_labcontrol.csv")
    recs = _recordings(d, "recording", "position_mm", "force_N")
    ids = sorted(r for r in recs if abs(d["voltage_V"][d["recording"] == r][0] - voltage) < 1e-3)
    w = int(np.searchsorted(d["t_s"][d["recording"] == ids[0]], 5.0 - 1e-9))
    x = torch.stack([_t(recs[i][0]) for i in ids[0::2]])
    y = torch.stack([_t(recs[i][1]) for i in ids[0::2]])
    return Split(x, y, w, [(_t(recs[i][0]), _t(recs[i][1]), w) for i in ids[1::2]])


def friction_damper(train: Sequence[int] = range(10),
                    test: Sequence[int] = range(10, 14), *,
                    file: str = "friction_damper_backlash_brfd.csv") -> Split:
    """Displacement -> force: the ``train`` recordings one after the other (one training row,
    as the device ran them), the ``test`` ones held out, all from rest. By default the sine
    tests 0-9 train and the earthquake histories 10-13 are held out; the README's
    alternative trains on the 1 in sines (1, 4, 7: 0.25, 0.5 and 1 Hz) and holds out the
    0.5 in and 1.5 in ones (0, 2, 3, 5, 6, 8, 9). ``file``: the 30 lb band tension's record
    (sines and earthquakes), or ``friction_damper_backlash_brfd_36lb.csv`` (the sines 0-9 at
    36 lb)."""
    d = read_csv(REAL / file)
    recs = _recordings(d, "recording", "displacement_in", "force_kip")
    x = _t(np.concatenate([recs[i][0] for i in train]))[None]
    y = _t(np.concatenate([recs[i][1] for i in train]))[None]
    return Split(x, y, 0, [(_t(recs[i][0]), _t(recs[i][1]), 0) for i in test])


SEALS = {"napn": "NAPN", "nap310": "NAP310", "pk": "PK", "kdn": "KDN",
         "oring257": "O-ring257", "xring257": "X-ring257"}
"""The seals of ``pneumatic_cylinder_seals_friction.csv`` by protocol suffix: name in the file."""


def pneumatic(seal: str | None = None) -> Split:
    """Position -> seal friction (pressure x piston area - rod force): 1 and 7 bar train (7 bar
    cut to the length of the 1 bar record, one row each), 3 and 5 bar held out, from rest.

    ``seal``: None for the O-ring of ``pneumatic_cylinder_oring_friction.csv`` (25 mm bore), or
    a key of :data:`SEALS` for one of the six seals of ``pneumatic_cylinder_seals_friction.csv``
    (bore 25.7 mm for the two "257" seals, 25 mm for the others)."""
    if seal is None:
        d = read_csv(REAL / "pneumatic_cylinder_oring_friction.csv")
        bore_m = 0.025
    else:
        d = read_csv(REAL / "pneumatic_cylinder_seals_friction.csv")
        rows = d["seal"] == SEALS[seal]
        d = {k: v[rows] for k, v in d.items()}
        bore_m = 0.0257 if SEALS[seal].endswith("257") else 0.025
    friction = d["pressure_bar"] * 1e5 * math.pi * (bore_m / 2) ** 2 - d["force_N"]
    recs = _recordings(d, "pressure_setpoint_bar", "position_mm", friction)
    T = min(len(recs[1][0]), len(recs[7][0]))
    x = torch.stack([_t(recs[b][0][:T]) for b in (1, 7)])
    y = torch.stack([_t(recs[b][1][:T]) for b in (1, 7)])
    return Split(x, y, 0, [(_t(recs[b][0]), _t(recs[b][1]), 0) for b in (3, 5)])


def sma() -> Split:
    """Chamber temperature (C) -> extension (mm) of a shape-memory-alloy specimen cycled
    between -30 and 50 C under a constant load (7 cycles): the record up to the fifth start of
    cooling (four cycles) trains, the load ramp at 50 C before the first cooling only running
    the states; the rest (three cycles) is held out, the whole record run from the start and
    scored from the cut."""
    d = read_csv(REAL / "sma_isobaric_thermal_cycles.csv")
    temp, ext = d["chamber_temperature_C"], d["extension_mm"]
    cooling = np.flatnonzero((temp[:-1] >= 45.0) & (temp[1:] < 45.0)) + 1  # 45 C crossed down
    w, cut = int(cooling[0]), int(cooling[4])
    return Split(_t(temp[:cut])[None], _t(ext[:cut])[None], w, [(_t(temp), _t(ext), cut)])


def forc() -> Split:
    """Applied field (Oe) -> moment (emu) of a FeCo nanowire array, first-order reversal
    curves (VSM). Each curve starts from positive saturation (15 kOe, not recorded) at its
    calibration point (6.81 kOe: the curve's first row), goes to its reversal field and sweeps
    up to 4.1-6.8 kOe. The curves 0, 2, 4, ... (in measurement order) train, one after the
    other in one row as the instrument ran them, the first calibration point only running the
    states; the curves 1, 3, 5, ... are held out, each from a zero state, its calibration
    point only running the states."""
    d = read_csv(REAL / "feco_nanowires_forc.csv")
    recs = _recordings(d, "curve", "field_Oe", "moment_emu")
    train, test = sorted(recs)[0::2], sorted(recs)[1::2]
    x = _t(np.concatenate([recs[c][0] for c in train]))[None]
    y = _t(np.concatenate([recs[c][1] for c in train]))[None]
    return Split(x, y, 1, [(_t(recs[c][0]), _t(recs[c][1]), 1) for c in test])


def micromanipulator(*, compensator: bool) -> Split:
    """A piezoelectric micromanipulator (drive voltage -> capacitive displacement sensor, 200
    Hz): the identification record (40 periods of a 1 Hz sine over the full 0-3.6 V range)
    trains, the test record (a smaller 1 Hz sine that decays to rest, then two drives whose
    amplitude grows and shrinks, shaped by the source's own compensator) is held out. Each is
    run from its start, its first period (200 samples) only running the states.
    ``compensator``: displacement -> voltage (the inverse model); else voltage ->
    displacement."""
    d = read_csv(REAL / "piezo_micromanipulator.csv")
    x, y = ("displacement_um", "voltage_V") if compensator else ("voltage_V", "displacement_um")
    recs = _recordings(d, "recording", x, y)
    w = int(np.searchsorted(d["t_s"][d["recording"] == 0], 1.0 - 1e-9))  # 1 s: one period
    return Split(_t(recs[0][0])[None], _t(recs[0][1])[None], w,
                 [(_t(recs[1][0]), _t(recs[1][1]), w)])


def read_piezo(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Time (s), voltage (V) and displacement (um) of the SmartHysteresis piezo record, as
    published: no header, columns (empty index, time, displacement, voltage).

    Raises:
        ValueError: the file does not have that layout (naming the path).
    """
    try:
        a = np.loadtxt(path, delimiter=",", usecols=(1, 2, 3), ndmin=2)
    except (ValueError, IndexError) as err:
        raise ValueError(f"--piezo {path}: expected rows ',time,displacement,voltage' "
                         f"(the published file): {err}") from None
    if len(a) < 2 or not np.isfinite(a).all() or not (np.diff(a[:, 0]) > 0).all():
        raise ValueError(f"--piezo {path}: expected at least 2 rows of finite values with "
                         "increasing time")
    return a[:, 0], a[:, 2], a[:, 1]


def piezo(path: Path, *, compensator: bool) -> Split:
    """One record of a piezo actuator (1 Hz, 150 V sine from rest at about 3.26 s), split in
    time: the samples before 7 s train (the first 3.3 s, at rest and the first 40 ms of
    motion, only run the states), the record's remainder is held out (the whole record is run
    from rest, scored from 7 s). ``compensator``: displacement -> voltage (the inverse
    model); else voltage -> displacement."""
    t, volt, disp = read_piezo(path)
    x, y = (disp, volt) if compensator else (volt, disp)
    cut, w = int(np.searchsorted(t, 7.0)), int(np.searchsorted(t, 3.3))
    if not 0 < w < cut < len(t):
        raise ValueError(f"--piezo {path}: the record must run past 7 s, got {t[-1]:.3g} s")
    return Split(_t(x[:cut])[None], _t(y[:cut])[None], w, [(_t(x), _t(y), cut)])


def read_slac_run(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Current (A) and integrated gradient (T) of one SLAC magnetic-measurement run
    (``strdat.ruN`` as published: a header, then a table under a dashed rule whose columns
    are current, its sigma, integrated gradient, its sigma, ...).

    Raises:
        ValueError: the file does not have that layout (naming the path).
    """
    lines = Path(path).read_text().splitlines()
    rule = next((i for i, line in enumerate(lines) if line.lstrip().startswith("---")), None)
    if rule is None:
        raise ValueError(f"--quad {path}: no table (expected a dashed rule under the column "
                         "headers 'MAIN +/- sigma BL sigBL ...')")
    rows = []
    for line in lines[rule + 1:]:
        fields = line.split()
        if not fields:
            continue
        try:
            rows.append((float(fields[0]), float(fields[2])))
        except (ValueError, IndexError):
            raise ValueError(f"--quad {path}: expected rows 'current sigma BL sigBL ...', got "
                             f"{line.strip()!r}") from None
    a = np.array(rows).reshape(-1, 2)
    if len(a) < 2 or not np.isfinite(a).all():
        raise ValueError(f"--quad {path}: expected at least 2 rows of finite values")
    return a[:, 0], a[:, 1]


def quad_files(folder: Path) -> dict[int, Path]:
    """The run files of the quadrupole in ``folder``, by run number (:data:`QUAD_RUNS`)."""
    return {r: Path(folder) / f"strdat.ru{r}" for r in QUAD_RUNS}


def quad(folder: Path, *, compensator: bool) -> Split:
    """An accelerator quadrupole's integrated gradient against its current: trained on the
    major loop (run 3, 0 -> 165 A -> 0 twice; its first rise only runs the states), held out:
    the minor loops (runs 4-6) and the alternating set points (7, 8), each run after the
    major loop's currents (the magnet's history before a run: cycled, then at 0 A) and scored
    on its own samples. ``compensator``: gradient -> current (the inverse model); else
    current -> gradient."""
    runs = {r: read_slac_run(path) for r, path in quad_files(folder).items()}

    def xy(r: int) -> tuple[np.ndarray, np.ndarray]:
        current, gradient = runs[r]
        return (gradient, current) if compensator else (current, gradient)

    x, y = xy(3)
    falls = np.flatnonzero(np.diff(runs[3][0]) < 0)
    w = int(falls[0]) + 1 if len(falls) else 1  # the first rise of the current
    test = [(_t(np.concatenate([x, a])), _t(np.concatenate([y, b])), len(x))
            for a, b in map(xy, QUAD_RUNS[1:])]
    return Split(_t(x)[None], _t(y)[None], w, test)


def shortened(split: Split, n: int = 50, *, stride: bool = False,
              every: int | None = None) -> Split:
    """A short record of about ``n`` scored training samples: the first training row, its
    warm-up and the ``n`` samples after it (a short log of the device), or with ``stride``
    every k-th sample of every training row (a closed loop sampled coarsely: its shape kept),
    or with ``every = k`` every k-th sample of each training row's warm-up and of the ``n k``
    samples after it (a short log at 1/k of the rate: where k-th samples of the whole row
    would skip most of each period). The held-out recordings are unchanged."""
    if every is not None:
        if stride or every < 1:
            raise ValueError(f"shortened: every must be a positive int without stride, got "
                             f"every={every}, stride={stride}")
        cut = split.warmup + n * every
        return split._replace(x=split.x[:, :cut:every], y=split.y[:, :cut:every],
                              warmup=-(-split.warmup // every))
    if not stride:
        return split._replace(x=split.x[:1, :split.warmup + n],
                              y=split.y[:1, :split.warmup + n])
    k = max(1, split.y[:, split.warmup:].numel() // n)
    return split._replace(x=split.x[:, ::k], y=split.y[:, ::k], warmup=-(-split.warmup // k))


def tiled(split: Split, total: int = 100_000) -> Split:
    """A long record: each training row repeated end to end until the rows hold ``total``
    scored samples in all (a test of scale and run time: no new information)."""
    rows, T = split.x.shape
    reps = -(-(total // rows + split.warmup) // T)
    return split._replace(x=split.x.repeat(1, reps), y=split.y.repeat(1, reps))


class Files(NamedTuple):
    """The data files read from options (the others are in ``examples/data/real/``)."""

    ferrite: Path = FERRITE
    piezo: Path = PIEZO
    quad: Path = QUAD

    def missing(self, need: str) -> list[Path]:
        """The files that option ``need`` names (for ``quad``: the run files in its folder)
        and that are not there."""
        path = getattr(self, need)
        paths = list(quad_files(path).values()) if need == "quad" else [path]
        return [p for p in paths if not p.is_file()]


class Protocol(NamedTuple):
    """A data set's protocol."""

    about: str
    """What is fitted to what, and what is held out."""
    build: Callable[[Files], Split]
    """The builder of its split from the optional files."""
    needs: str | None = None
    """The option (a :class:`Files` field) whose file it reads; None: shipped files only."""


DATASETS: dict[str, Protocol] = {name: Protocol(*entry) for name, entry in {
    # name: (about, build[, the option whose file it reads])
    "mnzn_ferrite": ("B -> H, loops 0+3 / 1+2", lambda f: ferrite(f.ferrite, [0, 3], [1, 2]),
                     "ferrite"),
    "mnzn_ferrite_largest": ("B -> H, loop 3 / 0+1+2",
                             lambda f: ferrite(f.ferrite, [3], [0, 1, 2]), "ferrite"),
    "m130_steel": ("B -> H, loops 0+2 / 1", lambda f: jamodel([0, 2], [1])),
    "m130_steel_largest": ("B -> H, loop 2 / 0+1", lambda f: jamodel([2], [0, 1])),
    "mnzn_hp_ferrite": ("B -> H, loops 4+7 / 5+6", lambda f: jamodel([4, 7], [5, 6])),
    "mnzn_hp_ferrite_largest": ("B -> H, loop 7 / 4+5+6", lambda f: jamodel([7], [4, 5, 6])),
    "mr_damper_0V": ("position -> force, even / odd", lambda f: mr_damper(0.0)),
    "mr_damper_0.87V": ("position -> force, even / odd", lambda f: mr_damper(0.8712)),
    "mr_damper_1.98V": ("position -> force, even / odd", lambda f: mr_damper(1.98)),
    "mr_damper_3.21V": ("position -> force, even / odd", lambda f: mr_damper(3.212)),
    "friction_damper": ("displacement -> force, sines / earthquakes",
                        lambda f: friction_damper()),
    "friction_damper_sines": ("displacement -> force, 1 in sines / 0.5 and 1.5 in sines",
                              lambda f: friction_damper((1, 4, 7), (0, 2, 3, 5, 6, 8, 9))),
    "friction_damper_36lb_sines": ("as friction_damper_sines, at a band tension of 36 lb",
                                   lambda f: friction_damper(
                                       (1, 4, 7), (0, 2, 3, 5, 6, 8, 9),
                                       file="friction_damper_backlash_brfd_36lb.csv")),
    "pneumatic_oring": ("position -> friction, 1+7 / 3+5 bar", lambda f: pneumatic()),
    **{f"pneumatic_{k}": (f"position -> friction of the {v} seal, 1+7 / 3+5 bar",
                          lambda f, k=k: pneumatic(k)) for k, v in SEALS.items()},
    "sma_actuator": ("temperature -> extension, cycles 1-4 / 5-7", lambda f: sma()),
    "feco_forc": ("field -> moment, reversal curves 0, 2, 4, ... / 1, 3, 5, ...",
                  lambda f: forc()),
    "mnzn_ferrite_short": ("mnzn_ferrite, training loops sampled every 5th: 52 samples",
                           lambda f: shortened(ferrite(f.ferrite, [0, 3], [1, 2]), stride=True),
                           "ferrite"),
    "mr_damper_0V_short": ("mr_damper_0V, the first 50 scored samples of one training row",
                           lambda f: shortened(mr_damper(0.0))),
    "pneumatic_oring_short": ("pneumatic_oring, the first 50 samples of the 1 bar record",
                              lambda f: shortened(pneumatic())),
    "pneumatic_oring_long": ("pneumatic_oring, training rows tiled to 1e5 samples",
                             lambda f: tiled(pneumatic())),
    "piezo_actuator": ("displacement -> voltage, t < 7 s / t >= 7 s (one record, --piezo)",
                       lambda f: piezo(f.piezo, compensator=True), "piezo"),
    "piezo_actuator_forward": ("voltage -> displacement, as piezo_actuator",
                               lambda f: piezo(f.piezo, compensator=False), "piezo"),
    "piezo_actuator_short": ("piezo_actuator, the training part sampled every 370th: 50 samples",
                             lambda f: shortened(piezo(f.piezo, compensator=True), stride=True),
                             "piezo"),
    "piezo_manipulator": ("displacement -> voltage, identification record / test record",
                          lambda f: micromanipulator(compensator=True)),
    "piezo_manipulator_forward": ("voltage -> displacement, as piezo_manipulator",
                                  lambda f: micromanipulator(compensator=False)),
    "piezo_manipulator_short": ("piezo_manipulator, one period of the training record at 50 Hz: "
                                "50 samples",
                                lambda f: shortened(micromanipulator(compensator=True), every=4)),
    "quad_magnet": ("integrated gradient -> current, major loop / minor loops (--quad)",
                    lambda f: quad(f.quad, compensator=True), "quad"),
    "quad_magnet_forward": ("current -> integrated gradient, as quad_magnet",
                            lambda f: quad(f.quad, compensator=False), "quad"),
}.items()}
"""Data sets by name: their protocol, the builder of its split and the option it reads."""


# --- scoring ------------------------------------------------------------------------------
Predict = Callable[[Tensor], Tensor]
"""Model output for an input (rows, time), physical units."""


class Fitted(NamedTuple):
    predict: Predict
    choice: str
    holdout: float
    """RMSE (target units) on the hold-out of the chosen settings, fitted before it."""


def holdout(T: int, warmup: int) -> int:
    """First hold-out sample of a training row: the last quarter of its scored samples
    (as :func:`torchhys.training.baselines.holdout_mask` cuts the scored samples)."""
    return warmup + holdout_cuts(T - warmup, 0, VALIDATION)[1]


def test_rmse(predict: Predict, split: Split) -> tuple[float, int]:
    """RMSE over the scored samples of all held-out recordings, and their number."""
    errors = []
    with torch.no_grad():
        for x, y, w in split.test:
            errors.append((predict(x[None])[0] - y)[w:])
    e = torch.cat(errors)
    return float(e.square().mean().sqrt()), e.numel()


def _rmse(a: Tensor, b: Tensor) -> float:
    return float((a - b).square().mean().sqrt())


def _scored(split: Split) -> Tensor:
    mask = torch.zeros_like(split.x, dtype=torch.bool)
    mask[:, split.warmup:] = True
    return mask


def line(split: Split, budget: Budget) -> Fitted:
    p = fit_polynomial(split.x, split.y, _scored(split), degrees=(1,))
    b, k = (*p.p.convert().coef, 0.0)[:2]  # a constant input: the mean, slope 0
    return Fitted(p, f"slope={k:.4g}, offset={b:.4g}", p.validation_rmse)


def poly(split: Split, budget: Budget) -> Fitted:
    p = fit_polynomial(split.x, split.y, _scored(split))
    return Fitted(p, f"degree={p.degree}", p.validation_rmse)


class Scaled(NamedTuple):
    """Training rows, the input divided by its std, the target standardized."""

    x: Tensor
    y: Tensor
    warmup: int
    sx: float
    my: float
    sy: float

    @property
    def cut(self) -> int:
        return holdout(self.x.shape[1], self.warmup)

    @property
    def validation(self) -> float:
        """The hold-out share as ``select_pi_ridge`` / ``select_penalty`` take it."""
        return (self.x.shape[1] - self.cut) / self.x.shape[1]

    def fitted(self, f: Callable[[Tensor], Tensor], choice: str, score: float) -> Fitted:
        """Physical-unit model and hold-out RMSE from a model of the scaled data."""
        return Fitted(lambda v: f(v / self.sx) * self.sy + self.my, choice, score * self.sy)

    def score(self, f: Callable[[Tensor], Tensor]) -> float:
        with torch.no_grad():
            return _rmse(f(self.x)[:, self.cut:], self.y[:, self.cut:])


def scaled(split: Split) -> Scaled:
    x, y = split.x[:, split.warmup:], split.y[:, split.warmup:]
    sx, my, sy = float(x.std()), float(y.mean()), float(y.std())
    return Scaled(split.x / sx, (split.y - my) / sy, split.warmup, sx, my, sy)


# --- Prandtl-Ishlinskii and Preisach ------------------------------------------------------
Choice = tuple[float, int, float, float]
"""(hold-out RMSE, number of widths, grid power, ridge); n = 0: no candidate."""


def _rising(d: Scaled, end: int) -> float:
    """+1 if the target rises with the input on the scored samples before ``end``, else -1."""
    xs, ys = d.x[:, d.warmup:end], d.y[:, d.warmup:end]
    return 1.0 if float(((xs - xs.mean()) * ys).sum()) >= 0 else -1.0


def _pi_choice(d: Scaled, budget: Budget, nonnegative: bool, sign: float = 1.0) -> Choice:
    """The best PI model of ``sign`` x target from the input (ridge by ``select_pi_ridge``)."""
    best = (math.inf, 0, 0.0, 0.0)
    for n in budget.pi_n:
        for power in budget.powers:
            widths = play_width_grid(d.x, n, power=power)
            ridge, scores = select_pi_ridge(d.x, sign * d.y, widths, RIDGES,
                                            nonnegative=nonnegative, validation=d.validation,
                                            warmup=d.warmup)
            best = min(best, (scores[ridge], n, power, ridge))
    return best


def _inverse_pi(d: Scaled, sign: float, n: int, power: float, ridge: float,
                end: int) -> Callable:
    """``sign`` x the exact inverse of the non-negative PI model of the input from ``sign`` x
    target, fitted on samples [warmup, end) of every row (widths from the span there)."""
    t = sign * d.y[:, :end]
    forward = fit_prandtl_ishlinskii(t, d.x[:, :end], play_width_grid(t, n, power=power),
                                     ridge=ridge, warmup=d.warmup, nonnegative=True)
    inverse = forward.inverse()
    return lambda v: sign * inverse(v)[0]


def _inverse_pi_choice(d: Scaled, budget: Budget, sign: float) -> Choice:
    best = (math.inf, 0, 0.0, 0.0)
    for n in budget.pi_n:
        for power in budget.powers:
            for ridge in RIDGES:
                try:
                    f = _inverse_pi(d, sign, n, power, ridge, d.cut)
                except ValueError:  # no strictly increasing loading curve: no inverse
                    continue
                best = min(best, (d.score(f), n, power, ridge))
    return best


def pi_constrained(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    best = min((_pi_choice(d, budget, True, sign), False, sign) for sign in (1.0, -1.0))
    best = min(best, *((_inverse_pi_choice(d, budget, sign), True, sign)
                       for sign in (1.0, -1.0)))
    (score, n, power, ridge), inverse, sign = best
    text = f"n={n}, power={power:g}, ridge={ridge:g}, sign={sign:+.0f}"
    if inverse:
        f = _inverse_pi(d, sign, n, power, ridge, d.x.shape[1])
        return d.fitted(f, f"inverse of forward, {text}", score)
    model = fit_prandtl_ishlinskii(d.x, sign * d.y, play_width_grid(d.x, n, power=power),
                                   ridge=ridge, warmup=d.warmup, nonnegative=True)
    return d.fitted(lambda v: sign * model(v)[0], f"direct, {text}", score)


def pi_ls(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    score, n, power, ridge = _pi_choice(d, budget, nonnegative=False)
    model = fit_prandtl_ishlinskii(d.x, d.y, play_width_grid(d.x, n, power=power), ridge=ridge,
                                   warmup=d.warmup)
    return d.fitted(lambda v: model(v)[0], f"n={n}, power={power:g}, ridge={ridge:g}", score)


def _gpi(d: Scaled, inverse: bool, n: int, power: float, ridge: float, units: int, end: int,
         epochs: int) -> Callable[[Tensor], Tensor]:
    """Generalized PI model of t = sign x target from the input, fitted on samples [0, end)
    of every row, or the inverse of one of the input from t; ``sign`` makes t rise with the
    input."""
    sign = _rising(d, end)
    t = sign * d.y[:, :end]
    u, out = (t, d.x[:, :end]) if inverse else (d.x[:, :end], t)
    model = fit_generalized_pi(u, out, play_width_grid(u, n, power=power), units=units,
                               ridge=ridge, lbfgs_epochs=epochs, warmup=d.warmup)
    if not inverse:
        return lambda v: sign * model(v)[0]
    exact = model.bounded_inverse(u)  # g^-1 within the PI part's training range +- half
    return lambda v: sign * exact(v)[0]


def generalized_pi(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    sign = _rising(d, d.cut)
    candidates = []
    for inverse, (_, n, power, ridge) in ((False, _pi_choice(d, budget, True, sign)),
                                          (True, _inverse_pi_choice(d, budget, sign))):
        for units in budget.gpi_units if n else ():
            try:
                score = d.score(_gpi(d, inverse, n, power, ridge, units, d.cut,
                                     budget.gpi_epochs))
            except (FloatingPointError, ValueError):  # diverged, or no inverse
                continue
            candidates.append((score, inverse, n, power, ridge, units))
    for k, (score, inverse, n, power, ridge, units) in enumerate(sorted(candidates)):
        try:  # the best candidate whose refit on the whole training part converges
            f = _gpi(d, inverse, n, power, ridge, units, d.x.shape[1], budget.gpi_epochs)
        except FloatingPointError:
            continue
        how = "inverse of forward" if inverse else "direct"
        note = f" ({k} better refit(s) diverged)" if k else ""
        return d.fitted(f, f"{how}, n={n}, power={power:g}, ridge={ridge:g}, units={units}, "
                           f"sign={_rising(d, d.x.shape[1]):+.0f}, "
                           f"lbfgs={budget.gpi_epochs}{note}", score)
    raise FloatingPointError("every generalized PI candidate diverged")


def preisach(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    best = (math.inf, 0, 0.0, 0.0)
    for n in budget.preisach_n:
        for sign in (1.0, -1.0):
            p, scores = select_penalty(d.x, sign * d.y, list(SMOOTHNESS), kind="smoothness",
                                       validation=d.validation, n=n, warmup=d.warmup)
            best = min(best, (scores[p], n, sign, p))
    score, n, sign, p = best
    model = fit_preisach(d.x, sign * d.y, n=n, smoothness=p, warmup=d.warmup)
    return d.fitted(lambda v: sign * model(v)[0], f"n={n}, smoothness={p:g}, sign={sign:+.0f}",
                    score)


StopSetting = tuple[int, float, int, float, float]
"""(number of thresholds, grid power, segments, sign, ridge) of the stop-type rows."""


def _stop_settings(d: Scaled, budget: Budget) -> Iterator[tuple[StopSetting, float]]:
    """Every setting of the stop-type grid, each with the ridge ``select_stop_pi_ridge``
    chooses for the stops alone on the hold-out, and that ridge's hold-out RMSE."""
    for n in budget.stop_n:
        for power in (1.0, 2.0):
            thresholds = play_width_grid(d.x[:, d.warmup:], n, power=power)
            for segments in budget.stop_segments:
                for sign in (1.0, -1.0):
                    ridge, scores = select_stop_pi_ridge(
                        d.x, sign * d.y, thresholds, RIDGES, segments=segments,
                        validation=d.validation, warmup=d.warmup)
                    yield (n, power, segments, sign, ridge), scores[ridge]


def _stop_choice(setting: StopSetting) -> str:
    n, power, segments, sign, ridge = setting
    return (f"n={n}, power={power:g}, segments={segments}, ridge={ridge:g}, "
            f"sign={sign:+.0f}")


def stop_pi(split: Split, budget: Budget) -> Fitted:
    """``fit_stop_pi`` (non-negative slopes) of the target or of its negative (a non-negative
    model's loops run clockwise only); thresholds on ``play_width_grid`` (up to the input's
    span), their number, the grid power, the segments, the sign and the ridge chosen on the
    hold-out."""
    d = scaled(split)
    score, setting = min((score, setting) for setting, score in _stop_settings(d, budget))
    n, power, segments, sign, ridge = setting
    model = fit_stop_pi(d.x, sign * d.y, play_width_grid(d.x[:, d.warmup:], n, power=power),
                        segments=segments, ridge=ridge, warmup=d.warmup)
    return d.fitted(lambda v: sign * model(v)[0], _stop_choice(setting), score)


def _drift(d: Scaled, end: int) -> Drift:
    """:func:`~torchhys.fit_drift` (free slope, ``DRIFT_SCALES`` spans of the scored input) on
    the samples before ``end``."""
    x, y, w = d.x[:, :end], d.y[:, :end], d.warmup
    span = float(x[:, w:].max() - x[:, w:].min())
    return fit_drift(x, y, [span * c for c in DRIFT_SCALES], warmup=w)


def _stop_pi_drift(d: Scaled, setting: StopSetting, drift: Drift,
                   end: int) -> Callable[[Tensor], Tensor]:
    """The stops (as the ``stop_pi`` row fits them) fitted on the samples before ``end``
    beside ``drift`` (fitted on the same samples, :func:`_drift`), then a least-squares
    affine readout of the two outputs on those samples."""
    n, power, segments, sign, ridge = setting
    x, y, w = d.x[:, :end], d.y[:, :end], d.warmup
    stops = fit_stop_pi(x, sign * y, play_width_grid(d.x[:, w:], n, power=power),
                        segments=segments, ridge=ridge, warmup=w)

    def features(v: Tensor) -> Tensor:
        return torch.stack([stops(v)[0], drift(v)[0], torch.ones_like(v)], -1)

    with torch.no_grad():
        coef = torch.linalg.lstsq(features(x)[:, w:].reshape(-1, 3).to(F64),
                                  y[:, w:].reshape(-1, 1).to(F64)).solution[:, 0]
    return lambda v: features(v).to(F64) @ coef


def stop_pi_drift(split: Split, budget: Budget) -> Fitted:
    """The stop-type PI model beside a drift of the accumulated input variation (the
    ``[stop_pi, drift]`` candidate of ``configs/measured.yaml``, its readout by least
    squares): the stops' number, grid power, segments and sign chosen on the hold-out of the
    whole, each setting's ridge as the ``stop_pi`` row chooses it (on the stops alone)."""
    d = scaled(split)
    drift = _drift(d, d.cut)  # the same for every setting of the stops
    score, setting = min((d.score(_stop_pi_drift(d, setting, drift, d.cut)), setting)
                         for setting, _ in _stop_settings(d, budget))
    end = d.x.shape[1]
    return d.fitted(_stop_pi_drift(d, setting, _drift(d, end), end), _stop_choice(setting),
                    score)


class NotApplicable(ValueError):
    """A model that does not apply to this data set (its row reads n/a)."""


def jiles_atherton(split: Split, budget: Budget) -> Fitted:
    """The inverse Jiles-Atherton model (B in T -> H in A/m), physical units: fitted on the
    part before the hold-out for the hold-out RMSE, then on the whole training part."""
    if not split.magnetic:
        raise NotApplicable("B -> H records only")

    def fit(x: Tensor, y: Tensor) -> JilesAtherton:
        return fit_jiles_atherton(x, y, warmup=split.warmup, starts=budget.ja_starts,
                                  iterations=budget.ja_iterations)

    cut = holdout(split.x.shape[1], split.warmup)
    with torch.no_grad():
        score = _rmse(fit(split.x[:, :cut], split.y[:, :cut])(split.x)[0][:, cut:],
                      split.y[:, cut:])
    model = fit(split.x, split.y)
    return Fitted(lambda v: model(v)[0], model.extra_repr(), score)


# --- networks -----------------------------------------------------------------------------
def _eiho_net(x: Tensor, threshold: float | str) -> InverseHysteresisNet:
    torch.manual_seed(0)
    widths = 0.4 * play_width_grid(x, 16, power=1.0)
    ops = [EIHO(a=1.0, rule="recent", output="branch", threshold=threshold), Backlash(widths)]
    return InverseHysteresisNet(ops, 16).double()


def _train_head(net: InverseHysteresisNet, x: Tensor, y: Tensor, warmup: int, end: int,
                steps: int) -> list[float]:
    """Fit the normalization, then L-BFGS-train the head on samples [warmup, end) of every
    row (steps of up to 20 iterations); the RMSE on [end, T) after each step."""
    net.fit_normalization(x[:, :end], y[:, :end])
    with torch.no_grad():
        feats, _ = net.features(x)
    params = [p for p in net.parameters() if p.requires_grad]
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=20, history_size=50,
                            line_search_fn="strong_wolfe", tolerance_grad=1e-12,
                            tolerance_change=1e-15)
    ft, yt = feats[:, warmup:end], y[:, warmup:end]

    def closure() -> Tensor:
        opt.zero_grad()
        loss = (net.head(ft) - yt).square().mean()
        loss.backward()
        return loss

    curve = []
    for _ in range(steps):
        opt.step(closure)
        if end < x.shape[1]:
            with torch.no_grad():
                curve.append(_rmse(net.head(feats[:, end:]), y[:, end:]))
    return curve


def eiho_net(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    best = (math.inf, 0, 0.0)
    for threshold in (0.0, "auto"):
        curve = _train_head(_eiho_net(d.x, threshold), d.x, d.y, d.warmup, d.cut,
                            budget.net_steps)
        k = int(np.argmin(curve))
        best = min(best, (curve[k], k + 1, threshold), key=lambda b: b[0])
    score, steps, threshold = best
    net = _eiho_net(d.x, threshold)
    _train_head(net, d.x, d.y, d.warmup, d.x.shape[1], steps)
    return d.fitted(lambda v: net(v)[0], f"threshold={threshold}, lbfgs_steps={steps}x20",
                    score)


def _config_model(path: Path) -> tuple[dict, dict, torch.dtype, int]:
    """The model section (with the module's defaults), trainer section, dtype and seed, read
    as ``torchhys fit`` reads the file (jsonargparse's YAML loader: ``1e-8`` is a number)."""
    cfg = read_config(path)
    defaults = {k: p.default for k, p in
                inspect.signature(InverseHysteresisModule.__init__).parameters.items()
                if p.default is not inspect.Parameter.empty}
    trainer = cfg.get("trainer") or {}
    dtype = F64 if str(trainer.get("precision", "32")).startswith("64") else torch.float32
    return {**defaults, **cfg["model"]}, trainer, dtype, int(cfg.get("seed_everything", 0))


def _train_config(path: Path, x: Tensor, y: Tensor, w: int, budget: Budget,
                  overrides: dict | None = None, held: Tensor | None = None,
                  ) -> tuple[InverseHysteresisNet, int, int]:
    """Build the config's network (its model section with a candidate's ``overrides``), fit
    its data-dependent operators and normalization on (x, y) (rows, time) and train it on
    samples [w, T), without the samples ``held`` ((rows, time) bool: a cross-validation
    fold's block, the states running through it): the net, epochs done, epochs asked."""
    m, trainer, dtype, seed = _config_model(path)
    m = {**m, **(overrides or {})}
    torch.manual_seed(seed)
    ops, fitters = build_operators(m["operator"], m["operator_kwargs"])
    net = InverseHysteresisNet(ops, m["hidden"], activation=m["activation"])
    initialize(net, m["init"])
    net.to(dtype)
    x, y = x.to(dtype), y.to(dtype)
    known = None if held is None else ~held  # the samples the fits may use
    fit_data_dependent(net.operators, fitters, x, y, warmup=w, mask=known)
    net.fit_normalization(x, y, mask=known)
    mask = torch.zeros_like(x, dtype=torch.bool)
    mask[:, w:] = True
    if held is not None:
        mask &= ~held
    fixed = not any(p.requires_grad for p in net.operators.parameters())
    with torch.no_grad():
        feats = net.features(x)[0] if fixed else None
    kwargs = dict(m["optimizer_kwargs"] or {})
    if m["optimizer"] != "cg":
        kwargs.setdefault("lr", m["lr"])
    if m["optimizer"] == "lbfgs":
        kwargs.setdefault("line_search_fn", "strong_wolfe")
    opt = OPTIMIZERS[m["optimizer"]]([p for p in net.parameters() if p.requires_grad], **kwargs)

    def closure() -> Tensor:
        opt.zero_grad()
        out = net.head(feats) if fixed else net(x)[0]
        loss = (out - y)[mask].square().mean()
        loss.backward()
        return loss

    epochs = int(trainer.get("max_epochs") or 1000)
    if budget.default_epochs is not None:
        epochs = min(epochs, budget.default_epochs)
    start, done = time.perf_counter(), 0
    while done < epochs and time.perf_counter() - start < budget.seconds:
        opt.step(closure)
        done += 1
    return net, done, epochs


def _describe(m: dict) -> str:
    specs = m["operator"] if isinstance(m["operator"], list) else [m["operator"]]
    names = "+".join(str(s.get("name")) + (f"({s['direction']})" if "direction" in s else "")
                     if isinstance(s, dict) else str(s) for s in specs)
    return f"{names} + {m['hidden']} {m['activation']}"


def _score(config: Path, overrides: dict, x: Tensor, y: Tensor, w: int, budget: Budget,
           cv: int | str | None, mode: str | None = None) -> tuple[float, float, bool]:
    """A candidate's validation MSE and its standard error, as ``torchhys fit`` scores it
    with ``model.select_cv`` = ``cv``: None, on the last quarter of the scored samples of
    every training row, fitted before it; ``k``, by blocked cross-validation inside the
    training rows (:func:`~torchhys.training.selection.fold_masks`: each fold fitted on
    the whole rows without its block's targets, the states running through it);
    ``"recording"``, each training row held out once, fitted on the others; with ``mode``
    ``"rolling"``, each block (row) after the first scored by a fit of those before it
    (for blocks, ``fold_masks(..., rolling=True)``). Returns the MSE
    and its standard error, NaN (never chosen, as ``torchhys fit`` scores it) when a fit
    fails (``FitError``) or the MSE is not finite, and whether a training stopped at the
    budget's time cap."""
    if cv is None:
        c = holdout(x.shape[1], w)
        folds = [(x[:, :c], y[:, :c], (slice(None), slice(c, None)), None)]
    elif cv == RECORDING:
        if x.shape[0] < 2:
            raise ValueError(f"model.select_cv={RECORDING!r} holds each training recording out "
                             f"once, but the protocol has {x.shape[0]} training row")
        if mode == "rolling":
            fits = [(list(range(r)), r) for r in range(1, len(x))]
        else:
            fits = [([j for j in range(len(x)) if j != r], r) for r in range(len(x))]
        folds = [(x[rest], y[rest], (slice(r, r + 1), slice(w, None)), None)
                 for rest, r in fits]
    else:
        mask = torch.zeros_like(x, dtype=torch.bool)
        mask[:, w:] = True
        folds = []
        rolling = mode == "rolling"
        for f in range(cv - 1 if rolling else cv):
            fitted, held = fold_masks(mask, cv, f, rolling=rolling)
            folds.append((x, y, held, mask & ~fitted))
    errors, capped = [], False
    for fx, fy, scored, held in folds:
        try:
            net, done, epochs = _train_config(config, fx, fy, w, budget, overrides, held)
        except FitError:
            return math.nan, math.nan, capped
        capped |= done < epochs
        dtype = next(net.parameters()).dtype
        with torch.no_grad():
            e = net(x.to(dtype))[0].to(F64) - y
        errors.append(e[scored].square().reshape(-1))
    e2 = torch.cat(errors)
    mse = float(e2.mean())
    if not math.isfinite(mse):
        return math.nan, math.nan, capped
    return mse, standard_error(e2), capped


def default_net(split: Split, budget: Budget, config: Path = CONFIG
                ) -> tuple[InverseHysteresisNet, str, float]:
    """The network of :func:`default` (trained as it says), its description and its
    hold-out RMSE."""
    x, y, w = split.x, split.y, split.warmup
    m = _config_model(config)[0]
    candidates = m.pop("select", None) or [{}]
    cv = m.pop("select_cv", None)
    mode = m.pop("select_cv_mode", None)
    rule = m.pop("select_rule", None) or "min"
    scores, capped_cv = [], False
    for i, overrides in enumerate(candidates):
        mse, se, capped = _score(config, overrides, x, y, w, budget, cv, mode)
        scores.append(CandidateScore(i, overrides, mse, val_se=se))  # NaN: never chosen
        capped_cv |= capped
    if all(math.isnan(s.val_mse) for s in scores):
        raise FitError("no candidate of the config could be fitted")
    chosen = best(scores, rule)  # as torchhys fit chooses (the first candidate NaN or not)
    order = [chosen] + sorted((s for s in scores if s is not chosen
                               and not math.isnan(s.val_mse)), key=lambda s: s.val_mse)
    failed, refit = 0, None
    for s in order:  # the chosen candidate, or the best one whose refit succeeds
        try:
            refit = _train_config(config, x, y, w, budget, candidates[s.index])
            i = s.index
            break
        except FitError:
            failed += 1
    if refit is None:
        raise FitError("no candidate of the config could be refitted")
    net, done, epochs = refit
    validation, score = "", math.sqrt(s.val_mse)
    if cv is not None:  # the row's hold-out RMSE, as the other rows'
        how = f"{cv} rolling" if mode == "rolling" else f"{cv}"
        validation = f", select_cv {how} RMSE {score:.4g}"
        held = _score(config, candidates[i], x, y, w, budget, None)[0]
        score = math.sqrt(held) if math.isfinite(held) else math.inf
    capped = f" (capped at {budget.seconds:g} s)" if done < epochs else ""
    if capped_cv:
        capped += f" (a validation training capped at {budget.seconds:g} s)"
    note = f" ({failed} failed refits)" if failed else ""
    label = f"candidate {i}{note}: " if len(candidates) > 1 else ""
    choice = (f"{config.name}: {label}{_describe({**m, **candidates[i]})}, {m['optimizer']} "
              f"{done} epochs{capped}{validation}")
    return net, choice, score


def default(split: Split, budget: Budget, config: Path = CONFIG) -> Fitted:
    """The model section of a ``torchhys fit`` config, trained as its trainer section says
    on the whole training part. With ``model.select``, every candidate is scored as
    ``torchhys fit`` scores it (:func:`_score`: on the hold-out, or by the cross-validation
    of the config's ``select_cv``), the config's ``select_rule`` chooses one (a candidate
    that cannot be fitted is skipped), and it is refitted on the whole training part;
    without, the hold-out RMSE comes from a second fit before it. The row's hold-out RMSE
    is that of the chosen candidate fitted before the hold-out (as every row's, for
    ``selected``). Its prediction is the network's output saturated to the training target
    range (the exported command limits; :func:`default_net` gives the network, as
    ``benchmarks/deploy_safety.py`` scores it through the exported compensator's input clamp
    and direction guard); the candidates are scored without it, as ``torchhys fit`` scores
    them."""
    net, choice, score = default_net(split, budget, config)
    dtype = next(net.parameters()).dtype
    low, high = default_limits(net)  # the exported command limits
    return Fitted(lambda v: net(v.to(dtype))[0].to(F64).clamp(low, high), choice, score)


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


def run_in_processes(args: argparse.Namespace, jobs: int) -> tuple[list[dict], list[str]]:
    """Each protocol of ``args.data`` in a process of its own (this script with the same
    options and ``--data NAME``), ``jobs`` at a time; their tables read back in the order of
    ``args.data``, and their logs.

    Raises:
        RuntimeError: a protocol's process failed (its name and the end of its output).
    """
    common = ["--ferrite", str(args.ferrite), "--piezo", str(args.piezo), "--quad",
              str(args.quad), "--config", str(args.config), "--models", *args.models]
    if args.quick:
        common.append("--quick")
    with tempfile.TemporaryDirectory() as tmp:
        def one(name: str) -> tuple[str, str]:
            out = Path(tmp) / f"{name}.csv"
            done = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--data",
                                   name, "--out", str(out), *common],
                                  capture_output=True, text=True)
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
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
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


if __name__ == "__main__":
    main()
