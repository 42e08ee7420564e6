"""PowellBealeCG: convergence (quadratic termination, Rosenbrock) and the restart rules."""

import math

import pytest
import torch
from _optim_helpers import make

from torchhys.optim import LineSearchResult

REASONS = ("initial", "orthogonality", "n_iterations", "not_downhill", "failed_search")


def rosenbrock(x):
    """Extended Rosenbrock (decoupled pairs, More-Garbow-Hillstrom)."""
    return (100.0 * (x[1::2] - x[::2] ** 2) ** 2 + (1.0 - x[::2]) ** 2).sum()


def spd_quadratic(n, cond=50.0, seed=0, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    q, _ = torch.linalg.qr(torch.randn(n, n, generator=gen, dtype=dtype))
    eig = torch.logspace(0.0, math.log10(cond), n, dtype=dtype)
    a = q @ torch.diag(eig) @ q.T
    b = torch.randn(n, generator=gen, dtype=dtype)
    return 0.5 * (a + a.T), b




def exact_quadratic_search(phi, f0, s0, a1):
    """Exact line search for a quadratic: the slope is linear in the step."""
    _, s1, _ = phi(a1)
    step = -s0 * a1 / (s1 - s0)
    f, _, g = phi(step)
    return LineSearchResult(step, f, g, 2, "ok")


def craft_state(opt, x, d_prev, g_prev, since_restart):
    """Pretend a previous iteration left direction ``d_prev`` and gradient ``g_prev``."""
    opt.state[x].update(
        d=d_prev, prev_flat_grad=g_prev, d_t=d_prev.clone(), y_t=torch.zeros_like(d_prev),
        since_restart=since_restart, n_iter=1, func_evals=0, t=1.0, prev_loss=None,
        loss=None, restarts=dict.fromkeys(REASONS, 0), last_restart=None,
    )


def current_grad(fun, x):
    x = x.detach().clone().requires_grad_(True)
    fun(x).backward()
    return x.grad


# --- convergence -----------------------------------------------------------------------
@pytest.mark.parametrize("n", [2, 5, 12])
def test_quadratic_terminates_in_n_iterations_with_exact_search(n):
    a, b = spd_quadratic(n)
    fun = lambda x: 0.5 * x @ a @ x - b @ x  # noqa: E731
    x, opt, closure = make(fun, torch.zeros(n, dtype=torch.float64),
                           line_search=exact_quadratic_search, tolerance_grad=0.0)
    for _ in range(n):
        opt.step(closure)
    assert sum(opt.state[x]["restarts"].values()) == 1  # only the initial steepest descent
    torch.testing.assert_close(x.detach(), torch.linalg.solve(a, b), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("n", [4, 9])
def test_quadratic_terminates_after_a_restart_from_a_non_steepest_direction(n):
    a, b = spd_quadratic(n, seed=n)
    fun = lambda x: 0.5 * x @ a @ x - b @ x  # noqa: E731
    x0 = torch.randn(n, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    x, opt, closure = make(fun, x0, line_search=exact_quadratic_search, tolerance_grad=0.0,
                           orthogonality=1e30)
    g = current_grad(fun, x0)
    gen = torch.Generator().manual_seed(2)
    d_prev = torch.randn(n, dtype=torch.float64, generator=gen)
    d_prev -= (d_prev @ g) / (g @ g) * g  # so that -g + Z1 d_prev is downhill
    g_prev = g - torch.randn(n, dtype=torch.float64, generator=gen)
    craft_state(opt, x, d_prev, g_prev, since_restart=n - 1)
    opt.step(closure)
    state = opt.state[x]
    assert state["last_restart"] == "n_iterations"
    d_t = state["d_t"]
    assert abs(d_t @ g) / (d_t.norm() * g.norm()) < 0.99  # not steepest descent
    for _ in range(n - 1):
        opt.step(closure)
    assert state["restarts"]["n_iterations"] == 1 and state["restarts"]["not_downhill"] == 0
    torch.testing.assert_close(x.detach(), torch.linalg.solve(a, b), rtol=1e-8, atol=1e-8)


@pytest.mark.parametrize("search", ["charalambous", "strong_wolfe"])
def test_quadratic_terminates_with_tight_builtin_searches(search):
    n = 8
    a, b = spd_quadratic(n, cond=20.0)
    fun = lambda x: 0.5 * x @ a @ x - b @ x  # noqa: E731
    x, opt, closure = make(fun, torch.zeros(n, dtype=torch.float64), line_search=search,
                           alpha=1e-12, beta=1e-9, scale_tol=1e12, tolerance_grad=0.0,
                           iterations_per_step=n)
    opt.step(closure)
    assert opt.state[x]["n_iter"] == n
    torch.testing.assert_close(x.detach(), torch.linalg.solve(a, b), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("search", ["charalambous", "strong_wolfe"])
def test_extended_rosenbrock_to_1e_8(search):
    x0 = torch.tensor([-1.2, 1.0] * 5, dtype=torch.float64)
    x, opt, closure = make(rosenbrock, x0, line_search=search, iterations_per_step=200,
                           tolerance_grad=1e-9)
    opt.step(closure)
    assert float(rosenbrock(x.detach())) < 1e-8
    # Near the minimum the step a ||d|| falls below minstep = 1e-6 before max |g| <= 1e-9.
    assert opt.stop_reason in ("gradient_tolerance", "minimum_step")
    assert opt.state[x]["n_iter"] < 100


def test_loss_never_increases():
    x0 = torch.tensor([-1.2, 1.0] * 3, dtype=torch.float64)
    x, opt, closure = make(rosenbrock, x0, tolerance_grad=0.0)
    losses = [float(opt.step(closure).detach()) for _ in range(60)]
    assert all(b <= a for a, b in zip(losses, losses[1:], strict=False))
    assert losses[-1] < 1e-10


# --- restart rules ---------------------------------------------------------------------
def _one_crafted_step(d_prev_fn, g_prev_fn, since_restart=0, **options):
    x0 = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    fun = lambda x: (torch.tensor([1.0, 3.0, 7.0], dtype=x.dtype) * x**2).sum()  # noqa: E731
    g = current_grad(fun, x0)
    x, opt, closure = make(fun, x0, **options)
    craft_state(opt, x, d_prev_fn(g), g_prev_fn(g), since_restart)
    opt.step(closure)
    return opt.state[x], g


def _orthogonal_to(g):
    w = torch.tensor([1.0, 1.0, 1.0], dtype=g.dtype)
    return w - (w @ g) / (g @ g) * g


# d_prev orthogonal to g keeps -g + Z1 d_prev inside Powell's downhill window.
def test_orthogonality_rule_fires_for_parallel_gradients():
    state, g = _one_crafted_step(_orthogonal_to, lambda g: 0.5 * g + _orthogonal_to(g))
    assert state["last_restart"] == "orthogonality"
    assert state["restarts"]["orthogonality"] == 1


def test_n_iterations_rule_fires_after_n_iterations():
    # g_prev orthogonal to g: Powell's orthogonality test stays silent.
    state, _ = _one_crafted_step(_orthogonal_to, _orthogonal_to, since_restart=2)
    assert state["last_restart"] == "n_iterations"  # n = 3 parameters


def test_n_iterations_rule_counts_cycle_length():
    n = 10
    a, b = spd_quadratic(n)
    fun = lambda x: 0.5 * x @ a @ x - b @ x  # noqa: E731
    x, opt, closure = make(fun, torch.zeros(n, dtype=torch.float64),
                           line_search=exact_quadratic_search, restart_every=3)
    for _ in range(7):
        opt.step(closure)
    restarts = opt.state[x]["restarts"]
    assert restarts["n_iterations"] == 2 and restarts["orthogonality"] == 0


def test_not_downhill_rule_replaces_the_direction_by_steepest_descent():
    # d_prev = g and Z1 = 1 make -g + Z1 d_prev = 0, which is not downhill.
    state, g = _one_crafted_step(lambda g: g.clone(), lambda g: -_orthogonal_to(g))
    assert state["last_restart"] == "not_downhill"
    torch.testing.assert_close(state["d"], -g)


def test_failed_conjugate_search_retries_along_steepest_descent():
    state, g = _one_crafted_step(_orthogonal_to, _orthogonal_to, max_evals=1, delta=1e6)
    assert state["restarts"]["failed_search"] == 1


# --- first trial step ------------------------------------------------------------------
def _first_trials(fun, x0, iterations=1, **options):
    trials = []

    def recording(phi, f0, s0, a1):
        trials.append((a1, f0, s0))
        return exact_quadratic_search(phi, f0, s0, a1)

    x, opt, closure = make(fun, x0, line_search=recording, tolerance_grad=0.0, **options)
    for _ in range(iterations):
        opt.step(closure)
    return trials


@pytest.mark.parametrize("offset,delta", [(0.0, 0.01), (0.0, 50.0), (-100.0, 0.01)])
def test_first_trial_of_the_first_iteration_follows_traincgb(offset, delta):
    a, b = spd_quadratic(5)
    fun = lambda x: 0.5 * x @ a @ x - b @ x + 0.5 * b @ torch.linalg.solve(a, b) + offset  # noqa: E731
    x0 = torch.ones(5, dtype=torch.float64)
    (a1, f0, s0), = _first_trials(fun, x0, delta=delta)
    g_norm = current_grad(fun, x0).norm().item()
    assert s0 == pytest.approx(-(g_norm**2))
    # delta is a length along the unit direction; 2 f0 / |s0| reaches a loss of 0 on a
    # quadratic model and does not count when f0 <= 0.
    expected = max(delta / g_norm, 2.0 * f0 / abs(s0)) if f0 > 0 else delta / g_norm
    assert a1 == pytest.approx(expected, rel=1e-12)
    assert (f0 > 0) == (offset == 0.0)


def test_later_first_trials_assume_the_previous_decrease():
    a, b = spd_quadratic(6)
    fun = lambda x: 0.5 * x @ a @ x - b @ x  # noqa: E731
    trials = _first_trials(fun, torch.ones(6, dtype=torch.float64), iterations=4)
    for (_, f_prev, _), (a1, f, s0) in zip(trials, trials[1:], strict=False):
        assert a1 == pytest.approx(2.0 * (f_prev - f) / abs(s0), rel=1e-12)
