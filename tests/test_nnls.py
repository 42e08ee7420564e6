"""The active-set solver shared by the least-squares fits
(torchhys.identification._nnls.nnls_gram), cold
and warm-started, against scipy's bounded least squares in float64."""
from __future__ import annotations

import csv
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from torchhys import fit_stop_pi
from torchhys.identification._nnls import nnls_gram
from torchhys.identification.fitting import play_width_grid

SMA = (Path(__file__).resolve().parents[1] / "examples" / "data" / "real"
       / "sma_isobaric_thermal_cycles.csv")

optimize = pytest.importorskip("scipy.optimize")


def _problem(seed: int, rows: int = 60, m: int = 25, n_free: int = 2):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(rows, m, generator=g, dtype=torch.float64)
    A[:, :5] *= 100.0  # badly scaled columns: the solver scales them itself
    y = torch.randn(rows, generator=g, dtype=torch.float64)
    free = torch.zeros(m, dtype=torch.bool)
    free[m - n_free:] = True
    return A, y, free


def _reference(A: torch.Tensor, y: torch.Tensor, free: torch.Tensor) -> np.ndarray:
    lower = np.where(free.numpy(), -np.inf, 0.0)
    res = optimize.lsq_linear(A.numpy(), y.numpy(), bounds=(lower, np.inf), method="bvls",
                              tol=1e-14)
    return res.x


@pytest.mark.parametrize("seed", range(4))
def test_cold_start_matches_bounded_least_squares(seed: int) -> None:
    A, y, free = _problem(seed)
    w = nnls_gram(A.T @ A, A.T @ y, free)
    ref = _reference(A, y, free)
    assert (w[~free] >= 0).all()
    assert 0 < int((w[~free] == 0).sum()) < int((~free).sum())  # some bounds are active
    np.testing.assert_allclose(w.numpy(), ref, atol=1e-9 * np.abs(ref).max())


@pytest.mark.parametrize("start", ["solution", "other penalty", "negative", "all positive",
                                   "zeros"])
def test_warm_start_gives_the_same_solution(start: str) -> None:
    """Whatever its support, a warm start ends at the cold start's solution."""
    A, y, free = _problem(7)
    G, h = A.T @ A, A.T @ y
    cold = nnls_gram(G, h, free)
    g = torch.Generator().manual_seed(1)
    init = {
        "solution": cold,
        "other penalty": nnls_gram(G + 5.0 * torch.eye(G.shape[0], dtype=G.dtype), h, free),
        "negative": -torch.rand(h.shape, generator=g, dtype=torch.float64),
        "all positive": torch.rand(h.shape, generator=g, dtype=torch.float64),
        "zeros": torch.zeros_like(h),
    }[start]
    kept = init.clone()
    warm = nnls_gram(G, h, free, init)
    assert torch.equal(init, kept)  # not modified
    np.testing.assert_allclose(warm.numpy(), cold.numpy(), atol=1e-10 * float(cold.abs().max()))
    np.testing.assert_allclose(warm.numpy(), _reference(A, y, free),
                               atol=1e-9 * float(cold.abs().max()))


def test_warm_start_from_a_near_solution_takes_fewer_solves(monkeypatch) -> None:
    """Started from the solution of a slightly different penalty, the active set method
    solves the passive set's equations fewer times than from the free variables alone."""
    import torchhys.identification._nnls as nnls

    A, y, free = _problem(3, rows=200, m=80)
    G, h = A.T @ A, A.T @ y
    calls = []
    solve = nnls._passive_solve

    def counted(*args):
        calls.append(1)
        return solve(*args)

    monkeypatch.setattr(nnls, "_passive_solve", counted)
    near = nnls_gram(G + 1e-3 * torch.eye(80, dtype=G.dtype), h, free)
    calls.clear()
    cold = nnls_gram(G, h, free)
    n_cold = len(calls)
    calls.clear()
    warm = nnls_gram(G, h, free, near)
    assert len(calls) < n_cold / 2, (len(calls), n_cold)
    np.testing.assert_allclose(warm.numpy(), cold.numpy(), atol=1e-10 * float(cold.abs().max()))


def test_a_singular_passive_set_gets_the_minimum_norm_solution() -> None:
    """Two equal columns (a singular Gram matrix), both in the passive set from a warm
    start: the weight splits evenly between them (the minimum-norm solution), the same on
    every call, at the least squares' value."""
    g = torch.Generator().manual_seed(5)
    a, b = (torch.rand(40, generator=g, dtype=torch.float64) for _ in range(2))
    A = torch.stack([a, a, b, torch.ones(40, dtype=torch.float64)], 1)
    y = 3.0 * a + 0.5 * b + 0.01 * torch.randn(40, generator=g, dtype=torch.float64)
    free = torch.tensor([False, False, False, True])
    G, h = A.T @ A, A.T @ y
    runs = [nnls_gram(G, h, free, torch.ones(4, dtype=torch.float64)) for _ in range(5)]
    assert all(torch.equal(runs[0], r) for r in runs[1:])
    w = runs[0]
    assert float(w[0]) == pytest.approx(float(w[1]), rel=1e-9) and float(w[0]) > 0
    ref = _reference(A[:, 1:], y, free[1:])  # the same fit with one copy of the column
    np.testing.assert_allclose([float(w[0] + w[1]), *w[2:].tolist()], ref, rtol=1e-8,
                               atol=1e-10)


@pytest.mark.parametrize("power, segments, sign", [(1.0, 4, 1.0), (1.0, 4, -1.0),
                                                   (2.0, 8, -1.0)])
def test_a_singular_fit_ends_at_its_optimum_without_warning(power, segments, sign) -> None:
    """40 stops on the SMA record (temperature -> extension, both standardized), no
    penalty: the largest stops never slip, so their features are collinear and the Gram
    matrix is singular. Rounding made the active set cycle among supports at one objective
    until the iteration cap (a RuntimeWarning about non-convergence, on these three fits);
    the method now stops when its steps stop lowering the objective. The training RMSE is
    no worse than with a tiny ridge (a well-posed problem whose solution is feasible here)."""
    with open(SMA, newline="") as f:
        rows = list(csv.DictReader(f))
    x = torch.tensor([float(r["chamber_temperature_C"]) for r in rows], dtype=torch.float64)
    y = torch.tensor([float(r["extension_mm"]) for r in rows], dtype=torch.float64)
    x, y = ((v - v.mean()) / v.std() for v in (x, y))
    thresholds = play_width_grid(x[None], 40, power=power)

    def rmse(ridge: float) -> float:
        m = fit_stop_pi(x[None], sign * y[None], thresholds, segments=segments, ridge=ridge)
        with torch.no_grad():
            return float((m(x[None])[0][0] - sign * y).square().mean().sqrt())

    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        exact = rmse(0.0)
    assert exact <= rmse(1e-10) * (1 + 1e-9)
