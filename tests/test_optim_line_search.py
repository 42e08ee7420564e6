"""Line searches of torchhys.optim: acceptance conditions, interpolation, non-finite trials."""

import math

import pytest
import torch

from torchhys.optim.line_search import charalambous, cubic_minimizer, strong_wolfe

SEARCHES = [charalambous, strong_wolfe]


def make_phi(fun, dfun):
    """phi(a) -> (loss, slope, grad) for a one-dimensional problem along d = 1."""
    calls = []

    def phi(a):
        calls.append(a)
        s = dfun(a)
        return fun(a), s, torch.tensor([s], dtype=torch.float64)

    return phi, calls


def test_cubic_minimizer_is_exact_for_a_cubic():
    f = lambda a: a**3 - 3.0 * a  # noqa: E731 - local minimum at a = 1
    df = lambda a: 3.0 * a**2 - 3.0  # noqa: E731
    assert cubic_minimizer(0.0, f(0.0), df(0.0), 3.0, f(3.0), df(3.0)) == pytest.approx(1.0)
    assert cubic_minimizer(3.0, f(3.0), df(3.0), 0.5, f(0.5), df(0.5)) == pytest.approx(1.0)


def test_cubic_minimizer_is_exact_for_a_quadratic():
    f = lambda a: (a - 2.5) ** 2  # noqa: E731
    df = lambda a: 2.0 * (a - 2.5)  # noqa: E731
    assert cubic_minimizer(0.0, f(0.0), df(0.0), 10.0, f(10.0), df(10.0)) == pytest.approx(2.5)


def test_cubic_minimizer_without_minimum_is_nan():
    assert math.isnan(cubic_minimizer(1.0, 0.0, 1.0, 1.0, 0.0, 1.0))
    f = lambda a: -(a**3) - a  # noqa: E731 - strictly decreasing
    df = lambda a: -3.0 * a**2 - 1.0  # noqa: E731
    assert math.isnan(cubic_minimizer(1.0, f(1.0), df(1.0), 2.0, f(2.0), df(2.0)))


@pytest.mark.parametrize("search", SEARCHES)
@pytest.mark.parametrize("a1", [1e-4, 0.3, 3.0, 1e3])
@pytest.mark.parametrize(
    "fun,dfun",
    [
        (lambda a: (a - 3.0) ** 2, lambda a: 2.0 * (a - 3.0)),
        (lambda a: math.exp(min(a, 700.0) - 2) - a, lambda a: math.exp(min(a, 700.0) - 2) - 1),
        (lambda a: (a - 1.0) ** 4 + 0.1 * a * a, lambda a: 4.0 * (a - 1.0) ** 3 + 0.2 * a),
    ],
)
def test_accepted_step_satisfies_both_conditions(search, a1, fun, dfun):
    phi, calls = make_phi(fun, dfun)
    f0, s0 = fun(0.0), dfun(0.0)
    res = search(phi, f0, s0, a1, alpha=1e-3, beta=0.1)
    assert res.status == "ok"
    assert res.evals == len(calls) <= 100
    assert res.loss == fun(res.step) < f0
    assert res.loss <= f0 + 1e-3 * res.step * s0
    assert abs(dfun(res.step)) <= 0.1 * abs(s0)
    assert res.grad.item() == dfun(res.step)


@pytest.mark.parametrize("search", SEARCHES)
@pytest.mark.parametrize("a1", [0.3, 2.0])
def test_tight_beta_gives_an_exact_step_on_a_quadratic(search, a1):
    phi, calls = make_phi(lambda a: 4.0 * (a - 0.7) ** 2, lambda a: 8.0 * (a - 0.7))
    res = search(phi, 4.0 * 0.49, -8.0 * 0.7, a1, alpha=1e-12, beta=1e-10)
    assert res.status == "ok"
    assert res.step == pytest.approx(0.7, abs=1e-12)
    assert len(calls) <= (2 if search is charalambous else 4)


@pytest.mark.parametrize("search", SEARCHES)
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_trial_points_shrink_the_step(search, bad):
    def fun(a):
        return (a - 1.0) ** 2 if a < 1.5 else bad

    def dfun(a):
        return 2.0 * (a - 1.0) if a < 1.5 else bad

    phi, calls = make_phi(fun, dfun)
    res = search(phi, 1.0, -2.0, 100.0, alpha=1e-3, beta=0.1)
    assert calls[0] == 100.0 and calls[1] < 100.0
    assert res.status == "ok" and res.step < 1.5
    assert math.isfinite(res.loss) and res.loss < 1.0


@pytest.mark.parametrize("search", SEARCHES)
def test_no_decrease_fails_without_moving(search):
    # A slope that claims descent while the loss only grows: no step can be accepted.
    phi, calls = make_phi(lambda a: a, lambda a: -1.0)
    res = search(phi, 0.0, -1.0, 1.0, min_step=1e-6)
    assert res.step == 0.0 and res.grad is None and res.loss == 0.0
    assert res.status == "minimum_step"
    assert res.evals == len(calls) < 100
    assert min(calls) < 1e-6 * 10


@pytest.mark.parametrize("search", SEARCHES)
def test_max_evals_without_decrease(search):
    phi, calls = make_phi(lambda a: a, lambda a: -1.0)
    res = search(phi, 0.0, -1.0, 1.0, min_step=0.0, max_evals=7)
    assert res.status == "no_decrease" and res.step == 0.0
    assert len(calls) == 7


def test_charalambous_stops_on_a_narrow_bracket_with_the_best_point():
    # A kink at a = 1: slopes never get small, the bracket shrinks around it.
    phi, calls = make_phi(lambda a: abs(a - 1.0) - 1.0, lambda a: math.copysign(1.0, a - 1.0))
    res = charalambous(phi, 0.0, -1.0, 0.3, scale_tol=20.0)
    assert res.status == "tolerance"
    assert res.loss < 0.0 and res.loss == abs(res.step - 1.0) - 1.0
    assert len(calls) < 100


@pytest.mark.parametrize("search", SEARCHES)
def test_a_first_trial_that_meets_both_conditions_is_accepted_at_once(search):
    # phi'(1.05) = 0.1 * phi'(0) / (-1): within beta = 0.1 of a zero slope, no interpolation.
    phi, calls = make_phi(lambda a: (a - 1.0) ** 2, lambda a: 2.0 * (a - 1.0))
    res = search(phi, 1.0, -2.0, 1.05, alpha=1e-3, beta=0.1)
    assert res.status == "ok" and res.evals == 1 and calls == [1.05]
    assert res.step == 1.05 and res.loss == pytest.approx(0.0025)
