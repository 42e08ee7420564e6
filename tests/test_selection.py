"""``torchhys.selection.select``: model selection on tensors, without Lightning, checked
against float64 numpy references of its folds and readouts."""

from __future__ import annotations

import csv
import math
import warnings

import numpy as np
import pytest
import torch

from torchhys.identification.specs import fit_data_dependent
from torchhys.selection import Selection, select, standard_error
from torchhys.selection.candidates import (
    build_candidate,
    candidate_spec,
    solve_readout,
    train_full_batch,
)
from torchhys.selection.folds import Batch, make_folds

LINE = {"operator": None}
STOPS = {"operator": [{"fit": "stop_pi", "n_widths": 8, "power": 2.0, "segments": 2}]}


def _record(T: int = 600, rows: int = 1, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """A backlash-like loop with noise: y lags x by a play of width 0.3, (rows, T)."""
    g = torch.Generator().manual_seed(seed)
    t = torch.linspace(0, 6 * math.pi, T, dtype=torch.float64)
    xs, ys = [], []
    for r in range(rows):
        x = (1 + 0.3 * r) * torch.sin(t) * (0.6 + 0.4 * torch.cos(t / 5))
        y = torch.empty_like(x)
        state = 0.0
        for i, v in enumerate(x.tolist()):
            state = min(max(state, v - 0.3), v + 0.3)
            y[i] = state
        xs.append(x)
        ys.append(y + 0.01 * torch.randn(T, generator=g, dtype=torch.float64))
    return torch.stack(xs), torch.stack(ys)


def _line_fold_errors(x: np.ndarray, y: np.ndarray, fit: np.ndarray, val: np.ndarray
                      ) -> np.ndarray:
    """Squared errors on ``val`` of the least-squares line fitted on ``fit`` (numpy)."""
    a = np.stack([x[fit], np.ones(fit.sum())], 1)
    c = np.linalg.lstsq(a, y[fit], rcond=None)[0]
    return (c[0] * x[val] + c[1] - y[val]) ** 2


def test_blocked_cv_of_the_line_equals_a_numpy_reference() -> None:
    x, y = _record()
    w, k = 50, 3
    result = select([LINE], x, y, warmup=w, cv=k, warn_coverage=False)
    xn, yn = x[0].numpy(), y[0].numpy()
    blocks = np.array_split(np.arange(w, x.shape[1]), k)
    errors, folds = [], []
    for j in range(k):
        fit = np.zeros(x.shape[1], bool)
        fit[w:] = True
        fit[blocks[j]] = False
        val = np.zeros_like(fit)
        val[blocks[j]] = True
        e = _line_fold_errors(xn, yn, fit, val)
        errors.append(e)
        folds.append(e.mean())
    pooled = np.concatenate(errors)
    score = result.scores[0]
    assert score.val_mse == pytest.approx(pooled.mean(), rel=1e-10)
    assert list(score.folds) == pytest.approx(folds, rel=1e-10)
    assert score.val_se == pytest.approx(standard_error(torch.from_numpy(pooled)), rel=1e-10)


def test_rolling_recording_and_holdout_folds_of_the_line_equal_numpy() -> None:
    x, y = _record(T=300, rows=3)
    xn, yn = x.numpy(), y.numpy()
    w = 20
    scored = np.zeros(x.shape, bool)
    scored[:, w:] = True
    # leave one recording out: fitted on the other rows' scored samples
    res = select([LINE], x, y, warmup=w, cv="recording", warn_coverage=False)
    ref = []
    for r in range(3):
        fit = scored.copy()
        fit[r] = False
        val = np.zeros_like(fit)
        val[r] = scored[r]
        ref.append(_line_fold_errors(xn, yn, fit, val))
    assert res.scores[0].val_mse == pytest.approx(np.concatenate(ref).mean(), rel=1e-10)
    # rolling recordings: row r + 1 on a fit of rows 0..r
    res = select([LINE], x, y, warmup=w, cv="recording", mode="rolling", warn_coverage=False)
    ref = []
    for r in range(2):
        fit = np.zeros_like(scored)
        fit[:r + 1] = scored[:r + 1]
        val = np.zeros_like(fit)
        val[r + 1] = scored[r + 1]
        ref.append(_line_fold_errors(xn, yn, fit, val))
    assert list(res.scores[0].folds) == pytest.approx([e.mean() for e in ref], rel=1e-10)
    # the hold-out: the last quarter of each row's scored samples, fitted on those before
    res = select([LINE], x[:1], y[:1], warmup=w, cv=None, warn_coverage=False)
    n = x.shape[1] - w
    cut = w + n - int(round(0.25 * n))
    fit = np.zeros(x.shape[1], bool)
    fit[w:cut] = True
    e = _line_fold_errors(xn[0], yn[0], fit, ~fit & (np.arange(x.shape[1]) >= cut))
    assert res.scores[0].val_mse == pytest.approx(e.mean(), rel=1e-10)
    assert res.scores[0].folds == ()


def test_the_fit_leaves_out_a_longer_warmup_the_padding_and_the_held_block() -> None:
    x = torch.randn(2, 40, dtype=torch.float64)
    mask = torch.zeros(2, 40, dtype=torch.bool)
    mask[0, 2:] = True
    mask[1, 3:30] = True  # row 1: a longer warm-up, padding after sample 30
    fold = make_folds(x, x, torch.tensor([2, 3]), mask, 2)[0]
    held = fold.val.mask
    assert bool(held[0, 2]) and bool(held[1, 3]) and not bool(held[:, 25:].any())
    want = torch.ones(2, 40, dtype=torch.bool)
    want[1, 2] = False  # the warm-up beyond the least one
    want[1, 30:] = False  # the padding
    want &= ~held
    assert torch.equal(fold.fit.mask, want) and fold.warmup == 2
    assert torch.equal(fold.train.mask, mask & ~held)


def test_the_solved_readout_is_what_lbfgs_training_converges_to() -> None:
    x, y = _record(T=400)
    spec = candidate_spec(None, STOPS)
    solved = select([STOPS], x, y, warmup=40, cv=2, warn_coverage=False).model
    # the same candidate, its readout trained by L-BFGS from its initialization instead
    trained, fitters = build_candidate(spec)
    fit_data_dependent(trained.operators, fitters, x, y, warmup=40)
    trained.fit_normalization(x, y)
    tight = {"max_iter": 200, "tolerance_grad": 1e-14, "tolerance_change": 1e-16}
    train_full_batch(trained, {**spec, "optimizer_kwargs": tight},
                     Batch(x, y, torch.arange(400)[None] >= 40), epochs=20)
    with torch.no_grad():
        a, b = solved(x)[0], trained(x)[0]
    assert (a - b).abs().max() < 1e-6 * y.abs().max()


def test_a_candidate_that_cannot_be_fitted_scores_nan_with_its_reason_and_is_not_chosen(
) -> None:
    x, _ = _record(T=300)
    y = 2 * x + 0.01 * torch.randn(x.shape, generator=torch.Generator().manual_seed(1),
                                   dtype=x.dtype)  # a line: no hysteresis model beats it
    bad = {"operator": [{"fit": "pi_nonneg", "n_widths": 5, "direction": "direct"}]}
    with pytest.warns(RuntimeWarning, match="candidate 0, fold 1 of 3 skipped"):
        result = select([bad, LINE], x, y, warmup=20, cv=3, warn_coverage=False)
    first = result.scores[0]
    assert math.isnan(first.val_mse) and math.isnan(first.folds[2])
    assert first.error.startswith("fold 1 of 3: FitError: pi_nonneg") and "(folds 2-3 not run)" \
        in first.error
    assert result.chosen.index == 1 and result.scores[1].error == ""
    with pytest.warns(RuntimeWarning), pytest.raises(ValueError, match="NaN"):
        select([bad], x, y, warmup=20, cv=3, warn_coverage=False)


def test_nan_in_a_scored_sample_is_one_error() -> None:
    x, y = _record(T=200)
    y[0, 150] = float("nan")
    with pytest.raises(ValueError, match="row 0, sample 150"):
        select([LINE], x, y, cv=2, warn_coverage=False)


def test_bad_options_are_one_line_errors_naming_them() -> None:
    x, y = _record(T=200)
    with pytest.raises(ValueError, match="'hiden': not a model argument"):
        select([{"hiden": 3}], x, y, warn_coverage=False)
    with pytest.raises(ValueError, match="rule"):
        select([LINE], x, y, rule="max", warn_coverage=False)
    with pytest.raises(ValueError, match="candidates is empty"):
        select([], x, y)
    with pytest.raises(TypeError, match="list of dicts"):
        select(LINE, x, y)
    with pytest.raises(ValueError, match="recording"):
        select([LINE], x, y, cv="recording", warn_coverage=False)
    with pytest.raises(ValueError, match="one shape"):
        select([LINE], x, y[:, :-1])
    with pytest.raises(ValueError, match="optimizer_kwargs"):
        select([{"optimizer": "adam"}], x, y, warn_coverage=False)


def test_recordings_ids_make_rows_padded_and_masked() -> None:
    x, y = _record(T=300, rows=2)
    flat_x = torch.cat([x[0], x[1, :200]])
    flat_y = torch.cat([y[0], y[1, :200]])
    ids = torch.cat([torch.zeros(300), torch.ones(200)]).long()
    got = select([LINE], flat_x, flat_y, recordings=ids, warmup=10, cv="recording",
                 warn_coverage=False)
    mask = torch.zeros(2, 300, dtype=torch.bool)
    mask[0, 10:] = True
    mask[1, 10:200] = True
    want = select([LINE], torch.stack([x[0], torch.cat([x[1, :200], x[1, 199:200].expand(100)])]),
                  torch.stack([y[0], torch.cat([y[1, :200], y[1, 199:200].expand(100)])]),
                  mask=mask, warmup=10, cv="recording", warn_coverage=False)
    assert got.scores[0].folds == want.scores[0].folds


def test_jobs_give_the_scores_of_one_process_and_progress_is_told(tmp_path) -> None:
    x, y = _record(T=300)
    seen: list = []

    class Told:
        def starts(self, candidate: int, fold: int | None) -> None:
            seen.append(("starts", candidate, fold))

        def scored(self, score) -> None:  # noqa: ANN001
            seen.append(("scored", score.index))

    one = select([LINE, STOPS], x, y, warmup=20, cv=2, progress=Told(), warn_coverage=False)
    assert ("starts", 1, 1) in seen and [s for s in seen if s[0] == "scored"] == [
        ("scored", 0), ("scored", 1)]
    if "fork" in __import__("multiprocessing").get_all_start_methods():
        two = select([LINE, STOPS], x, y, warmup=20, cv=2, jobs=2, warn_coverage=False)
        assert [s.val_mse for s in two.scores] == [s.val_mse for s in one.scores]
    path = one.write_csv(tmp_path / "selection.csv")
    rows = list(csv.DictReader(path.open()))
    assert [r["selected"] for r in rows] == [str(int(i == one.chosen.index)) for i in (0, 1)]
    assert "fold_2" in rows[0] and isinstance(one, Selection)
    assert "candidate" in one.table() and one.describe() == "2-fold blocked cross-validation"


def test_a_spent_budget_skips_the_later_candidates() -> None:
    x, y = _record(T=200)
    result = select([LINE, LINE], x, y, cv=2, budget_s=1e-9, warn_coverage=False)
    assert math.isnan(result.scores[1].val_mse) and "skipped" in result.scores[1].error
    assert result.chosen.index == 0


def test_solve_readout_matches_numpy_lstsq_on_two_features() -> None:
    x, y = _record(T=300)
    spec = candidate_spec(None, {"operator": [{"name": "backlash", "widths": [0.1, 0.3]}]})
    net, _ = build_candidate(spec)
    net.fit_normalization(x, y)
    mask = torch.arange(300)[None] >= 30
    solve_readout(net, Batch(x, y, mask))
    with torch.no_grad():
        feats = net.features(x)[0][mask].numpy()
    a = np.concatenate([feats, np.ones((feats.shape[0], 1))], 1)
    c = np.linalg.lstsq(a, y[mask].numpy(), rcond=None)[0]
    with torch.no_grad():
        got = net(x)[0][mask].numpy()
    assert np.abs(got - a @ c).max() < 1e-9


def test_the_training_pages_example_runs(tmp_path, monkeypatch) -> None:
    """docs/training.md's example of ``select`` runs as written on a record."""
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[1] / "docs" / "training.md").read_text()
    (code,) = [b for b in re.findall(r"```python\n(.*?)```", page, re.S)
               if "from torchhys.selection import select" in b]
    x, y = _record(T=600)
    monkeypatch.chdir(tmp_path)
    scope = {"x": x, "y": y, "response": x}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        exec(compile(code, "docs/training.md", "exec"), scope)  # noqa: S102
    assert scope["result"].chosen.index in (0, 1)
    assert scope["command"].shape == x.shape and (tmp_path / "selection.csv").is_file()


def test_the_holdout_cuts_each_row_at_its_own_last_quarter() -> None:
    x, y = _record(T=400, rows=2)
    mask = torch.ones(2, 400, dtype=torch.bool)
    mask[1, 100:] = False  # a short second recording, padded
    fold = make_folds(x, y, torch.tensor([0, 0]), mask, None)[0]
    assert int(fold.val.mask[0].sum()) == 100 and int(fold.val.mask[1].sum()) == 25
    assert int(fold.train.mask[0].sum()) == 300 and int(fold.train.mask[1].sum()) == 75
    assert not bool((fold.fit.mask & fold.val.mask).any())


def test_a_gap_in_the_mask_is_not_fitted_and_not_finite_there_is_fine() -> None:
    x, y = _record(T=400)
    mask = torch.ones(1, 400, dtype=torch.bool)
    mask[0, 200:220] = False  # samples that do not exist: their targets are not used
    y_gap = y.clone()
    y_gap[0, 200:220] = 1e6
    fold = make_folds(x, y_gap, torch.tensor([10]), mask & (torch.arange(400) >= 10), 2)[0]
    assert not bool(fold.fit.mask[0, 200:220].any()) and not bool(fold.train.mask[0, 200:220].any())
    a = select([LINE], x, y, mask=mask, warmup=10, cv=2, warn_coverage=False)
    b = select([LINE], x, y_gap, mask=mask, warmup=10, cv=2, warn_coverage=False)
    assert a.scores[0].val_mse == pytest.approx(b.scores[0].val_mse, rel=1e-12)


def test_record_options_that_do_not_fit_together_are_one_line_errors() -> None:
    x, y = _record(T=200)
    flat = x[0]
    ids = torch.zeros(200, dtype=torch.long)
    with pytest.raises(ValueError, match="recordings .* or mask"):
        select([LINE], flat, y[0], recordings=ids, mask=torch.ones(1, 200, dtype=torch.bool))
    with pytest.raises(ValueError, match=r"warmup must be an int or one per row \(1\), got 2"):
        select([LINE], x, y, warmup=[1, 2], warn_coverage=False)
    with pytest.raises(ValueError, match="warmup must be an int"):
        select([LINE], x, y, warmup=2.7, warn_coverage=False)
    with pytest.raises(ValueError, match="mode='rolling' needs cv"):
        select([LINE], x, y, cv=None, mode="rolling", warn_coverage=False)


def test_a_validation_record_of_its_own_equals_numpy() -> None:
    """``val=record(...)``: fitted on the whole training record, scored on the validation
    rows' own samples, each row running through its training part first (a time split):
    numpy's least-squares line on ``[w, cut)``, scored on ``[cut, T)``."""
    from torchhys.selection.run import record

    x, y = _record(T=400)
    w, cut = 20, 300
    val_mask = torch.zeros(1, 400, dtype=torch.bool)
    val_mask[0, cut:] = True
    res = select([LINE, STOPS], x[:, :cut], y[:, :cut], warmup=w, cv=None,
                 val=record(x, y, mask=val_mask), warn_coverage=False)
    xn, yn = x[0].numpy(), y[0].numpy()
    fit = np.zeros(400, bool)
    fit[w:cut] = True
    e = _line_fold_errors(xn, yn, fit, ~fit & (np.arange(400) >= cut))
    assert res.scores[0].val_mse == pytest.approx(e.mean(), rel=1e-10)
    assert res.scores[0].folds == () and res.describe() == "the validation split"
    assert res.scores[1].val_mse < res.scores[0].val_mse  # the loop beats the line
    with pytest.raises(ValueError, match=r"val .* needs cv=None and mode=None, got cv=4"):
        select([LINE], x[:, :cut], y[:, :cut], cv=4, val=record(x, y, mask=val_mask),
               warn_coverage=False)


@pytest.mark.skipif("fork" not in __import__("multiprocessing").get_all_start_methods(),
                    reason="select_jobs > 1 needs processes started by fork")
def test_a_validation_record_scored_in_processes_keeps_the_network_its_score_fitted(
        monkeypatch) -> None:
    """With ``val`` and ``jobs=2`` the chosen candidate's one fit comes back from the
    process that scored it: no second fit (``fit_record`` is never called), the network
    equals the one process's, and the scores are plain :class:`CandidateScore` s."""
    from torchhys.selection import run
    from torchhys.selection.run import record
    from torchhys.selection.scores import CandidateScore

    x, y = _record(T=400)
    val_mask = torch.zeros(1, 400, dtype=torch.bool)
    val_mask[0, 300:] = True
    args = dict(warmup=20, cv=None, val=record(x, y, mask=val_mask), warn_coverage=False)
    one = select([LINE, STOPS], x[:, :300], y[:, :300], **args)

    def refit(*a, **k):  # noqa: ANN002, ANN003
        raise AssertionError("the chosen candidate was fitted a second time")

    monkeypatch.setattr(run, "fit_record", refit)
    two = select([LINE, STOPS], x[:, :300], y[:, :300], jobs=2, **args)
    assert [s.val_mse for s in two.scores] == [s.val_mse for s in one.scores]
    assert all(type(s) is CandidateScore for s in two.scores) and two.chosen.index == 1
    want, got = one.model.state_dict(), two.model.state_dict()
    assert want.keys() == got.keys() and all(torch.equal(want[k], got[k]) for k in want)


def test_every_candidate_nan_names_each_reason() -> None:
    """When no candidate scores, the error names each candidate's reason (a family that
    cannot be fitted is not reported as a diverged training)."""
    from torchhys.selection.scores import CandidateScore, best

    scored = [CandidateScore(0, {}, math.nan, error="fold 1 of 4: FitError: pi_nonneg: no "
                             "better than a straight line"),
              CandidateScore(1, {}, math.nan, error="validation MSE nan: the training "
                             "diverged")]
    with pytest.raises(ValueError, match=r"candidate 0: fold 1 of 4: FitError: pi_nonneg.*"
                                         r"candidate 1: validation MSE nan"):
        best(scored)
