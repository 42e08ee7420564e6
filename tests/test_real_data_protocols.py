"""The real-data benchmark's data sets and protocols (``benchmarks.real_data.datasets`` and
``.protocols``): each protocol's training rows and held-out recordings, checked against the
files read here, and the files each protocol reads."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

import benchmarks.real_data as rd

ROOT = Path(__file__).resolve().parents[1]
FERRITE = ROOT / "examples" / "data" / "mnzn_ferrite_bh_loops.csv"


def test_each_protocol_declares_the_file_it_reads(tmp_path):
    """A protocol that declares no option builds from the shipped files alone (every option
    pointing nowhere); one that declares an option fails without that file and builds with
    the others absent (the ferrite loops: the copy in examples/data)."""
    nowhere = rd.Files(*(tmp_path / name for name in rd.Files._fields))
    assert {p.needs for p in rd.DATASETS.values()} == {None, *rd.Files._fields}
    for name, protocol in rd.DATASETS.items():
        if protocol.needs is None:
            split = protocol.build(nowhere)
            assert split.y[:, split.warmup:].numel() > 0 and split.test, name
            continue
        with pytest.raises((OSError, ValueError)):
            protocol.build(nowhere)
        if protocol.needs == "ferrite":
            assert protocol.build(nowhere._replace(ferrite=FERRITE)).test, name


def test_short_and_long_records_keep_the_held_out_part():
    split = rd.DATASETS["mnzn_ferrite"][1](rd.Files(FERRITE))
    coarse = rd.shortened(split, stride=True)  # every 5th sample of the two loops
    assert coarse.y[:, coarse.warmup:].numel() == 52
    np.testing.assert_array_equal(coarse.x.numpy(), split.x[:, ::5].numpy())
    assert coarse.test is split.test
    slow = rd.shortened(split, n=20, every=3)  # warm-up and 60 samples, every 3rd
    assert slow.warmup == -(-split.warmup // 3) and slow.test is split.test
    np.testing.assert_array_equal(slow.y.numpy(),
                                  split.y[:, :split.warmup + 60:3].numpy())
    assert split.warmup % 3 == 0 and slow.y[:, slow.warmup:].shape[1] == 20
    for bad in ({"every": 0}, {"every": 2, "stride": True}):
        with pytest.raises(ValueError, match="every must be a positive int"):
            rd.shortened(split, **bad)
    log = rd.shortened(split)  # the first row, its warm-up and 50 samples
    assert log.x.shape == (1, split.warmup + 50) and log.warmup == split.warmup
    np.testing.assert_array_equal(log.y.numpy(), split.y[:1, :split.warmup + 50].numpy())
    long = rd.tiled(split, total=10_000)
    assert long.y[:, long.warmup:].numel() >= 10_000 and long.test is split.test
    T = split.x.shape[1]
    np.testing.assert_array_equal(long.x[:, T:2 * T].numpy(), split.x.numpy())


def _piezo_file(path: Path, n: int = 2001, rate: float = 200.0) -> tuple[np.ndarray, ...]:
    """A record in the published SmartHysteresis layout: ',time,displacement,voltage'."""
    t = np.arange(n) / rate
    volt = np.where(t >= 3.26, 150.0 * np.sin(2 * np.pi * (t - 3.26)), 0.0)
    disp = 0.12 * volt + 0.3 * np.sin(3.0 * t)
    rows = zip(t, volt, disp, strict=True)
    path.write_text("".join(f",{a:.17g},{c:.17g},{b:.17g}\n" for a, b, c in rows))
    return t, volt, disp


def test_piezo_record_is_split_in_time(tmp_path):
    t, volt, disp = _piezo_file(tmp_path / "piezo.csv")
    cut, w = int(np.searchsorted(t, 7.0)), int(np.searchsorted(t, 3.3))
    comp = rd.piezo(tmp_path / "piezo.csv", compensator=True)
    # displacement -> voltage: one training row up to 7 s, states run to 3.3 s
    np.testing.assert_array_equal(comp.x.numpy(), disp[None, :cut])
    np.testing.assert_array_equal(comp.y.numpy(), volt[None, :cut])
    assert comp.warmup == w and t[w] >= 3.3 > t[w - 1]
    # the whole record is run from rest and scored from 7 s on
    (x, y, start), = comp.test
    np.testing.assert_array_equal(x.numpy(), disp)
    assert start == cut and t[cut] >= 7.0 > t[cut - 1]
    fwd = rd.piezo(tmp_path / "piezo.csv", compensator=False)
    np.testing.assert_array_equal(fwd.x.numpy(), volt[None, :cut])
    np.testing.assert_array_equal(fwd.test[0][1].numpy(), disp)


def test_sma_record_is_split_in_time():
    """Temperature -> extension: four thermal cycles train (from the first cooling; the load
    ramp at the hot temperature before it only runs the states), the last three are held
    out, the whole record run from its start."""
    d = rd.read_csv(rd.REAL / "sma_isobaric_thermal_cycles.csv")
    temp, ext = d["chamber_temperature_C"], d["extension_mm"]
    assert len(temp) == 1176 and np.isfinite(temp).all() and np.isfinite(ext).all()
    split = rd.DATASETS["sma_actuator"][1](rd.Files())
    w, cut = split.warmup, split.x.shape[1]
    np.testing.assert_array_equal(split.x.numpy(), temp[None, :cut])
    np.testing.assert_array_equal(split.y.numpy(), ext[None, :cut])
    (x, y, start), = split.test
    np.testing.assert_array_equal(x.numpy(), temp)
    np.testing.assert_array_equal(y.numpy(), ext)
    assert start == cut
    # before w: the load ramp at 50 C (the temperature held, the extension rising with the
    # load); from w: cooling; each cycle reaches -30 C once: 4 in training, 3 held out
    assert temp[:w].min() >= 45.0 > temp[w]
    assert np.ptp(d["load_N"][w:]) < 0.05 * d["load_N"][w:].mean()  # the load is held

    def cycles(a):  # falls below -25 C
        return int(((a[:-1] >= -25.0) & (a[1:] < -25.0)).sum())
    assert cycles(temp[w:cut]) == 4 and cycles(temp[cut:]) == 3
    assert temp[cut] < 45.0 <= temp[cut - 1]  # the cut: the fifth start of cooling


def test_piezo_file_errors_name_the_option(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,voltage\n0,1\n")
    with pytest.raises(ValueError, match="--piezo .*bad.csv"):
        rd.read_piezo(bad)
    short = tmp_path / "short.csv"
    _piezo_file(short, n=1000)  # 5 s: ends before the 7 s cut
    with pytest.raises(ValueError, match="must run past 7 s"):
        rd.piezo(short, compensator=True)


@pytest.mark.parametrize("dataset, file", [
    ("friction_damper_sines", "friction_damper_backlash_brfd.csv"),
    ("friction_damper_36lb_sines", "friction_damper_backlash_brfd_36lb.csv")])
def test_friction_damper_sines_protocol(dataset, file):
    """The 1 in sine tests train (one row, in order), the 0.5 in and 1.5 in ones are held
    out from rest: the file's rows, and the 1.5 in tests reach beyond the training range."""
    split = rd.DATASETS[dataset][1](rd.Files(FERRITE))
    d = rd.read_csv(ROOT / "examples/data/real" / file)
    rec = d["recording"].astype(int)
    train = np.isin(rec, [1, 4, 7])
    assert split.x.shape == (1, int(train.sum())) and split.warmup == 0
    np.testing.assert_array_equal(split.x[0].numpy(), d["displacement_in"][train])
    np.testing.assert_array_equal(split.y[0].numpy(), d["force_kip"][train])
    assert [len(x) for x, _, _ in split.test] == [int((rec == i).sum())
                                                  for i in (0, 2, 3, 5, 6, 8, 9)]
    reach = [float(x.abs().max()) / float(split.x.abs().max()) for x, _, _ in split.test]
    assert [round(r * 2) / 2 for r in reach] == [0.5, 1.5, 0.5, 1.5, 0.5, 1.5, 0.5]
    assert sorted(set(rec)) == list(range(10 if "36lb" in file else 14))


def test_the_two_band_tensions_are_two_records():
    """The 36 lb sine tests are measurements of their own: the same drive as the 30 lb ones
    (amplitudes, frequencies, lengths), with a higher friction force."""
    a = np.genfromtxt(ROOT / "examples/data/real/friction_damper_backlash_brfd.csv",
                      delimiter=",", names=True)
    b = np.genfromtxt(ROOT / "examples/data/real/friction_damper_backlash_brfd_36lb.csv",
                      delimiter=",", names=True)
    for r in range(10):
        x, y = a[a["recording"] == r], b[b["recording"] == r]
        assert len(x) == len(y)
        np.testing.assert_allclose(np.abs(y["displacement_in"]).max(),
                                   np.abs(x["displacement_in"]).max(), rtol=0.05)
        assert np.percentile(np.abs(y["force_kip"]), 95) > 1.2 * np.percentile(
            np.abs(x["force_kip"]), 95)


def _slac_run(path: Path, run: int, current: np.ndarray, gradient: np.ndarray) -> None:
    """A run in the published layout of the SLAC magnetic measurements (strdat.ruN)."""
    head = (f"SLAC Magnetic Measurements\nDate: 11-11-2021\n\nProject: LCLS-II\n"
            f"Run Number: {run}\nTest Currents for MAIN (A): \n"
            + "".join(f"{c:10.2f}" for c in current) + "\n\n\n"
            "                                 Integrated Gradient (Quadrupole) \n\n"
            "     MAIN   +/- sigma         BL         sigBL           TF        sigTF\n"
            "            (A)                     (T)                       (T/A)\n"
            " ------------+----------  -----------+-----------   ------------+------------\n")
    rows = "".join(f"{c:12.4f}{0.001:11.4f}{g:13.6f}{1e-5:12.6f}{g / max(c, 1):13.6f}"
                   f"{1e-6:12.6f}  \n" for c, g in zip(current, gradient, strict=True))
    path.write_text(head + rows)


def test_quad_runs_are_read_and_split_by_run(tmp_path):
    rng = np.random.default_rng(0)
    runs = {}
    for r in rd.QUAD_RUNS:
        n = 61 if r == 3 else 10 + r
        # run 3 rises to 165 A in 11 samples, then falls (a later peak reads a little higher)
        current = np.concatenate([[0.0], np.linspace(16.5, 165.0, 10), [150.0, 165.04],
                                  rng.uniform(0, 165, n - 13)]) if r == 3 else \
            rng.uniform(0, 165, n)
        gradient = 0.0316 * current + 0.03 + 1e-4 * rng.standard_normal(n)
        _slac_run(tmp_path / f"strdat.ru{r}", r, current, gradient)
        runs[r] = np.round(current, 4), np.round(gradient, 6)
    np.testing.assert_array_equal(
        np.stack(rd.read_slac_run(tmp_path / "strdat.ru5")), np.stack(runs[5]))
    comp = rd.quad(tmp_path, compensator=True)
    # gradient -> current; the major loop trains, its first rise (11 samples) runs the states
    np.testing.assert_array_equal(comp.x.numpy(), runs[3][1][None])
    np.testing.assert_array_equal(comp.y.numpy(), runs[3][0][None])
    assert comp.warmup == 11
    assert len(comp.test) == len(rd.QUAD_RUNS) - 1
    for (x, y, w), r in zip(comp.test, rd.QUAD_RUNS[1:], strict=True):
        # each held-out run after the major loop's currents, scored on its own samples
        assert w == 61
        np.testing.assert_array_equal(x.numpy(), np.concatenate([runs[3][1], runs[r][1]]))
        np.testing.assert_array_equal(y[w:].numpy(), runs[r][0])
    fwd = rd.quad(tmp_path, compensator=False)
    np.testing.assert_array_equal(fwd.x.numpy(), runs[3][0][None])
    assert rd.Files(quad=tmp_path).missing("quad") == []
    (tmp_path / "strdat.ru8").unlink()  # a folder without every run is skipped
    assert rd.Files(quad=tmp_path).missing("quad") == [tmp_path / "strdat.ru8"]
    _slac_run(tmp_path / "strdat.ru8", 8, *runs[8])
    rows = rd.main(["--quick", "--data", "quad_magnet_forward", "--quad", str(tmp_path),
                    "--models", "stop_pi"])
    assert {r["n_train"] for r in rows} == {50}
    assert {r["n_test"] for r in rows} == {
        sum(len(runs[r][0]) for r in rd.QUAD_RUNS[1:])}


def test_a_quad_run_in_another_layout_is_refused(tmp_path):
    (tmp_path / "strdat.ru3").write_text("current,gradient\n0,0.03\n16.5,0.55\n")
    with pytest.raises(ValueError, match=r"--quad .*strdat.ru3: no table"):
        rd.read_slac_run(tmp_path / "strdat.ru3")
    (tmp_path / "strdat.ru4").write_text(" ----+----\n 1.0 0.1 x\n")
    with pytest.raises(ValueError, match=r"--quad .*strdat.ru4: expected rows"):
        rd.read_slac_run(tmp_path / "strdat.ru4")


def test_micromanipulator_records_train_and_test():
    """The piezo micromanipulator: the identification record (a 1 Hz sine over the full
    voltage range, 200 Hz) trains, the test record (loops of many amplitudes inside it) is held
    out, each whole and from its start, its first period only running the states; the
    compensator swaps input and target."""
    d = rd.read_csv(rd.REAL / "piezo_micromanipulator.csv")
    rec, t = d["recording"], d["t_s"]
    volt, disp = d["voltage_V"], d["displacement_um"]
    assert np.isfinite(volt).all() and np.isfinite(disp).all()
    assert [int((rec == r).sum()) for r in (0, 1)] == [8027, 14155]
    for r in (0, 1):
        np.testing.assert_allclose(np.diff(t[rec == r]), 0.005, atol=1e-9)  # 200 Hz
    v0, v1 = volt[rec == 0], volt[rec == 1]
    np.testing.assert_array_equal(v0[200:], v0[:-200])  # one period: 1 s
    assert v0.min() == 0.0 and v0.max() == 3.6
    assert v0.min() < v1.min() and v1.max() < v0.max()  # the test loops lie inside

    fwd = rd.DATASETS["piezo_manipulator_forward"][1](rd.Files())
    inv = rd.DATASETS["piezo_manipulator"][1](rd.Files())
    assert fwd.warmup == inv.warmup == 200 and not fwd.magnetic
    np.testing.assert_array_equal(fwd.x.numpy(), v0[None])
    np.testing.assert_array_equal(fwd.y.numpy(), disp[rec == 0][None])
    np.testing.assert_array_equal(inv.x.numpy(), fwd.y.numpy())
    np.testing.assert_array_equal(inv.y.numpy(), fwd.x.numpy())
    (x, y, w), = fwd.test
    np.testing.assert_array_equal(x.numpy(), v1)
    np.testing.assert_array_equal(y.numpy(), disp[rec == 1])
    assert w == 200
    (xi, yi, wi), = inv.test
    np.testing.assert_array_equal(xi.numpy(), disp[rec == 1])
    np.testing.assert_array_equal(yi.numpy(), v1)
    assert wi == 200
    short = rd.DATASETS["piezo_manipulator_short"][1](rd.Files())
    # one period of warm-up and one scored, at 50 Hz (every 4th sample): 50 scored samples
    assert short.warmup == 50 and short.y[:, short.warmup:].numel() == 50
    np.testing.assert_array_equal(short.x.numpy(), disp[rec == 0][None, :400:4])
    np.testing.assert_array_equal(short.y.numpy(), v0[None, :400:4])
    assert len(short.test) == 1
    np.testing.assert_array_equal(short.test[0][0].numpy(), disp[rec == 1])
    assert short.test[0][2] == 200  # the held-out record stays at 200 Hz
    assert rd.DATASETS["piezo_manipulator"].needs is None  # shipped: no option
    assert rd.DATASETS["piezo_actuator_short"].needs == "piezo"


def test_seal_records_train_and_test():
    """The six seals of the pneumatic cylinder: per seal, the 1 and 7 bar records train (cut
    to a common length), the 3 and 5 bar ones are held out, all from rest; the friction is
    the chamber pressure on the piston (its bore per seal) less the rod force. Checked against
    the columns read with the csv module and a friction computed here."""
    with open(rd.REAL / "pneumatic_cylinder_seals_friction.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    seals = list(dict.fromkeys(r["seal"] for r in rows))
    assert seals == list(rd.SEALS.values())
    recs: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        recs.setdefault((r["seal"], int(r["pressure_setpoint_bar"])), []).append(r)
    assert sorted({bar for _, bar in recs}) == [1, 3, 5, 7] and len(recs) == 24
    ids = [int(r["recording"]) for r in rows]
    assert ids == sorted(ids) and len(set(ids)) == 24  # one recording per seal and pressure

    for key, name in rd.SEALS.items():
        bore = 25.7e-3 if "257" in name else 25e-3
        rec = {bar: recs[(name, bar)] for bar in (1, 3, 5, 7)}
        col = {bar: {c: np.array([float(r[c]) for r in rec[bar]])
                     for c in ("t_ms", "position_mm", "pressure_bar", "force_N")}
               for bar in rec}
        for bar, c in col.items():
            assert np.all(np.diff(c["t_ms"]) > 0), (name, bar)
            assert abs(np.median(c["pressure_bar"]) - bar) < 0.1, (name, bar)
            assert c["position_mm"].min() < 0 and c["position_mm"].max() > 35  # full strokes

        friction = {bar: c["pressure_bar"] * 1e5 * math.pi * bore**2 / 4 - c["force_N"]
                    for bar, c in col.items()}
        split = rd.DATASETS[f"pneumatic_{key}"][1](rd.Files())
        T = min(len(rec[1]), len(rec[7]))
        assert split.warmup == 0 and not split.magnetic and split.x.shape == (2, T)
        for i, bar in enumerate((1, 7)):
            np.testing.assert_array_equal(split.x[i].numpy(), col[bar]["position_mm"][:T])
            np.testing.assert_allclose(split.y[i].numpy(), friction[bar][:T], rtol=0,
                                       atol=1e-9)
        assert [len(x) for x, _, _ in split.test] == [len(rec[3]), len(rec[5])]
        for (x, y, w), bar in zip(split.test, (3, 5), strict=True):
            assert w == 0
            np.testing.assert_array_equal(x.numpy(), col[bar]["position_mm"])
            np.testing.assert_allclose(y.numpy(), friction[bar], rtol=0, atol=1e-9)
        assert rd.DATASETS[f"pneumatic_{key}"].needs is None  # shipped: no option
    # the O-ring file's protocol is the same, its bore 25 mm
    oring = rd.DATASETS["pneumatic_oring"][1](rd.Files())
    d = rd.read_csv(rd.REAL / "pneumatic_cylinder_oring_friction.csv")
    one = d["recording"] == 0
    np.testing.assert_allclose(
        oring.y[0].numpy(), d["pressure_bar"][one] * 1e5 * math.pi * 0.0125**2
        - d["force_N"][one], rtol=0, atol=1e-9)


def test_reversal_curves_train_and_test():
    """The FeCo nanowire FORCs: 152 curves, each a calibration point near positive saturation
    then a sweep up from its reversal field; the even-numbered curves train in one row in
    measurement order, the odd ones are held out from their calibration point. Checked against
    the file read with the csv module."""
    with open(rd.REAL / "feco_nanowires_forc.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    curves: dict[int, list[tuple[float, float]]] = {}
    for r in rows:
        curves.setdefault(int(r["curve"]), []).append((float(r["field_Oe"]),
                                                       float(r["moment_emu"])))
    assert sorted(curves) == list(range(152))
    assert sum(len(c) - 1 for c in curves.values()) == 30476
    reversal = [c[1][0] for c in curves.values()]
    assert all(np.diff(reversal) < 0)  # each curve reverses lower than the one before
    for c in curves.values():
        h = np.array(c)[:, 0]
        assert h[0] > 6800 and np.all(np.diff(h[1:]) > 0) and 4000 < h[-1] < h[0] + 1
    # the loop saturates: the lowest reversal's moment is near minus the calibration moment
    assert curves[151][1][1] == pytest.approx(-curves[151][0][1], rel=0.05)

    split = rd.DATASETS["feco_forc"][1](rd.Files())
    train = [p for i in range(0, 152, 2) for p in curves[i]]
    assert split.warmup == 1 and not split.magnetic
    np.testing.assert_array_equal(split.x[0].numpy(), [h for h, _ in train])
    np.testing.assert_array_equal(split.y[0].numpy(), [m for _, m in train])
    assert len(split.test) == 76
    for (x, y, w), i in zip(split.test, range(1, 152, 2), strict=True):
        assert w == 1
        np.testing.assert_array_equal(x.numpy(), [h for h, _ in curves[i]])
        np.testing.assert_array_equal(y.numpy(), [m for _, m in curves[i]])
    assert rd.DATASETS["feco_forc"].needs is None

