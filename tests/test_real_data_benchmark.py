"""Smoke test of benchmarks.real_data: its quick mode on the MnZn ferrite loops (the copy
in examples/data), the table's columns, and memoryless baselines fitted on the training part
only."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from _training_helpers import cli

import benchmarks.real_data as rd
from benchmarks.real_data import default_row
from torchhys import Drift, StopPrandtlIshlinskii, fit_jiles_atherton
from torchhys.training.selection import best

ROOT = Path(__file__).resolve().parents[1]
FERRITE = ROOT / "examples" / "data" / "mnzn_ferrite_bh_loops.csv"
COLUMNS = ("dataset", "model", "rmse", "ratio", "n_train", "n_test", "choice")


@pytest.fixture(scope="module")
def bench():
    return rd


@pytest.fixture
def choices(bench, monkeypatch):
    """The ``(scores, rule)`` of every choice the benchmark makes (its ``best``, watched)."""
    calls = []

    def watched(scores, rule="min"):
        calls.append((list(scores), rule))
        return best(scores, rule)

    monkeypatch.setattr(default_row, "best", watched)
    return calls


@pytest.fixture(scope="module")
def table(bench, tmp_path_factory):
    out = tmp_path_factory.mktemp("real_data") / "table.csv"
    rows = bench.main(["--quick", "--data", "mnzn_ferrite", "--ferrite", str(FERRITE),
                       "--out", str(out)])
    return rows, out


def _measured_with(select: str) -> str:
    """configs/measured.yaml with its ``select`` and ``select_rule`` replaced by ``select``
    (YAML lines of the model section)."""
    text = (ROOT / "configs" / "measured.yaml").read_text()
    cut, end = text.index("  select:"), text.index("\ndata:") + 1
    return text[:cut] + select + text[end:]


def _test_part(split):
    xs = np.concatenate([x[w:].numpy() for x, _, w in split.test])
    ys = np.concatenate([y[w:].numpy() for _, y, w in split.test])
    return xs, ys


def _rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2)))


def test_table_columns_and_rows(bench, table):
    rows, out = table
    with open(out, newline="") as f:
        reader = csv.DictReader(f)
        written = list(reader)
    assert tuple(reader.fieldnames) == COLUMNS
    assert [r["model"] for r in written] == [*bench.MODELS, "selected"]
    assert {"line", "poly", "pi_constrained", "generalized_pi", "preisach", "eiho_net",
            "default"} <= set(bench.MODELS)
    base = min(r["rmse"] for r in rows if r["model"] in ("line", "poly"))
    for r, w in zip(rows, written, strict=True):
        assert tuple(r) == COLUMNS
        assert r["dataset"] == w["dataset"] == "mnzn_ferrite"
        # loops 0 and 3 train, 1 and 2 test: the last of three periods (129 samples) scored
        assert (r["n_train"], r["n_test"]) == (258, 258)
        assert math.isfinite(r["rmse"]) and r["rmse"] > 0
        assert r["ratio"] == pytest.approx(r["rmse"] / base)
        assert float(w["rmse"]) == pytest.approx(r["rmse"], rel=1e-12)
        assert r["choice"] and not r["choice"].startswith("failed")


def _row(dataset: str, model: str, rmse: float, base: float) -> dict:
    return {"dataset": dataset, "model": model, "rmse": rmse, "ratio": rmse / base,
            "n_train": 1, "n_test": 1, "choice": ""}


def test_targets_tally_counts_and_names_the_misses(bench):
    """Two protocols: on ``a`` the default meets the ratio and the best family (an n/a row
    skipped) does not; on ``b`` the default misses and is worse than the line, the best
    family meets it."""
    rows = [_row("a", "line", 2.0, 1.0), _row("a", "poly", 1.0, 1.0),
            _row("a", "stop_pi", 0.8, 1.0), _row("a", "jiles_atherton", math.nan, 1.0),
            _row("a", "default", 0.4, 1.0), _row("a", "selected", 0.8, 1.0),
            _row("b", "line", 1.0, 1.0), _row("b", "poly", 3.0, 1.0),
            _row("b", "preisach", 0.3, 1.0), _row("b", "eiho_net", 0.45, 1.0),
            _row("b", "default", 1.5, 1.0)]
    text = bench.targets(rows)
    assert "over 2 protocols" in text
    assert "default: ratio <= 0.5 on 1 of 2; misses: b 1.50" in text
    assert "no worse than the line on 1 of 2; worse: b" in text
    assert "best family: ratio <= 0.5 on 1 of 2; misses: a 0.80 (stop_pi)" in text
    # without default rows only the families are tallied
    text = bench.targets([r for r in rows if r["model"] != "default"])
    assert "default" not in text.split(":", 1)[1] and "on 1 of 2" in text


def test_saved_tables_are_tallied_as_the_run(bench, table, tmp_path, capsys):
    rows, out = table
    read = bench.main(["--tables", str(out)])
    assert [(r["dataset"], r["model"]) for r in read] == [(r["dataset"], r["model"])
                                                         for r in rows]
    for r, w in zip(rows, read, strict=True):
        assert w["rmse"] == pytest.approx(r["rmse"], rel=1e-12)
    assert bench.targets(read) == bench.targets(rows)
    assert bench.targets(rows) in capsys.readouterr().out
    bad = tmp_path / "other.csv"
    bad.write_text("dataset,model,rmse\nx,line,1\n")
    with pytest.raises(ValueError, match="--tables .*other.csv"):
        bench.read_tables([bad])


def test_jobs_run_each_protocol_in_a_process_of_its_own(bench, tmp_path, capsys):
    """``--jobs 2``: the same rows as one process, in the order of ``--data``, a missing
    optional file still skipped with its message; a failing protocol names itself."""
    args = ["--quick", "--models", "stop_pi", "--ferrite", str(FERRITE),
            "--piezo", str(tmp_path / "absent.csv"),
            "--data", "pneumatic_kdn", "piezo_actuator", "mnzn_ferrite"]
    serial = bench.main(args)
    capsys.readouterr()
    parallel = bench.main([*args, "--jobs", "2", "--out", str(tmp_path / "t.csv")])
    out = capsys.readouterr().out
    assert "skipping piezo_actuator" in out and "targets over 2 protocols" in out
    assert [(r["dataset"], r["model"], r["choice"]) for r in parallel] == [
        (r["dataset"], r["model"], r["choice"]) for r in serial]
    for a, b in zip(serial, parallel, strict=True):
        assert b["rmse"] == pytest.approx(a["rmse"], rel=1e-12)
    assert len(bench.read_tables([tmp_path / "t.csv"])) == len(serial)
    broken = tmp_path / "broken.yaml"
    broken.write_text("model:\n  select: 3\n")
    with pytest.raises(RuntimeError, match="pneumatic_kdn: its process failed"):
        bench.main(["--quick", "--models", "default", "--config", str(broken), "--jobs", "2",
                    "--data", "pneumatic_kdn", "pneumatic_pk"])
    with pytest.raises(SystemExit):
        bench.main([*args, "--jobs", "0"])


def test_models_option_fits_those_rows_beside_the_baselines(bench, table):
    rows = bench.main(["--quick", "--data", "mnzn_ferrite", "--ferrite", str(FERRITE),
                       "--models", "stop_pi"])
    assert [r["model"] for r in rows] == ["line", "poly", "stop_pi", "selected"]
    full = {r["model"]: r for r in table[0]}
    for r in rows[:3]:  # the same fits as in the full table
        assert r["rmse"] == full[r["model"]]["rmse"] and r["ratio"] == full[r["model"]]["ratio"]


def test_baselines_use_the_training_part_only(bench, table):
    rows = {r["model"]: r for r in table[0]}
    split = bench.DATASETS["mnzn_ferrite"][1](bench.Files(FERRITE))
    w = split.warmup
    xt, yt = split.x[:, w:].reshape(-1).numpy(), split.y[:, w:].reshape(-1).numpy()
    xs, ys = _test_part(split)
    k, c = np.polyfit(xt, yt, 1)
    assert rows["line"]["rmse"] == pytest.approx(_rmse(k * xs + c - ys), rel=1e-9)
    # the hold-out: the last quarter of the scored samples of each training row
    cut = bench.holdout(split.x.shape[1], w)
    assert cut == split.x.shape[1] - round(0.25 * 129)
    fx, fy = split.x[:, w:cut].reshape(-1).numpy(), split.y[:, w:cut].reshape(-1).numpy()
    vx, vy = split.x[:, cut:].reshape(-1).numpy(), split.y[:, cut:].reshape(-1).numpy()
    k, c = np.polyfit(fx, fy, 1)
    assert rows["line"]["choice"].endswith(f"; hold-out {_rmse(k * vx + c - vy):.4g}")
    scores = [_rmse(np.polynomial.Polynomial.fit(fx, fy, d)(vx) - vy) for d in range(1, 10)]
    degree = 1 + int(np.argmin(scores))
    assert rows["poly"]["choice"] == f"degree={degree}; hold-out {min(scores):.4g}"
    p = np.polynomial.Polynomial.fit(xt, yt, degree)
    assert rows["poly"]["rmse"] == pytest.approx(_rmse(p(xs) - ys), rel=1e-9)
    # changing the held-out targets changes nothing in the fitted baselines
    spoiled = split._replace(test=[(x, 1e6 + 0 * y, w) for x, y, w in split.test])
    for fit in (bench.line, bench.poly):
        a, b = fit(split, bench.QUICK), fit(spoiled, bench.QUICK)
        assert (a.choice, a.holdout) == (b.choice, b.holdout)
        x = split.test[0][0][None]
        np.testing.assert_array_equal(a.predict(x).numpy(), b.predict(x).numpy())


@pytest.mark.parametrize("option, dataset", [("--ferrite", "mnzn_ferrite"),
                                             ("--piezo", "piezo_actuator"),
                                             ("--quad", "quad_magnet")])
def test_missing_optional_file_is_skipped(bench, tmp_path, capsys, option, dataset):
    rows = bench.main(["--quick", "--data", dataset, option, str(tmp_path / "absent.csv")])
    assert rows == []
    assert f"skipping {dataset}" in capsys.readouterr().out


def test_each_protocol_declares_the_file_it_reads(bench, tmp_path):
    """A protocol that declares no option builds from the shipped files alone (every option
    pointing nowhere); one that declares an option fails without that file and builds with
    the others absent (the ferrite loops: the copy in examples/data)."""
    nowhere = bench.Files(*(tmp_path / name for name in bench.Files._fields))
    assert {p.needs for p in bench.DATASETS.values()} == {None, *bench.Files._fields}
    for name, protocol in bench.DATASETS.items():
        if protocol.needs is None:
            split = protocol.build(nowhere)
            assert split.y[:, split.warmup:].numel() > 0 and split.test, name
            continue
        with pytest.raises((OSError, ValueError)):
            protocol.build(nowhere)
        if protocol.needs == "ferrite":
            assert protocol.build(nowhere._replace(ferrite=FERRITE)).test, name


def test_short_and_long_records_keep_the_held_out_part(bench):
    split = bench.DATASETS["mnzn_ferrite"][1](bench.Files(FERRITE))
    coarse = bench.shortened(split, stride=True)  # every 5th sample of the two loops
    assert coarse.y[:, coarse.warmup:].numel() == 52
    np.testing.assert_array_equal(coarse.x.numpy(), split.x[:, ::5].numpy())
    assert coarse.test is split.test
    slow = bench.shortened(split, n=20, every=3)  # warm-up and 60 samples, every 3rd
    assert slow.warmup == -(-split.warmup // 3) and slow.test is split.test
    np.testing.assert_array_equal(slow.y.numpy(),
                                  split.y[:, :split.warmup + 60:3].numpy())
    assert split.warmup % 3 == 0 and slow.y[:, slow.warmup:].shape[1] == 20
    for bad in ({"every": 0}, {"every": 2, "stride": True}):
        with pytest.raises(ValueError, match="every must be a positive int"):
            bench.shortened(split, **bad)
    log = bench.shortened(split)  # the first row, its warm-up and 50 samples
    assert log.x.shape == (1, split.warmup + 50) and log.warmup == split.warmup
    np.testing.assert_array_equal(log.y.numpy(), split.y[:1, :split.warmup + 50].numpy())
    long = bench.tiled(split, total=10_000)
    assert long.y[:, long.warmup:].numel() >= 10_000 and long.test is split.test
    T = split.x.shape[1]
    np.testing.assert_array_equal(long.x[:, T:2 * T].numpy(), split.x.numpy())


def test_the_default_row_follows_the_configs_selection_rule(bench, tmp_path, choices):
    """The default row scores each candidate on the hold-out (MSE and its standard error)
    and chooses with the config's select_rule, as torchhys fit does."""
    split = bench.DATASETS["mnzn_ferrite"][1](bench.Files(FERRITE))
    two = _measured_with("""  select:
    - operator: null
    - operator: [{fit: gpi, n_widths: 5, units: 2, epochs: 40, direction: inverse}]
  select_rule: RULE
""")
    for rule in ("min", "1se"):
        path = tmp_path / f"{rule}.yaml"
        path.write_text(two.replace("RULE", rule))
        fitted = bench.default(split, bench.QUICK, path)
        scores, used = choices[-1]
        assert used == rule and [s.index for s in scores] == [0, 1]
        assert all(s.val_se > 0 for s in scores)
        chosen = best(scores, rule)
        assert f"candidate {chosen.index}" in fitted.choice
        assert fitted.holdout == pytest.approx(math.sqrt(chosen.val_mse), rel=1e-12)
        assert fitted.predict(split.test[0][0][None]).isfinite().all()


@pytest.mark.parametrize(("cv", "mode"), [(3, None), ("recording", None), (3, "rolling"),
                                         ("recording", "rolling")])
def test_the_default_row_cross_validates_as_its_config_says(bench, tmp_path, choices, cv,
                                                            mode):
    """With model.select_cv, the default row scores every candidate by cross-validation
    inside the training rows, as torchhys fit does: blocked (each row's scored samples cut
    into k contiguous blocks, each held out once, the rows run whole) or one training row
    held out at a time; with select_cv_mode rolling, each block (row) after the first
    scored by a fit of those before it only. The straight line's score against numpy least
    squares per fold."""
    split = bench.DATASETS["mnzn_ferrite"][1](bench.Files(FERRITE))
    path = tmp_path / "cv.yaml"
    path.write_text(_measured_with(f"""  select:
    - operator: null
    - operator: [{{fit: stop_pi, n_widths: 5, segments: 2}}]
  select_cv: {cv}
  select_cv_mode: {mode or "blocked"}
  select_rule: min
"""))
    fitted = bench.default(split, bench.QUICK, path)
    scores, _ = choices[-1]
    assert [s.index for s in scores] == [0, 1] and all(s.val_se > 0 for s in scores)
    x, y, w = split.x.numpy(), split.y.numpy(), split.warmup
    rows, T = x.shape
    if cv == "recording":
        folds = []
        for r in range(1 if mode == "rolling" else 0, rows):
            held = np.zeros_like(x, dtype=bool)
            held[r, w:] = True
            train = np.zeros_like(held)
            fitted_rows = range(r) if mode == "rolling" else [j for j in range(rows) if j != r]
            train[list(fitted_rows), w:] = True
            folds.append((train, held))
    else:
        folds = []
        blocks = np.array_split(np.arange(w, T), cv)
        for f in range(1 if mode == "rolling" else 0, cv):
            held = np.zeros_like(x, dtype=bool)
            held[:, blocks[f]] = True
            train = np.zeros_like(held)
            if mode == "rolling":
                train[:, np.concatenate(blocks[:f])] = True
            else:
                train[:, w:] = True
                train &= ~held
            folds.append((train, held))
    errors = []
    for train, held in folds:
        design = np.stack([np.ones(train.sum()), x[train]], axis=1)
        coef = np.linalg.lstsq(design, y[train], rcond=None)[0]
        errors.append(coef[0] + coef[1] * x[held] - y[held])
    reference = float(np.mean(np.concatenate(errors) ** 2))
    assert scores[0].val_mse == pytest.approx(reference, rel=1e-6)
    chosen = best(scores, "min")
    assert f"candidate {chosen.index}" in fitted.choice
    how = f"{cv} rolling" if mode == "rolling" else f"{cv}"
    assert f"select_cv {how} RMSE {math.sqrt(chosen.val_mse):.4g}" in fitted.choice
    assert math.isfinite(fitted.holdout) and fitted.holdout != pytest.approx(
        math.sqrt(chosen.val_mse))  # the row's hold-out RMSE, not the cross-validation's


@pytest.mark.parametrize("mode", ["blocked", "rolling"])
def test_the_default_rows_cross_validation_scores_as_torchhys_fit_does(bench, tmp_path,
                                                                       monkeypatch, mode):
    """The default row's blocked (or rolling-origin) cross-validation gives the scores of
    ``torchhys fit --model.select_cv 3`` (its selection.csv) on the same training loops: a
    fitted family operator (the stop-type model, refitted in every fold on the fold's
    training samples only) and the line."""
    select = f"""  select:
    - operator: null
    - operator: [{{fit: stop_pi, n_widths: 5, segments: 2}}]
  select_cv: 3
  select_cv_mode: {mode}
  select_rule: min
"""
    path = tmp_path / "cv.yaml"
    path.write_text(_measured_with(select))
    root = tmp_path / "run"
    cli(monkeypatch, "fit", "--config", str(path), "--data.path", str(FERRITE),
        "--data.input_column", "B_T", "--data.target_column", "H_Apm",
        "--data.time_column", "null", "--data.run_column", "loop", "--data.warmup", "0",
        "--data.split_by", "recording", "--data.train_recordings", "[0, 3]",
        "--data.val_recordings", "[]", "--data.test_recordings", "[1, 2]",
        "--data.repeat", "3", "--trainer.max_epochs", "10", f"--trainer.default_root_dir={root}",
        "--trainer.enable_progress_bar=false")
    with (root / "logs/version_0/selection.csv").open() as fh:
        expected = [(float(r["val_mse"]), float(r["val_se"])) for r in csv.DictReader(fh)]
    split = bench.DATASETS["mnzn_ferrite"][1](bench.Files(FERRITE))
    candidates = [{"operator": None}, {"operator": [{"fit": "stop_pi", "n_widths": 5,
                                                     "segments": 2}]}]
    for candidate, (mse, se) in zip(candidates, expected, strict=True):
        got, got_se, capped = default_row._score(path, candidate, split.x, split.y, split.warmup,
                                                 bench.QUICK, 3, mode)
        # the CLI logs each fold's MSE in float32
        assert got == pytest.approx(mse, rel=1e-6) and got_se == pytest.approx(se, rel=1e-6)
        assert not capped


def test_a_candidate_that_cannot_be_fitted_keeps_its_place(bench, tmp_path, choices):
    """A candidate whose family cannot be fitted scores NaN in its place (as torchhys fit
    scores it), so the one-standard-error rule still reads the first candidate as the
    baseline, and a NaN is never chosen."""
    split = bench.DATASETS["mnzn_ferrite"][1](bench.Files(FERRITE))
    path = tmp_path / "nan.yaml"
    path.write_text(_measured_with("""  select:
    - operator: [{fit: pi_nonneg, n_widths: 10, direction: direct}]
    - operator: [{fit: stop_pi, n_widths: 5, segments: 2}]
  select_cv: 3
  select_rule: 1se
"""))
    fitted = bench.default(split, bench.QUICK, path)
    scores, _ = choices[-1]
    assert [s.index for s in scores] == [0, 1]
    assert math.isnan(scores[0].val_mse) and math.isfinite(scores[1].val_mse)
    assert "candidate 1" in fitted.choice


def test_the_config_is_read_as_torchhys_fit_reads_it(bench, tmp_path):
    """``ridge: 1e-8`` is a number, as jsonargparse reads it (PyYAML's safe loader reads a
    string)."""
    path = tmp_path / "c.yaml"
    path.write_text(_measured_with(
        "  select:\n    - operator: [{fit: stop_pi, n_widths: 5, ridge: 1e-8}]\n"))
    model = default_row._config_model(path)[0]
    assert model["select"][0]["operator"][0]["ridge"] == 1e-8


def test_leave_one_recording_out_needs_two_training_rows(bench, tmp_path):
    split = bench.DATASETS["mnzn_ferrite_largest"][1](bench.Files(FERRITE))
    path = tmp_path / "cv.yaml"
    path.write_text(_measured_with("  select:\n    - operator: null\n  select_cv: recording\n"))
    with pytest.raises(ValueError, match="select_cv='recording'.* 1 training row"):
        bench.default(split, bench.QUICK, path)


def _piezo_file(path: Path, n: int = 2001, rate: float = 200.0) -> tuple[np.ndarray, ...]:
    """A record in the published SmartHysteresis layout: ',time,displacement,voltage'."""
    t = np.arange(n) / rate
    volt = np.where(t >= 3.26, 150.0 * np.sin(2 * np.pi * (t - 3.26)), 0.0)
    disp = 0.12 * volt + 0.3 * np.sin(3.0 * t)
    rows = zip(t, volt, disp, strict=True)
    path.write_text("".join(f",{a:.17g},{c:.17g},{b:.17g}\n" for a, b, c in rows))
    return t, volt, disp


def test_piezo_record_is_split_in_time(bench, tmp_path):
    t, volt, disp = _piezo_file(tmp_path / "piezo.csv")
    cut, w = int(np.searchsorted(t, 7.0)), int(np.searchsorted(t, 3.3))
    comp = bench.piezo(tmp_path / "piezo.csv", compensator=True)
    # displacement -> voltage: one training row up to 7 s, states run to 3.3 s
    np.testing.assert_array_equal(comp.x.numpy(), disp[None, :cut])
    np.testing.assert_array_equal(comp.y.numpy(), volt[None, :cut])
    assert comp.warmup == w and t[w] >= 3.3 > t[w - 1]
    # the whole record is run from rest and scored from 7 s on
    (x, y, start), = comp.test
    np.testing.assert_array_equal(x.numpy(), disp)
    assert start == cut and t[cut] >= 7.0 > t[cut - 1]
    fwd = bench.piezo(tmp_path / "piezo.csv", compensator=False)
    np.testing.assert_array_equal(fwd.x.numpy(), volt[None, :cut])
    np.testing.assert_array_equal(fwd.test[0][1].numpy(), disp)


def test_sma_record_is_split_in_time(bench):
    """Temperature -> extension: four thermal cycles train (from the first cooling; the load
    ramp at the hot temperature before it only runs the states), the last three are held
    out, the whole record run from its start."""
    d = bench.read_csv(bench.REAL / "sma_isobaric_thermal_cycles.csv")
    temp, ext = d["chamber_temperature_C"], d["extension_mm"]
    assert len(temp) == 1176 and np.isfinite(temp).all() and np.isfinite(ext).all()
    split = bench.DATASETS["sma_actuator"][1](bench.Files())
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


def test_piezo_file_errors_name_the_option(bench, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,voltage\n0,1\n")
    with pytest.raises(ValueError, match="--piezo .*bad.csv"):
        bench.read_piezo(bad)
    short = tmp_path / "short.csv"
    _piezo_file(short, n=1000)  # 5 s: ends before the 7 s cut
    with pytest.raises(ValueError, match="must run past 7 s"):
        bench.piezo(short, compensator=True)


def test_jiles_atherton_row_on_b_h_records_only(bench):
    split = bench.DATASETS["mnzn_hp_ferrite"][1](bench.Files(FERRITE))
    assert split.magnetic and bench.shortened(split, stride=True).magnetic
    assert bench.tiled(split, total=2000).magnetic
    fitted = bench.jiles_atherton(split, bench.QUICK)
    rmse, n = bench.test_rmse(fitted.predict, split)
    poly, _ = bench.test_rmse(bench.poly(split, bench.QUICK).predict, split)
    assert n == 258 and rmse < poly  # five parameters beat the best polynomial
    # the hold-out RMSE is that of the same fit on the part before the hold-out
    cut = bench.holdout(split.x.shape[1], split.warmup)
    before = fit_jiles_atherton(split.x[:, :cut], split.y[:, :cut], warmup=split.warmup,
                                starts=bench.QUICK.ja_starts,
                                iterations=bench.QUICK.ja_iterations)
    with torch.no_grad():
        e = before(split.x)[0][:, cut:] - split.y[:, cut:]
    assert fitted.holdout == pytest.approx(float(e.square().mean().sqrt()), rel=1e-12)
    # held-out targets play no part in the fit
    spoiled = split._replace(test=[(x, 1e6 + 0 * y, w) for x, y, w in split.test])
    other = bench.jiles_atherton(spoiled, bench.QUICK)
    assert other.choice == fitted.choice
    assert not bench.DATASETS["mr_damper_0V"][1](bench.Files(FERRITE)).magnetic
    with pytest.raises(bench.NotApplicable, match="B -> H records only"):
        bench.jiles_atherton(bench.DATASETS["mr_damper_0V"][1](bench.Files(FERRITE)),
                             bench.QUICK)


@pytest.mark.parametrize("dataset, file", [
    ("friction_damper_sines", "friction_damper_backlash_brfd.csv"),
    ("friction_damper_36lb_sines", "friction_damper_backlash_brfd_36lb.csv")])
def test_friction_damper_sines_protocol(bench, dataset, file):
    """The 1 in sine tests train (one row, in order), the 0.5 in and 1.5 in ones are held
    out from rest: the file's rows, and the 1.5 in tests reach beyond the training range."""
    split = bench.DATASETS[dataset][1](bench.Files(FERRITE))
    d = bench.read_csv(ROOT / "examples/data/real" / file)
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


@pytest.mark.parametrize("dataset, bound", [("friction_damper", 0.6), ("friction_damper_sines",
                                                                       0.5)])
def test_stop_pi_row_predicts_the_friction_damper(bench, dataset, bound):
    """The stop-type PI row, fitted on sine tests, predicts held-out records (earthquakes,
    other amplitudes) well below a straight line (measured with the quick grid: 0.43 and
    0.29; every other family is at the line's level or above on the earthquakes); its settings come
    from the training part only: spoiling the held-out targets changes nothing."""
    split = bench.DATASETS[dataset][1](bench.Files(FERRITE))
    fitted = bench.stop_pi(split, bench.QUICK)
    rmse, _ = bench.test_rmse(fitted.predict, split)
    line, _ = bench.test_rmse(bench.line(split, bench.QUICK).predict, split)
    assert rmse < bound * line, (rmse, line, fitted.choice)
    spoiled = split._replace(test=[(x, 1e6 + 0 * y, w) for x, y, w in split.test])
    assert bench.stop_pi(spoiled, bench.QUICK).choice == fitted.choice


@pytest.mark.parametrize("seal", ["napn", "nap310", "pk", "kdn", "oring257", "xring257"])
def test_stop_pi_row_predicts_each_seals_other_pressures(bench, seal):
    """On each of the six other seals the stop-type PI row, fitted at 1 and 7 bar, predicts
    the friction at 3 and 5 bar well below a straight line (measured with the quick grid:
    0.23-0.38; the line and the best polynomial are within 0.2 % of each other there), its
    settings from the training part only."""
    split = bench.DATASETS[f"pneumatic_{seal}"][1](bench.Files())
    fitted = bench.stop_pi(split, bench.QUICK)
    rmse, _ = bench.test_rmse(fitted.predict, split)
    line, _ = bench.test_rmse(bench.line(split, bench.QUICK).predict, split)
    assert rmse < 0.45 * line, (rmse, line, fitted.choice)
    spoiled = split._replace(test=[(x, 1e6 + 0 * y, w) for x, y, w in split.test])
    assert bench.stop_pi(spoiled, bench.QUICK).choice == fitted.choice


def test_stop_pi_drift_row_follows_a_ratchet(bench):
    """A simulated plant, stops plus a drift of the accumulated input variation, fitted on
    its first cycles and scored on the later ones: the ``stop_pi_drift`` row follows the drift
    that the ``stop_pi`` row and the line cannot extrapolate (measured with the quick grid:
    RMSE 0.085 against 0.86 and 0.96); spoiling the held-out targets changes nothing."""
    t = torch.arange(1400, dtype=torch.float64)
    x = (torch.sin(2 * math.pi * t / 200) * torch.linspace(0.8, 1.0, 1400, dtype=torch.float64)
         + 0.1 * torch.sin(2 * math.pi * t / 37))
    stops = StopPrandtlIshlinskii(torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64),
                                  torch.tensor([[1.0], [0.6], [0.3]], dtype=torch.float64),
                                  linear_weight=0.5)
    drift = Drift(torch.tensor([6.0, 30.0], dtype=torch.float64),
                  torch.tensor([1.0, 2.0], dtype=torch.float64))
    with torch.no_grad():
        y = (stops(x[None])[0] + drift(x[None])[0])[0]
    split = bench.Split(x[None, :800], y[None, :800], 50, [(x, y, 800)])
    fitted = bench.stop_pi_drift(split, bench.QUICK)
    rmse = {name: bench.test_rmse(f.predict, split)[0] for name, f in (
        ("stop_pi_drift", fitted), ("stop_pi", bench.stop_pi(split, bench.QUICK)),
        ("line", bench.line(split, bench.QUICK)))}
    assert rmse["stop_pi_drift"] < 0.2 * min(rmse["stop_pi"], rmse["line"]), rmse
    spoiled = split._replace(test=[(x, 1e6 + 0 * y, w) for x, y, w in split.test])
    assert bench.stop_pi_drift(spoiled, bench.QUICK).choice == fitted.choice


def test_stop_pi_drift_row_on_the_sma_record(bench):
    """sma_actuator with the quick grid: the stops beside a drift predict cycles 5-7 at 0.43
    of the line's RMSE (measured), the stops alone at 0.61."""
    split = bench.DATASETS["sma_actuator"][1](bench.Files())
    rmse = {name: bench.test_rmse(getattr(bench, name)(split, bench.QUICK).predict, split)[0]
            for name in ("line", "stop_pi", "stop_pi_drift")}
    assert rmse["stop_pi_drift"] < 0.5 * rmse["line"], rmse
    assert rmse["stop_pi_drift"] < 0.8 * rmse["stop_pi"], rmse


def test_the_default_row_is_scored_within_the_exported_command_limits(bench, tmp_path):
    """Beyond the training input range the default row's prediction is the exported
    compensator's: saturated to the training target range (here a least-squares line, so the
    reference is numpy's line, clipped)."""
    t = np.linspace(0.0, 4.0 * np.pi, 400)
    x = np.sin(t)
    y = 2.0 * x + 0.5 + 0.05 * np.cos(3.0 * t)
    wide = 3.0 * np.sin(np.linspace(0.0, 2.0 * np.pi, 200))
    split = bench.Split(torch.tensor(x)[None], torch.tensor(y)[None], 0,
                        [(torch.tensor(wide), torch.tensor(2.0 * wide + 0.5), 0)])
    path = tmp_path / "line.yaml"
    path.write_text(_measured_with("  select:\n    - operator: null\n"))
    fitted = bench.default(split, bench.QUICK, path)
    with torch.no_grad():
        got = fitted.predict(torch.tensor(wide)[None])[0].numpy()
    slope, offset = np.polyfit(x, y, 1)
    want = np.clip(slope * wide + offset, y.min(), y.max())
    assert (np.abs(wide) > 1.5).any()  # the clip is exercised
    np.testing.assert_allclose(got, want, atol=1e-6)


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


def test_quad_runs_are_read_and_split_by_run(bench, tmp_path):
    rng = np.random.default_rng(0)
    runs = {}
    for r in bench.QUAD_RUNS:
        n = 61 if r == 3 else 10 + r
        # run 3 rises to 165 A in 11 samples, then falls (a later peak reads a little higher)
        current = np.concatenate([[0.0], np.linspace(16.5, 165.0, 10), [150.0, 165.04],
                                  rng.uniform(0, 165, n - 13)]) if r == 3 else \
            rng.uniform(0, 165, n)
        gradient = 0.0316 * current + 0.03 + 1e-4 * rng.standard_normal(n)
        _slac_run(tmp_path / f"strdat.ru{r}", r, current, gradient)
        runs[r] = np.round(current, 4), np.round(gradient, 6)
    np.testing.assert_array_equal(
        np.stack(bench.read_slac_run(tmp_path / "strdat.ru5")), np.stack(runs[5]))
    comp = bench.quad(tmp_path, compensator=True)
    # gradient -> current; the major loop trains, its first rise (11 samples) runs the states
    np.testing.assert_array_equal(comp.x.numpy(), runs[3][1][None])
    np.testing.assert_array_equal(comp.y.numpy(), runs[3][0][None])
    assert comp.warmup == 11
    assert len(comp.test) == len(bench.QUAD_RUNS) - 1
    for (x, y, w), r in zip(comp.test, bench.QUAD_RUNS[1:], strict=True):
        # each held-out run after the major loop's currents, scored on its own samples
        assert w == 61
        np.testing.assert_array_equal(x.numpy(), np.concatenate([runs[3][1], runs[r][1]]))
        np.testing.assert_array_equal(y[w:].numpy(), runs[r][0])
    fwd = bench.quad(tmp_path, compensator=False)
    np.testing.assert_array_equal(fwd.x.numpy(), runs[3][0][None])
    assert bench.Files(quad=tmp_path).missing("quad") == []
    (tmp_path / "strdat.ru8").unlink()  # a folder without every run is skipped
    assert bench.Files(quad=tmp_path).missing("quad") == [tmp_path / "strdat.ru8"]
    _slac_run(tmp_path / "strdat.ru8", 8, *runs[8])
    rows = bench.main(["--quick", "--data", "quad_magnet_forward", "--quad", str(tmp_path)])
    assert {r["n_train"] for r in rows} == {50}
    assert {r["n_test"] for r in rows if r["model"] != "jiles_atherton"} == {
        sum(len(runs[r][0]) for r in bench.QUAD_RUNS[1:])}


def test_a_quad_run_in_another_layout_is_refused(bench, tmp_path):
    (tmp_path / "strdat.ru3").write_text("current,gradient\n0,0.03\n16.5,0.55\n")
    with pytest.raises(ValueError, match=r"--quad .*strdat.ru3: no table"):
        bench.read_slac_run(tmp_path / "strdat.ru3")
    (tmp_path / "strdat.ru4").write_text(" ----+----\n 1.0 0.1 x\n")
    with pytest.raises(ValueError, match=r"--quad .*strdat.ru4: expected rows"):
        bench.read_slac_run(tmp_path / "strdat.ru4")


def test_the_default_holds_below_the_line_beyond_the_training_range(bench):
    """friction_damper_sines: a fifth to a third of the 1.5 in tests lie beyond the 1 in
    training range; the default, scored as exported (within the command limits), stays well
    below the line there (0.23x with the full grid, its stop-type candidate chosen)."""
    split = bench.DATASETS["friction_damper_sines"][1](bench.Files(FERRITE))
    lo, hi = float(split.x.min()), float(split.x.max())
    beyond = [float(((x < lo) | (x > hi)).double().mean()) for x, _, _ in split.test]
    assert max(beyond) > 0.2
    default = bench.test_rmse(bench.default(split, bench.QUICK).predict, split)[0]
    line = bench.test_rmse(bench.line(split, bench.QUICK).predict, split)[0]
    assert default < 0.8 * line


def test_the_default_follows_the_sma_records_drift(bench):
    """sma_actuator: fitted on cycles 1-4, the line predicts cycles 5-7 about 2 mm short on
    average (the extension ratchets up from cycle to cycle); the default's cross-validation
    chooses the 40 stops beside a drift of the accumulated temperature variation, which
    takes most of that offset (measured: mean error -0.50 mm, RMSE 0.52 of the line's;
    without the drift candidate it chose Preisach at 0.77, mean error about -1.9 mm)."""
    split = bench.DATASETS["sma_actuator"][1](bench.Files())
    fitted = bench.default(split, bench.QUICK)
    line = bench.line(split, bench.QUICK)
    assert "stop_pi+drift" in fitted.choice, fitted.choice
    x, y, start = split.test[0]
    errors = {name: (f.predict(x[None])[0] - y)[start:].detach()
              for name, f in (("default", fitted), ("line", line))}
    rmse = {k: float(e.square().mean().sqrt()) for k, e in errors.items()}
    assert rmse["default"] < 0.6 * rmse["line"], rmse
    assert rmse["default"] == pytest.approx(bench.test_rmse(fitted.predict, split)[0])
    assert -2.3 < float(errors["line"].mean()) < -1.5
    assert abs(float(errors["default"].mean())) < 1.0


@pytest.mark.slow
def test_the_default_inverts_a_preisach_model_on_the_ferrite_loops(bench):
    """mnzn_ferrite (trained on its smallest and largest loops, the middle ones held out):
    the default's cross-validation chooses the 40 stops beside the inverse of a graded
    Preisach model, which predict the held-out loops below half the error of the better
    memoryless baseline (measured: 0.352; on m130_steel it chooses the inverse generalized
    PI, 0.382)."""
    split = bench.DATASETS["mnzn_ferrite"][1](bench.Files(FERRITE))
    fitted = bench.default(split, bench.QUICK)
    assert "stop_pi+preisach(inverse)" in fitted.choice, fitted.choice
    rmse = bench.test_rmse(fitted.predict, split)[0]
    baseline = min(bench.test_rmse(bench.line(split, bench.QUICK).predict, split)[0],
                   bench.test_rmse(bench.poly(split, bench.QUICK).predict, split)[0])
    assert rmse < 0.45 * baseline, (rmse, baseline)


def test_micromanipulator_records_train_and_test(bench):
    """The piezo micromanipulator: the identification record (a 1 Hz sine over the full
    voltage range, 200 Hz) trains, the test record (loops of many amplitudes inside it) is held
    out, each whole and from its start, its first period only running the states; the
    compensator swaps input and target."""
    d = bench.read_csv(bench.REAL / "piezo_micromanipulator.csv")
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

    fwd = bench.DATASETS["piezo_manipulator_forward"][1](bench.Files())
    inv = bench.DATASETS["piezo_manipulator"][1](bench.Files())
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
    short = bench.DATASETS["piezo_manipulator_short"][1](bench.Files())
    # one period of warm-up and one scored, at 50 Hz (every 4th sample): 50 scored samples
    assert short.warmup == 50 and short.y[:, short.warmup:].numel() == 50
    np.testing.assert_array_equal(short.x.numpy(), disp[rec == 0][None, :400:4])
    np.testing.assert_array_equal(short.y.numpy(), v0[None, :400:4])
    assert len(short.test) == 1
    np.testing.assert_array_equal(short.test[0][0].numpy(), disp[rec == 1])
    assert short.test[0][2] == 200  # the held-out record stays at 200 Hz
    assert bench.DATASETS["piezo_manipulator"].needs is None  # shipped: no option
    assert bench.DATASETS["piezo_actuator_short"].needs == "piezo"


def test_seal_records_train_and_test(bench):
    """The six seals of the pneumatic cylinder: per seal, the 1 and 7 bar records train (cut
    to a common length), the 3 and 5 bar ones are held out, all from rest; the friction is
    the chamber pressure on the piston (its bore per seal) less the rod force. Checked against
    the columns read with the csv module and a friction computed here."""
    with open(bench.REAL / "pneumatic_cylinder_seals_friction.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    seals = list(dict.fromkeys(r["seal"] for r in rows))
    assert seals == list(bench.SEALS.values())
    recs: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        recs.setdefault((r["seal"], int(r["pressure_setpoint_bar"])), []).append(r)
    assert sorted({bar for _, bar in recs}) == [1, 3, 5, 7] and len(recs) == 24
    ids = [int(r["recording"]) for r in rows]
    assert ids == sorted(ids) and len(set(ids)) == 24  # one recording per seal and pressure

    for key, name in bench.SEALS.items():
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
        split = bench.DATASETS[f"pneumatic_{key}"][1](bench.Files())
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
        assert bench.DATASETS[f"pneumatic_{key}"].needs is None  # shipped: no option
    # the O-ring file's protocol is the same, its bore 25 mm
    oring = bench.DATASETS["pneumatic_oring"][1](bench.Files())
    d = bench.read_csv(bench.REAL / "pneumatic_cylinder_oring_friction.csv")
    one = d["recording"] == 0
    np.testing.assert_allclose(
        oring.y[0].numpy(), d["pressure_bar"][one] * 1e5 * math.pi * 0.0125**2
        - d["force_N"][one], rtol=0, atol=1e-9)


def test_reversal_curves_train_and_test(bench):
    """The FeCo nanowire FORCs: 152 curves, each a calibration point near positive saturation
    then a sweep up from its reversal field; the even-numbered curves train in one row in
    measurement order, the odd ones are held out from their calibration point. Checked against
    the file read with the csv module."""
    with open(bench.REAL / "feco_nanowires_forc.csv", newline="") as f:
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

    split = bench.DATASETS["feco_forc"][1](bench.Files())
    train = [p for i in range(0, 152, 2) for p in curves[i]]
    assert split.warmup == 1 and not split.magnetic
    np.testing.assert_array_equal(split.x[0].numpy(), [h for h, _ in train])
    np.testing.assert_array_equal(split.y[0].numpy(), [m for _, m in train])
    assert len(split.test) == 76
    for (x, y, w), i in zip(split.test, range(1, 152, 2), strict=True):
        assert w == 1
        np.testing.assert_array_equal(x.numpy(), [h for h, _ in curves[i]])
        np.testing.assert_array_equal(y.numpy(), [m for _, m in curves[i]])
    assert bench.DATASETS["feco_forc"].needs is None


def test_preisach_and_generalized_pi_rows_predict_held_out_reversal_curves(bench):
    """On the FORCs (each curve from saturation) a Preisach model fitted on the even curves
    predicts the odd ones better the finer its grid (measured: 0.66 of the better memoryless
    baseline with 8 levels, 0.19 with 30), and the generalized PI row with the quick budget is
    below half the baseline (measured 0.26); settings from the training part only."""
    split = bench.DATASETS["feco_forc"][1](bench.Files())
    baseline = min(bench.test_rmse(bench.line(split, bench.QUICK).predict, split)[0],
                   bench.test_rmse(bench.poly(split, bench.QUICK).predict, split)[0])
    coarse, fine = (bench.test_rmse(bench.preisach(split, bench.QUICK._replace(
        preisach_n=(n,))).predict, split)[0] / baseline for n in (8, 30))
    assert fine < 0.3 and fine < 0.5 * coarse, (coarse, fine)
    gpi = bench.generalized_pi(split, bench.QUICK)
    assert bench.test_rmse(gpi.predict, split)[0] < 0.4 * baseline, gpi.choice
