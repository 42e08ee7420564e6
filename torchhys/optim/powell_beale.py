"""Conjugate gradient with Powell-Beale restarts as a ``torch.optim.Optimizer``.

References:
    E. M. L. Beale, "A derivation of conjugate gradients", in Numerical Methods for
    Nonlinear Optimization, Academic Press, 1972.
    M. J. D. Powell, "Restart procedures for the conjugate gradient method", Mathematical
    Programming 12, 1977.
    C. Charalambous, "Conjugate gradient algorithm for efficient training of artificial
    neural networks", IEE Proceedings G 139(3), 1992.
    M. T. Hagan, H. B. Demuth and M. H. Beale, "Neural Network Design", chapter 12.
    J. Nocedal and S. J. Wright, "Numerical Optimization", 2nd ed., Springer, 2006, sec. 3.5.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from functools import partial
from typing import Any

import torch
from torch import Tensor

from torchhys.optim._options import check_options
from torchhys.optim.line_search import LineSearchFn, LineSearchResult, charalambous, strong_wolfe

__all__ = ["PowellBealeCG"]

_SEARCHES = {"charalambous": charalambous, "strong_wolfe": strong_wolfe}
_RESTART_REASONS = ("initial", "orthogonality", "n_iterations", "not_downhill", "failed_search")


def _dot(a: Tensor, b: Tensor) -> float:
    return float(torch.dot(a, b))


def _ratio(num: float, den: float) -> float:
    return num / den if den != 0.0 else 0.0


def _accepted(res: LineSearchResult, f0: float) -> bool:
    """A search result moves the parameters only with a positive step that lowers the loss."""
    return res.step > 0.0 and res.grad is not None and res.loss < f0


class PowellBealeCG(torch.optim.Optimizer):
    """Conjugate gradient with Powell-Beale restarts (``traincgb``) on one flat vector.

    All parameters are treated as one vector ``x`` of shape ``(n,)`` (as
    :class:`torch.optim.LBFGS` does); a parameter whose ``grad`` is ``None`` counts as a zero
    gradient. Iteration ``k`` with gradient ``g_k`` and ``y = g_k - g_{k-1}`` uses

    ``d_k = -g_k + Z1 d_{k-1} + Z2 d_t``, ``Z1 = g_k.y / d_{k-1}.y``, ``Z2 = g_k.y_t / d_t.y_t``

    (Beale's three-term recurrence; a coefficient with a zero denominator is 0). ``d_t`` is
    the direction computed at the last restart ``t`` and ``y_t = g_{t+1} - g_t``; ``Z2 = 0``
    at iterations ``t`` and ``t + 1``. A new cycle starts at iteration ``k`` (Powell, 1977)

    * when ``|g_{k-1}.g_k| >= orthogonality * ||g_k||^2`` (``"orthogonality"``), or
    * when ``k - t >= restart_every`` (default ``n``; ``"n_iterations"``);

    its first direction is ``d_k = -g_k + Z1 d_{k-1}``, which becomes ``d_t``. Any direction
    that is not sufficiently downhill, i.e. outside
    ``-1.2 ||g_k||^2 <= d_k.g_k <= -0.8 ||g_k||^2``, is replaced by ``-g_k``, which starts a
    new cycle (``"not_downhill"``). The very first direction is ``-g_0``.

    The step along ``d_k`` comes from a line search: ``"charalambous"`` (default, as
    ``traincgb``'s ``srchcha``), ``"strong_wolfe"``, or a callable
    ``search(phi, f0, s0, a1) -> LineSearchResult`` (see :mod:`torchhys.optim.line_search`;
    ``phi(a)`` evaluates the closure at ``x + a d`` and the result's ``grad`` must belong to
    ``x + step d``; a result that does not lower the loss is rejected).
    The first trial step of the first iteration is that of ``traincgb`` (whose directions
    have unit length): the larger of the parameter-space length ``delta`` and the minimizer
    ``2 f_0 / |d_0.g_0|`` of the quadratic with value ``f_0`` and slope ``d_0.g_0`` at ``0``
    and minimum value ``0``, i.e. ``max(delta / ||d_0||, 2 f_0 / |d_0.g_0|)``; only
    ``delta / ||d_0||`` counts when ``f_0 <= 0``. Later it is
    ``2 (f_{k-1} - f_k) / |d_k.g_k|`` (Nocedal and Wright, eq. 3.61), or the previous step
    when that is not positive and finite. ``traincgb`` also raises a later first trial to at
    least the previous step and ``delta``; that is left out here, since it makes the first
    trial overshoot and costs more evaluations per search.
    When a search along a conjugate direction finds no decrease, it is
    retried once along ``-g_k`` (``"failed_search"``); when that fails too the parameters
    are left unchanged, :attr:`stop_reason` says why and the next :meth:`step` starts afresh
    from steepest descent. The loss therefore never increases.

    Args:
        params: iterable of parameters (one parameter group), float32 or float64, all of
            one dtype and device.
        iterations_per_step: CG iterations done by each :meth:`step` call.
        line_search: ``"charalambous"``, ``"strong_wolfe"`` or a callable.
        alpha: sufficient-decrease constant, ``0 < alpha < beta``.
        beta: slope constant, ``alpha < beta < 1``.
        gamma: interpolation safeguard, ``0 < gamma < 0.5``.
        delta: parameter-space length ``a ||d||`` of the smallest first trial of the first
            iteration, positive.
        scale_tol: best step over the bracket width at which the Charalambous search stops,
            positive.
        minstep: smallest parameter-space step length ``a ||d||`` worth trying, ``>= 0``.
        max_evals: maximum loss evaluations per line search, ``>= 1``.
        tolerance_grad: stop (converged) when ``max |g| <= tolerance_grad``, ``>= 0``.
        restart_every: iterations per Beale cycle, ``None`` for ``n``.
        orthogonality: threshold of Powell's orthogonality test, positive.
        reuse_evaluation: when ``True``, a :meth:`step` that finds the parameters exactly as
            the previous one left them reuses the loss and gradient computed there instead of
            calling ``closure`` first, saving one evaluation per call (one per iteration with
            ``iterations_per_step=1``). Only valid when ``closure`` is a deterministic
            function of the parameters across calls (full batch, no dropout, unchanged data);
            Lightning's automatic optimization expects every ``step`` to call the closure.

    Attributes:
        stop_reason: why the last :meth:`step` call stopped early, or ``None``:
            ``"gradient_tolerance"``, ``"minimum_step"``, ``"no_decrease"``,
            ``"non_finite_loss"``.
        converged: ``True`` when the last stop was ``"gradient_tolerance"``.
        state: ``self.state[first_param]`` holds the flat tensors ``d``, ``prev_flat_grad``,
            ``d_t``, ``y_t`` (shape ``(n,)`` or ``None``), the counters ``n_iter``,
            ``func_evals``, ``since_restart``, a dict ``restarts`` counting restarts by
            reason, ``last_restart`` (reason at the last iteration or ``None``), the last
            step ``t`` and the losses ``prev_loss``, ``loss``; with ``reuse_evaluation`` also
            ``eval_params``, ``eval_loss``, ``eval_grad``: the flat parameters at the end of the
            last :meth:`step` that ended at a finite loss, and the loss and flat gradient there.

    Raises:
        ValueError: for an invalid option, more than one parameter group, or mixed dtypes.
        TypeError: for a non-float parameter or an unknown kind of ``line_search``.
    """

    def __init__(
        self,
        params: Iterable[Tensor] | Iterable[dict[str, Any]],
        *,
        iterations_per_step: int = 1,
        line_search: str | LineSearchFn = "charalambous",
        alpha: float = 1e-3,
        beta: float = 0.1,
        gamma: float = 0.1,
        delta: float = 0.01,
        scale_tol: float = 20.0,
        minstep: float = 1e-6,
        max_evals: int = 100,
        tolerance_grad: float = 1e-10,
        restart_every: int | None = None,
        orthogonality: float = 0.2,
        reuse_evaluation: bool = False,
    ) -> None:
        defaults = dict(
            iterations_per_step=iterations_per_step, line_search=line_search, alpha=alpha,
            beta=beta, gamma=gamma, delta=delta, scale_tol=scale_tol, minstep=minstep,
            max_evals=max_evals, tolerance_grad=tolerance_grad, restart_every=restart_every,
            orthogonality=orthogonality, reuse_evaluation=reuse_evaluation,
        )
        check_options(defaults, _SEARCHES)
        super().__init__(params, defaults)
        if len(self.param_groups) != 1:
            raise ValueError(
                "PowellBealeCG supports a single parameter group (like LBFGS); "
                f"got {len(self.param_groups)} groups"
            )
        self._params: list[Tensor] = self.param_groups[0]["params"]
        dtypes = {(p.dtype, p.device) for p in self._params}
        if any(not p.is_floating_point() for p in self._params):
            found = sorted(str(p.dtype) for p in self._params)
            raise TypeError(f"parameters must be floating point; got dtypes {found}")
        if len(dtypes) != 1:
            raise ValueError(f"parameters must share one dtype and device; got {dtypes}")
        self._numel = sum(p.numel() for p in self._params)

    # ----------------------------------------------------------------------------------
    @property
    def _state(self) -> dict[str, Any]:
        return self.state[self._params[0]]

    @property
    def stop_reason(self) -> str | None:
        return self._state.get("stop_reason")

    @property
    def converged(self) -> bool:
        return self._state.get("stop_reason") == "gradient_tolerance"

    def _flat_grad(self) -> Tensor:
        views = [
            torch.zeros(p.numel(), dtype=p.dtype, device=p.device)
            if p.grad is None else p.grad.reshape(-1)
            for p in self._params
        ]
        return torch.cat(views)

    def _flat_params(self) -> Tensor:
        return torch.cat([p.detach().reshape(-1) for p in self._params])

    def _set_params(self, x: Tensor) -> None:
        offset = 0
        for p in self._params:
            n = p.numel()
            p.copy_(x[offset : offset + n].view_as(p))
            offset += n

    # ----------------------------------------------------------------------------------
    def _restart(self, state: dict[str, Any], d: Tensor, reason: str) -> Tensor:
        state["d_t"], state["y_t"], state["since_restart"] = d, None, 0
        state["restarts"][reason] += 1
        state["last_restart"] = reason
        return d

    def _direction(self, state: dict[str, Any], g: Tensor) -> Tensor:
        """Next search direction, shape ``(n,)``; updates the cycle bookkeeping."""
        group = self.param_groups[0]
        d_prev, g_prev = state["d"], state["prev_flat_grad"]
        state["last_restart"] = None
        if d_prev is None:
            return self._restart(state, g.neg(), "initial")
        y = g - g_prev
        state["since_restart"] += 1
        if state["since_restart"] == 1:
            state["y_t"] = y
        gg = _dot(g, g)
        z1 = _ratio(_dot(g, y), _dot(d_prev, y))
        every = group["restart_every"] or self._numel
        reason = None
        if abs(_dot(g_prev, g)) >= group["orthogonality"] * gg:
            reason = "orthogonality"
        elif state["since_restart"] >= every:
            reason = "n_iterations"
        if reason is not None or state["since_restart"] == 1:
            d = g.neg().add_(d_prev, alpha=z1)
        else:
            d_t, y_t = state["d_t"], state["y_t"]
            z2 = _ratio(_dot(g, y_t), _dot(d_t, y_t))
            d = g.neg().add_(d_prev, alpha=z1).add_(d_t, alpha=z2)
        slope = _dot(d, g)
        if not -1.2 * gg <= slope <= -0.8 * gg:
            return self._restart(state, g.neg(), "not_downhill")
        return d if reason is None else self._restart(state, d, reason)

    def _search(
        self, closure: Callable[[], Tensor], x0: Tensor, d: Tensor, f0: float, g0: Tensor,
        a1: float,
    ) -> LineSearchResult:
        group = self.param_groups[0]

        def phi(a: float) -> tuple[float, float, Tensor]:
            self._set_params(torch.add(x0, d, alpha=a))
            f = float(closure().detach())
            g = self._flat_grad()
            return f, _dot(g, d), g

        search = group["line_search"]
        s0 = _dot(g0, d)
        if isinstance(search, str):
            kwargs = dict(alpha=group["alpha"], beta=group["beta"], gamma=group["gamma"],
                          max_evals=group["max_evals"],
                          min_step=group["minstep"] / float(torch.linalg.vector_norm(d)))
            if search == "charalambous":
                kwargs["scale_tol"] = group["scale_tol"]
            search = partial(_SEARCHES[search], **kwargs)
        return search(phi, f0, s0, a1)

    def _first_step(self, state: dict[str, Any], f: float, d: Tensor, s0: float) -> float:
        """First trial step along ``d`` (shape ``(n,)``) with slope ``s0 = g.d``."""
        if state["prev_loss"] is None:
            a1 = self.param_groups[0]["delta"] / float(torch.linalg.vector_norm(d))
            estimate = 2.0 * f / abs(s0)
            return max(a1, estimate) if math.isfinite(estimate) else a1
        a1 = 2.0 * (state["prev_loss"] - f) / abs(s0)
        return a1 if math.isfinite(a1) and a1 > 0.0 else state["t"]

    def _evaluate(self, closure: Callable[[], Tensor]) -> tuple[Tensor, float, Tensor]:
        """Loss tensor, loss and flat gradient ``(n,)`` at the current parameters."""
        state = self._state
        if self.param_groups[0]["reuse_evaluation"] and state.get("eval_params") is not None:
            if torch.equal(state["eval_params"], self._flat_params()):
                f = state["eval_loss"]
                return state["eval_grad"].new_tensor(f), f, state["eval_grad"]
        loss = closure()
        state["func_evals"] += 1
        return loss, float(loss.detach()), self._flat_grad()

    # ----------------------------------------------------------------------------------
    @torch.no_grad()
    def step(self, closure: Callable[[], Tensor] | None = None) -> Tensor:  # type: ignore[override]
        """Run ``iterations_per_step`` CG iterations.

        Args:
            closure: re-evaluates the model, calls ``backward`` and returns the loss
                (a scalar tensor). Called once at the start (unless ``reuse_evaluation``
                applies) and once per line-search trial.

        Returns:
            The loss at the parameters before the step (as returned by ``closure``, or the
            reused value as a tensor of the parameters' dtype).

        Raises:
            TypeError: when ``closure`` is missing or not callable.
        """
        if closure is None or not callable(closure):
            raise TypeError(
                f"PowellBealeCG.step needs a closure that returns the loss; got {closure!r}"
            )
        closure = torch.enable_grad()(closure)
        group, state = self.param_groups[0], self._state
        if "n_iter" not in state:
            state.update(d=None, prev_flat_grad=None, d_t=None, y_t=None, since_restart=0,
                         n_iter=0, func_evals=0, t=group["delta"], prev_loss=None, loss=None,
                         restarts=dict.fromkeys(_RESTART_REASONS, 0), last_restart=None)
        state["stop_reason"] = None
        orig_loss, f, g = self._evaluate(closure)
        if not (math.isfinite(f) and bool(torch.isfinite(g).all())):
            state["stop_reason"] = "non_finite_loss"
            return orig_loss
        for _ in range(group["iterations_per_step"]):
            if float(g.abs().max()) <= group["tolerance_grad"]:
                state["stop_reason"] = "gradient_tolerance"
                break
            x0 = self._flat_params()
            d = self._direction(state, g)
            res = self._search(closure, x0, d, f, g, self._first_step(state, f, d, _dot(g, d)))
            state["func_evals"] += res.evals
            if not _accepted(res, f) and state["last_restart"] not in ("initial", "not_downhill"):
                d = self._restart(state, g.neg(), "failed_search")
                res = self._search(closure, x0, d, f, g, self._first_step(state, f, d, _dot(g, d)))
                state["func_evals"] += res.evals
            if not _accepted(res, f):
                self._set_params(x0)
                reason = res.status if res.step == 0.0 else "no_decrease"
                state.update(stop_reason=reason, d=None, prev_flat_grad=None)
                break
            self._set_params(torch.add(x0, d, alpha=res.step))
            state.update(d=d, prev_flat_grad=g, t=res.step, prev_loss=f, loss=res.loss)
            state["n_iter"] += 1
            f, g = res.loss, res.grad
        if group["reuse_evaluation"]:  # f and g belong to the parameters as they are now
            state.update(eval_params=self._flat_params(), eval_loss=f, eval_grad=g)
        return orig_loss
