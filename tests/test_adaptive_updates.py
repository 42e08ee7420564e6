"""The recursive readout updates of torchhys.functional.adaptive against closed forms in
float64 numpy (ridge and exponentially weighted least squares), on a plant whose weights
change, and under the skip rules and bounds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from torchhys.functional.adaptive import nlms_update, rls_update

DT = torch.float64
INF = torch.tensor(float("inf"), dtype=DT)


def _data(n: int = 300, m: int = 4, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    z = np.column_stack([rng.standard_normal((n, m - 1)), np.ones(n)])
    t = z @ np.array([1.5, -2.0, 0.5, 0.3][:m]) + 0.05 * rng.standard_normal(n)
    return z, t


def _run_rls(z: np.ndarray, t: np.ndarray, w0: np.ndarray, delta: float, lam: float,
             **kw: float) -> tuple[torch.Tensor, torch.Tensor]:
    m = z.shape[1]
    w = torch.tensor(w0, dtype=DT)[None]
    P = torch.eye(m, dtype=DT)[None] / delta
    prev = torch.zeros(1, m, dtype=DT)  # not the first features: the first pair updates
    for zi, ti in zip(torch.tensor(z), torch.tensor(t), strict=True):
        w, P, _ = rls_update(w, P, zi[None], prev, ti[None], w_ref=torch.zeros(m, dtype=DT),
                             bound=INF, forgetting=lam, excitation=-1.0, **kw)
        prev = zi[None]
    return w[0], P[0]


def test_rls_without_forgetting_is_the_ridge_solution_around_the_start() -> None:
    z, t = _data()
    w0, delta = np.array([0.2, 0.1, -0.3, 1.0]), 0.5
    w, P = _run_rls(z, t, w0, delta, 1.0)
    A = z.T @ z + delta * np.eye(4)
    np.testing.assert_allclose(w.numpy(), np.linalg.solve(A, z.T @ t + delta * w0), atol=1e-10)
    np.testing.assert_allclose(P.numpy(), np.linalg.inv(A), atol=1e-12)


def test_rls_keeps_the_covariance_symmetric_bit_for_bit() -> None:
    """No symmetrization pass: the rank-one update is symmetric element for element."""
    z, t = _data(500, seed=7)
    _, P = _run_rls(z, t, np.zeros(4), 1e-3, 0.95)
    assert torch.equal(P, P.T)
    assert float(P.diagonal().min()) > 0.0


def test_rls_with_forgetting_is_exponentially_weighted_least_squares() -> None:
    z, t = _data(200)
    w0, delta, lam = np.zeros(4), 1.0, 0.97
    w, _ = _run_rls(z, t, w0, delta, lam)
    n = len(t)
    g = lam ** (n - 1 - np.arange(n))
    A = (z * g[:, None]).T @ z + delta * lam ** n * np.eye(4)
    want = np.linalg.solve(A, (z * g[:, None]).T @ t + delta * lam ** n * w0)
    np.testing.assert_allclose(w.numpy(), want, atol=1e-9)


def test_rls_follows_a_change_of_the_plants_weights() -> None:
    rng = np.random.default_rng(1)
    z = np.column_stack([rng.standard_normal((1200, 2)), np.ones(1200)])
    wa, wb = np.array([1.0, 2.0, 0.0]), np.array([1.4, 1.2, 0.5])
    t = np.concatenate([z[:600] @ wa, z[600:] @ wb])
    w, _ = _run_rls(z, t, np.zeros(3), 1e-2, 0.98)
    # the old weights' pairs weigh 0.98^600 ~ 5e-6 of the new ones' at the end
    np.testing.assert_allclose(w.numpy(), wb, atol=5e-5)
    assert float(np.abs(w.numpy() - wb).max()) < 1e-3 * float(np.abs(wa - wb).max())


def test_skipped_updates_keep_weights_and_covariance_bit_for_bit() -> None:
    m = 3
    w = torch.tensor([[1.0, 2.0, 3.0]] * 4, dtype=DT)
    P = torch.eye(m, dtype=DT).expand(4, m, m).clone()
    z = torch.tensor([[1.0, 0.5, 1.0], [1.0, 0.5, 1.0], [float("nan"), 0.5, 1.0],
                      [0.2, 0.1, 1.0]], dtype=DT)
    prev = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.5, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]],
                        dtype=DT)
    # row 0 updates; row 1: features unchanged; row 2: NaN feature; row 3: error 0.01, in
    # the dead zone
    t = torch.tensor([10.0, 10.0, 10.0, (z[3] * w[3]).sum() + 0.01], dtype=DT)
    w2, P2, ok = rls_update(w, P, z, prev, t, w_ref=w[0], bound=INF, forgetting=0.99,
                            dead_zone=0.05, excitation=1e-9)
    assert ok.tolist() == [True, False, False, False]
    assert torch.equal(w2[1:], w[1:]) and torch.equal(P2[1:], P[1:])
    assert not torch.equal(w2[0], w[0])
    w3, ok3 = nlms_update(w, z, prev, t, w_ref=w[0], bound=INF, dead_zone=0.05,
                          excitation=1e-9)
    assert ok3.tolist() == [True, False, False, False] and torch.equal(w3[1:], w[1:])
    tn = t.clone()
    tn[0] = float("inf")
    assert not bool(rls_update(w, P, z, prev, tn, w_ref=w[0], bound=INF)[2][0])


def test_the_box_and_the_trace_bound_hold_under_outliers() -> None:
    rng = np.random.default_rng(2)
    m = 3
    w_ref = torch.tensor([1.0, -1.0, 0.5], dtype=DT)
    bound = 0.5 * w_ref.abs()
    w, P = w_ref[None].clone(), torch.eye(m, dtype=DT)[None]
    prev = torch.zeros(1, m, dtype=DT)
    for k in range(3000):
        z = torch.tensor(rng.standard_normal((1, m)), dtype=DT)
        if k % 500 < 250:  # a still period: the features do not move
            z = prev.clone()
        t = (z * w_ref).sum(-1) * (1 + 10 * (k % 97 == 0))  # 10x outliers
        w, P, _ = rls_update(w, P, z, prev, t, w_ref=w_ref, bound=bound, forgetting=0.9,
                             trace_max=10.0, excitation=1e-12)
        prev = z
        assert bool(((w[0] - w_ref).abs() <= bound + 1e-15).all())
        assert float(torch.diagonal(P[0]).sum()) <= 10.0 * (1 + 1e-12)
        assert bool(torch.isfinite(P).all())


def test_nlms_converges_to_consistent_weights() -> None:
    rng = np.random.default_rng(3)
    z = np.column_stack([rng.standard_normal((4000, 2)), np.ones(4000)])
    wt = np.array([0.7, -1.3, 0.2])
    w = torch.zeros(1, 3, dtype=DT)
    prev = torch.zeros(1, 3, dtype=DT)
    for zi, ti in zip(torch.tensor(z), torch.tensor(z @ wt), strict=True):
        w, _ = nlms_update(w, zi[None], prev, ti[None], w_ref=torch.zeros(3, dtype=DT),
                           bound=INF, step=0.5, excitation=-1.0)
        prev = zi[None]
    np.testing.assert_allclose(w[0].numpy(), wt, atol=1e-8)


@pytest.mark.parametrize("fn", ["rls", "nlms"])
def test_the_updates_script(fn: str) -> None:
    z, t = _data(5)
    zt, tt = torch.tensor(z), torch.tensor(t)
    w = torch.zeros(5, 4, dtype=DT)
    prev = torch.zeros(5, 4, dtype=DT)
    ref = torch.zeros(4, dtype=DT)
    bound = torch.ones(4, dtype=DT)
    if fn == "rls":
        P = torch.eye(4, dtype=DT).expand(5, 4, 4).clone()
        eager = rls_update(w, P, zt, prev, tt, w_ref=ref, bound=bound, forgetting=0.99)
        scripted = torch.jit.script(rls_update)(w, P, zt, prev, tt, w_ref=ref, bound=bound,
                                                forgetting=0.99)
    else:
        eager = nlms_update(w, zt, prev, tt, w_ref=ref, bound=bound)
        scripted = torch.jit.script(nlms_update)(w, zt, prev, tt, w_ref=ref, bound=bound)
    for a, b in zip(eager, scripted, strict=True):
        assert torch.equal(a, b)
