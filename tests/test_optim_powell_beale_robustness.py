"""PowellBealeCG: non-finite trials, stop reasons, resume, dtypes, shapes and bad input."""

import io
import math

import pytest
import torch
from _optim_helpers import make

from torchhys.optim import LineSearchResult, PowellBealeCG


def rosenbrock(x):
    """Extended Rosenbrock (decoupled pairs, More-Garbow-Hillstrom)."""
    return (100.0 * (x[1::2] - x[::2] ** 2) ** 2 + (1.0 - x[::2]) ** 2).sum()




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


@pytest.mark.parametrize("reuse", [False, True])
def test_resume_from_state_dict_equals_uninterrupted_run(reuse):
    ref = _two_params()
    ref_opt = PowellBealeCG(ref, tolerance_grad=0.0, reuse_evaluation=reuse)
    _run(ref, ref_opt, 24)
    first = _two_params()
    opt = PowellBealeCG(first, tolerance_grad=0.0, reuse_evaluation=reuse)
    _run(first, opt, 11)
    buffer = io.BytesIO()
    torch.save({"params": [p.detach() for p in first], "opt": opt.state_dict()}, buffer)
    buffer.seek(0)
    saved = torch.load(buffer)
    resumed = [p.clone().requires_grad_(True) for p in saved["params"]]
    opt2 = PowellBealeCG(resumed, tolerance_grad=0.0, reuse_evaluation=reuse)
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


# --- reusing the evaluation at the end of the previous step ----------------------------
def _counted(params, **options):
    opt = PowellBealeCG(params, tolerance_grad=0.0, **options)
    calls = [0]

    def closure():
        calls[0] += 1
        opt.zero_grad()
        loss = _loss(params)
        loss.backward()
        return loss

    return opt, closure, calls


def test_reuse_makes_single_iteration_steps_cost_what_one_long_step_costs():
    long_params = _two_params()
    long_opt, closure, long_calls = _counted(long_params, iterations_per_step=12)
    long_opt.step(closure)
    for reuse, extra in [(True, 0), (False, 11)]:
        params = _two_params()
        opt, closure, calls = _counted(params, reuse_evaluation=reuse)
        ends = []
        for _ in range(12):
            returned = opt.step(closure)
            if ends:  # the loss before this step is the one the previous step ended at
                assert float(returned.detach()) == ends[-1]
            ends.append(opt.state[params[0]]["loss"])
        assert all(torch.equal(a, b) for a, b in zip(params, long_params, strict=True))
        assert calls[0] == long_calls[0] + extra == opt.state[params[0]]["func_evals"]


def test_reuse_evaluates_again_when_the_parameters_changed():
    params = _two_params()
    opt, closure, calls = _counted(params, reuse_evaluation=True)
    opt.step(closure)
    with torch.no_grad():
        params[1].add_(1e-3)
    expected = float(_loss(params).detach())
    before = calls[0]
    returned = opt.step(closure)
    assert float(returned.detach()) == expected
    assert calls[0] > before + 1  # the start was evaluated, then the line search ran


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
        (dict(reuse_evaluation=1), TypeError, "reuse_evaluation"),
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


def test_a_callable_search_that_raises_the_loss_is_rejected():
    def uphill(phi, f0, s0, a1):
        f, _, g = phi(-1.0)  # a step backwards: the loss grows
        return LineSearchResult(1.0, f, g, 1, "ok")

    x, opt, closure = make(lambda x: (x**2).sum(), torch.ones(2, dtype=torch.float64),
                           line_search=uphill)
    opt.step(closure)
    assert opt.stop_reason == "no_decrease"
    assert torch.equal(x.detach(), torch.ones(2, dtype=torch.float64))
