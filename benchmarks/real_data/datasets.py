"""The measured recordings: where they are, how they are read, and each protocol's split
into training rows and held-out recordings (physical units, float64)."""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

ROOT = Path(__file__).resolve().parents[2]
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
F64 = torch.float64


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
