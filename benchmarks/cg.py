"""Benchmark: PowellBealeCG against scipy's CG, torch's LBFGS and Adam.

Counts loss-and-gradient evaluations (and wall time, the median of a few repeats) until the
first evaluated point whose loss falls below a target, on

* the extended Rosenbrock function (decoupled pairs, More-Garbow-Hillstrom) with n = 10
  and n = 100, start (-1.2, 1, -1.2, 1, ...), target f < 1e-8;
* the chained Rosenbrock function (``scipy.optimize.rosen``) with n = 10, same start and
  target;
* a small MLP regression (1-20-20-1, tanh, 200 samples of sin(3x) + x / 2, float64) from
  three seeded initialisations, target mean squared error < 1e-4.

Every method evaluates the same torch function through one counting closure: each call
counts once, including the evaluation at the start of each ``PowellBealeCG.step`` and scipy's
evaluation at the starting point (the count equals scipy's ``nfev``). A run stops at the
target or after ``BUDGET`` evaluations. PowellBealeCG runs with ``iterations_per_step=50``
and, as a training loop calls it, with one iteration per ``step`` (with and without
``reuse_evaluation``). scipy is optional: its rows are skipped with a message when it is not
installed. Prints a markdown table; ``--starts K`` then prints, for PowellBealeCG's default
and scipy's CG, the evaluations from K further starts per problem family (MLP
initialisations 3, 4, ...; Rosenbrock starts perturbed by seeded N(0, 0.5^2) noise).

Usage: ``python benchmarks/cg.py [--repeats 3] [--starts 0]``
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from torchhys.optim import PowellBealeCG

BUDGET = 20_000
Objective = Callable[[list[torch.Tensor]], torch.Tensor]


class _Reached(Exception):
    """Raised inside an evaluation whose loss is below the target."""


@dataclass
class Problem:
    name: str
    make_params: Callable[[], list[torch.Tensor]]
    loss: Objective
    target: float
    adam_lr: float


@dataclass
class Outcome:
    evals: int
    iterations: int
    final: float
    reached: bool


class Counter:
    """Wraps the objective: counts evaluations and stops at the target."""

    def __init__(self, problem: Problem, params: list[torch.Tensor]) -> None:
        self.problem, self.params, self.evals, self.best = problem, params, 0, float("inf")

    def __call__(self) -> torch.Tensor:
        if self.evals >= BUDGET:
            raise _Reached
        for p in self.params:
            p.grad = None
        with torch.enable_grad():
            loss = self.problem.loss(self.params)
            loss.backward()
        self.evals += 1
        value = float(loss.detach())
        self.best = min(self.best, value)
        if value < self.problem.target:
            raise _Reached
        return loss


def extended_rosenbrock(params: list[torch.Tensor]) -> torch.Tensor:
    x = params[0]
    return (100.0 * (x[1::2] - x[::2] ** 2) ** 2 + (1.0 - x[::2]) ** 2).sum()


def chained_rosenbrock(params: list[torch.Tensor]) -> torch.Tensor:
    x = params[0]
    return (100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2).sum()


def rosenbrock_start(n: int) -> Callable[[], list[torch.Tensor]]:
    return lambda: [torch.tensor([-1.2, 1.0] * (n // 2), dtype=torch.float64).requires_grad_()]


_X = torch.linspace(-1.0, 1.0, 200, dtype=torch.float64).unsqueeze(1)
_Y = torch.sin(3.0 * _X) + 0.5 * _X
_SHAPES = [(20, 1), (20,), (20, 20), (20,), (1, 20), (1,)]


def mlp_start(seed: int) -> Callable[[], list[torch.Tensor]]:
    gen = torch.Generator().manual_seed(seed)
    init = [torch.randn(s, generator=gen, dtype=torch.float64) / s[-1] ** 0.5 for s in _SHAPES]
    return lambda: [w.clone().requires_grad_() for w in init]


def mlp_loss(params: list[torch.Tensor]) -> torch.Tensor:
    w1, b1, w2, b2, w3, b3 = params
    h = torch.tanh(_X @ w1.T + b1)
    h = torch.tanh(h @ w2.T + b2)
    return ((h @ w3.T + b3 - _Y) ** 2).mean()


PROBLEMS = [
    Problem("ext. Rosenbrock n=10", rosenbrock_start(10), extended_rosenbrock, 1e-8, 1e-2),
    Problem("ext. Rosenbrock n=100", rosenbrock_start(100), extended_rosenbrock, 1e-8, 1e-2),
    Problem("chained Rosenbrock n=10", rosenbrock_start(10), chained_rosenbrock, 1e-8, 1e-2),
] + [
    Problem(f"MLP 1-20-20-1 regression, init {seed}", mlp_start(seed), mlp_loss, 1e-4, 1e-2)
    for seed in range(3)
]


def run_powell_beale(problem: Problem, line_search: str, iterations_per_step: int = 50,
                     reuse: bool = False) -> Outcome:
    params = problem.make_params()
    opt = PowellBealeCG(params, iterations_per_step=iterations_per_step,
                        line_search=line_search, reuse_evaluation=reuse)
    counter = Counter(problem, params)
    try:
        while opt.stop_reason is None:
            opt.step(counter)
    except _Reached:
        pass
    state = opt.state[params[0]]
    return Outcome(counter.evals, state["n_iter"], counter.best, counter.best < problem.target)


def run_lbfgs(problem: Problem) -> Outcome:
    params = problem.make_params()
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=BUDGET, max_eval=2 * BUDGET,
                            tolerance_grad=0.0, tolerance_change=0.0, history_size=10,
                            line_search_fn="strong_wolfe")
    counter = Counter(problem, params)
    try:
        opt.step(counter)
    except _Reached:
        pass
    iters = opt.state[params[0]].get("n_iter", 0)
    return Outcome(counter.evals, iters, counter.best, counter.best < problem.target)


def run_adam(problem: Problem) -> Outcome:
    params = problem.make_params()
    opt = torch.optim.Adam(params, lr=problem.adam_lr)
    counter = Counter(problem, params)
    iters = 0
    try:
        while True:
            counter()
            opt.step()
            iters += 1
    except _Reached:
        pass
    return Outcome(counter.evals, iters, counter.best, counter.best < problem.target)


def run_scipy_cg(problem: Problem) -> Outcome:
    import numpy as np
    from scipy.optimize import minimize

    params = problem.make_params()
    counter = Counter(problem, params)
    sizes = [p.numel() for p in params]
    iters = [0]

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        with torch.no_grad():
            for p, chunk in zip(params, np.split(x, np.cumsum(sizes)[:-1]), strict=True):
                p.copy_(torch.from_numpy(chunk).view_as(p))
        loss = counter()
        grad = torch.cat([p.grad.reshape(-1) for p in params])
        return float(loss.detach()), grad.numpy().copy()

    def callback(_: np.ndarray) -> None:
        iters[0] += 1

    x0 = torch.cat([p.detach().reshape(-1) for p in params]).numpy().copy()
    try:
        minimize(fun, x0, jac=True, method="CG", callback=callback,
                 options={"gtol": 0.0, "maxiter": BUDGET})
    except _Reached:
        pass
    return Outcome(counter.evals, iters[0], counter.best, counter.best < problem.target)


METHODS: dict[str, Callable[[Problem], Outcome]] = {
    "PowellBealeCG (charalambous)": lambda p: run_powell_beale(p, "charalambous"),
    "PowellBealeCG (charalambous), 1 iteration/step": lambda p: run_powell_beale(
        p, "charalambous", 1),
    "PowellBealeCG (charalambous), 1 iteration/step, reuse": lambda p: run_powell_beale(
        p, "charalambous", 1, True),
    "PowellBealeCG (strong_wolfe)": lambda p: run_powell_beale(p, "strong_wolfe"),
    "scipy CG": run_scipy_cg,
    "torch LBFGS (strong_wolfe)": run_lbfgs,
    "torch Adam": run_adam,
}


def perturbed_rosenbrock_start(n: int, seed: int) -> Callable[[], list[torch.Tensor]]:
    gen = torch.Generator().manual_seed(seed)
    x0 = rosenbrock_start(n)()[0].detach()
    x0 = x0 + 0.5 * torch.randn(n, generator=gen, dtype=torch.float64)
    return lambda: [x0.clone().requires_grad_()]


def further_starts(k: int) -> dict[str, list[Problem]]:
    """K further starts per problem family, none of them among ``PROBLEMS``."""
    families: dict[str, list[Problem]] = {}
    for name, n, loss in [("ext. Rosenbrock n=10", 10, extended_rosenbrock),
                          ("ext. Rosenbrock n=100", 100, extended_rosenbrock),
                          ("chained Rosenbrock n=10", 10, chained_rosenbrock)]:
        families[name] = [Problem(name, perturbed_rosenbrock_start(n, s), loss, 1e-8, 1e-2)
                          for s in range(k)]
    families["MLP 1-20-20-1 regression"] = [
        Problem("MLP", mlp_start(s), mlp_loss, 1e-4, 1e-2) for s in range(3, 3 + k)
    ]
    return families


def print_starts(k: int) -> None:
    """Evaluations of PowellBealeCG's default and scipy's CG from further starts; the
    evaluation counts are compared over the starts from which both reach the target."""
    print(f"\n| family ({k} further starts) | reached (ours / scipy) | evals, median (ours / "
          "scipy) | ours <= scipy | median ratio ours / scipy |")
    print("|---|---:|---:|---:|---:|")
    for name, problems in further_starts(k).items():
        ours = [run_powell_beale(p, "charalambous") for p in problems]
        theirs = [run_scipy_cg(p) for p in problems]
        pairs = [(a.evals, b.evals) for a, b in zip(ours, theirs, strict=True)
                 if a.reached and b.reached]
        if not pairs:
            continue
        print(f"| {name} | {sum(o.reached for o in ours)} / {sum(o.reached for o in theirs)} | "
              f"{statistics.median(a for a, _ in pairs):g} / "
              f"{statistics.median(b for _, b in pairs):g} | "
              f"{sum(a <= b for a, b in pairs)}/{len(pairs)} | "
              f"{statistics.median(a / b for a, b in pairs):.2f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--starts", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    try:
        import scipy  # noqa: F401
    except ImportError:
        print("scipy is not installed: skipping the scipy CG rows")
        METHODS.pop("scipy CG")
    print("| problem | method | evals | iterations | seconds (median) | final f | reached |")
    print("|---|---|---:|---:|---:|---:|---|")
    for problem in PROBLEMS:
        for name, method in METHODS.items():
            outcome, times = method(problem), []  # the first run warms up and is not timed
            for _ in range(args.repeats):
                start = time.perf_counter()
                outcome = method(problem)
                times.append(time.perf_counter() - start)
            print(f"| {problem.name} | {name} | {outcome.evals} | {outcome.iterations} | "
                  f"{statistics.median(times):.3f} | {outcome.final:.2e} | "
                  f"{'yes' if outcome.reached else 'no'} |", flush=True)
    if args.starts > 0 and "scipy CG" in METHODS:
        print_starts(args.starts)


if __name__ == "__main__":
    main()
