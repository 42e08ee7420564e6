"""PowellBealeCG: convergence, restart rules, robustness, resume, dtypes and bad input."""

import io
import math

import pytest
import torch

from torchhys.optim import LineSearchResult, PowellBealeCG

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


def make(fun, x0, **options):
    x = x0.clone().requires_grad_(True)
    opt = PowellBealeCG([x], **options)

    def closure():
        opt.zero_grad()
        loss = fun(x)
        loss.backward()
        return loss

    return x, opt, closure


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


# --- robustness ------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [math.nan, math.inf])
@pytest.mark.parametrize("search", ["charalambous", "strong_wolfe"])
def test_non_finite_trial_points_do_not_poison_the_parameters(bad, search):
    def fun(x):
        loss = ((x - 0.5) ** 2).sum()
        return torch.where(x.norm() < 1.0, loss, torch.full_like(loss, bad))

    x, opt, closure = make(fun, torch.tensor([0.1, -0.2], dtype=torch.float64), delta=100.0,
                           line_search=search)
    for _ in range(5):
        opt.step(closure)
        assert torch.isfinite(x).all() and x.norm() < 1.0
    assert float(fun(x.detach())) < 1e-20


def test_no_decrease_leaves_parameters_unchanged():
    x = torch.tensor([1.0, 2.0], dtype=torch.float64, requires_grad=True)
    before = x.detach().clone()
    opt = PowellBealeCG([x])

    def closure():  # the gradient claims descent along -x, the loss grows in every direction
        opt.zero_grad()
        x.grad = before.clone()
        return (x.detach() - before).norm()

    opt.step(closure)
    assert torch.equal(x.detach(), before)
    assert opt.stop_reason in ("minimum_step", "no_decrease") and not opt.converged


def test_gradient_tolerance_stops_at_a_minimum():
    x, opt, closure = make(lambda x: ((x - 1.0) ** 2).sum(), torch.ones(3, dtype=torch.float64))
    opt.step(closure)
    assert opt.converged and opt.stop_reason == "gradient_tolerance"
    assert torch.equal(x.detach(), torch.ones(3, dtype=torch.float64))


def test_non_finite_starting_loss_is_reported():
    x, opt, closure = make(lambda x: (x * math.nan).sum(), torch.ones(2, dtype=torch.float64))
    opt.step(closure)
    assert opt.stop_reason == "non_finite_loss"
    assert torch.equal(x.detach(), torch.ones(2, dtype=torch.float64))


# --- resume, dtypes, several parameters ------------------------------------------------
def _two_params(dtype=torch.float64):
    w = torch.tensor([[-1.2, 1.0], [-1.2, 1.0]], dtype=dtype, requires_grad=True)
    v = torch.tensor([-1.2, 1.0], dtype=dtype, requires_grad=True)
    return [w, v]


def _loss(params):
    return rosenbrock(torch.cat([p.reshape(-1) for p in params]))


def _run(params, opt, steps):
    def closure():
        opt.zero_grad()
        loss = _loss(params)
        loss.backward()
        return loss

    for _ in range(steps):
        opt.step(closure)


def test_resume_from_state_dict_equals_uninterrupted_run():
    ref = _two_params()
    ref_opt = PowellBealeCG(ref, tolerance_grad=0.0)
    _run(ref, ref_opt, 24)
    first = _two_params()
    opt = PowellBealeCG(first, tolerance_grad=0.0)
    _run(first, opt, 11)
    buffer = io.BytesIO()
    torch.save({"params": [p.detach() for p in first], "opt": opt.state_dict()}, buffer)
    buffer.seek(0)
    saved = torch.load(buffer)
    resumed = [p.clone().requires_grad_(True) for p in saved["params"]]
    opt2 = PowellBealeCG(resumed, tolerance_grad=0.0)
    opt2.load_state_dict(saved["opt"])
    _run(resumed, opt2, 13)
    for a, b in zip(ref, resumed, strict=True):
        assert torch.equal(a, b)
    assert opt2.state[resumed[0]]["func_evals"] == ref_opt.state[ref[0]]["func_evals"]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_float32_and_float64(dtype):
    params = _two_params(dtype)
    opt = PowellBealeCG(params, iterations_per_step=100)
    _run(params, opt, 1)
    assert all(p.dtype == dtype for p in params)
    assert opt.state[params[0]]["d_t"].dtype == dtype
    assert float(_loss(params).detach()) < (1e-6 if dtype == torch.float32 else 1e-10)


def test_several_shapes_follow_the_flat_trajectory():
    params = [torch.tensor([[-1.2, 1.0, -1.2]], dtype=torch.float64, requires_grad=True),
              torch.tensor(1.0, dtype=torch.float64, requires_grad=True)]
    opt = PowellBealeCG(params, tolerance_grad=0.0)
    _run(params, opt, 15)
    x, flat_opt, closure = make(rosenbrock, torch.tensor([-1.2, 1.0, -1.2, 1.0],
                                                         dtype=torch.float64),
                                tolerance_grad=0.0)
    for _ in range(15):
        flat_opt.step(closure)
    torch.testing.assert_close(torch.cat([p.detach().reshape(-1) for p in params]), x.detach(),
                               rtol=1e-12, atol=1e-12)


def test_parameter_without_grad_counts_as_zero_gradient():
    x = torch.tensor([3.0, -1.0], dtype=torch.float64, requires_grad=True)
    unused = torch.tensor([5.0], dtype=torch.float64, requires_grad=True)
    opt = PowellBealeCG([x, unused], iterations_per_step=10)

    def closure():
        opt.zero_grad(set_to_none=True)
        loss = (x**2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    assert unused.grad is None and float(unused.detach()) == 5.0
    assert float((x.detach() ** 2).sum()) < 1e-12


# --- bad input -------------------------------------------------------------------------
@pytest.mark.parametrize(
    "options,error,match",
    [
        (dict(delta=-0.01), ValueError, "delta"),
        (dict(alpha=0.2, beta=0.1), ValueError, "beta"),
        (dict(alpha=0.1, beta=0.1), ValueError, "beta"),
        (dict(alpha=0.0), ValueError, "alpha"),
        (dict(gamma=0.7), ValueError, "gamma"),
        (dict(minstep=-1.0), ValueError, "minstep"),
        (dict(scale_tol=0.0), ValueError, "scale_tol"),
        (dict(tolerance_grad=-1e-3), ValueError, "tolerance_grad"),
        (dict(max_evals=0), ValueError, "max_evals"),
        (dict(iterations_per_step=1.5), TypeError, "iterations_per_step"),
        (dict(restart_every=0), ValueError, "restart_every"),
        (dict(line_search="armijo"), ValueError, "charalambous"),
        (dict(line_search=3), TypeError, "line_search"),
        (dict(alpha="small"), TypeError, "alpha"),
    ],
)
def test_bad_options_raise(options, error, match):
    with pytest.raises(error, match=match):
        PowellBealeCG([torch.zeros(2, requires_grad=True)], **options)


def test_several_param_groups_raise():
    groups = [{"params": [torch.zeros(2, requires_grad=True)]},
              {"params": [torch.zeros(3, requires_grad=True)]}]
    with pytest.raises(ValueError, match="single parameter group.*got 2"):
        PowellBealeCG(groups)


def test_bad_parameters_raise():
    with pytest.raises(TypeError, match="floating point"):
        PowellBealeCG([torch.zeros(2, dtype=torch.int64)])
    with pytest.raises(ValueError, match="one dtype"):
        PowellBealeCG([torch.zeros(2, requires_grad=True),
                       torch.zeros(2, dtype=torch.float64, requires_grad=True)])


def test_missing_closure_raises():
    opt = PowellBealeCG([torch.zeros(2, requires_grad=True)])
    with pytest.raises(TypeError, match="closure.*None"):
        opt.step()
