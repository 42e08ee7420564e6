"""Training dynamic models on one long record: windows side by side with carried states.

A model here maps a force sequence to a displacement sequence with a carried state
(``model(u, state) -> (y, state)``, ``state=None`` at rest) and has ``fs`` and
``state_size``. A free-run simulation of a long record needs one step per sample, so
:func:`fit_windows` cuts the record into K windows of W samples and runs them as a batch of
K rows: one loop of W steps per iteration. Window j starts from the state in which window
j - 1 ended at the previous iteration (detached): the windows form one free run of the record,
consistent once the parameters settle. The carried states are refreshed from a full free run
at every validation.

Layout (T samples, the last ``validation`` held out; sample 0 is the rest state)::

    sample  0 | 1 ........ W | W+1 ...... 2W | ... | (K-1)W+1 .. KW | (unused) | validation
    state  s0 -> window 0 ->  s1 -> window 1 -> ... -> window K-1

The validation RMSE is that of the free run of the whole record from rest, on its last
``validation`` samples; the model with the lowest one is kept (early stopping).
"""

from __future__ import annotations

import copy
import math
import time
from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor, nn

from torchhys._checks import check_choice, check_finite, check_floating, check_int, check_tensor
from torchhys.models._common import check_fs

__all__ = ["WindowFit", "check_record", "fit_windows", "simulate"]

_REJECTED = 1e6  # the loss of an unstable trial point (the scaled MSE is of order 1 or less)


class WindowFit(NamedTuple):
    """Outcome of :func:`fit_windows`."""

    val_rmse: float
    """Validation RMSE of the kept model (free run from rest), in y's unit."""
    iterations: int
    """Optimizer steps taken."""
    seconds: float
    """Wall-clock time."""
    history: list[tuple[int, float, float]]
    """(iteration, train-window RMSE, validation RMSE) at every validation."""


def check_record(model: nn.Module, u: Tensor, y: Tensor | None = None, *, fs: float) -> None:
    """Check a record against a model: 1-D floating tensors of one length, finite, sampled at
    the model's ``fs``.

    Raises:
        TypeError: a non-tensor or non-floating u or y.
        ValueError: shapes, NaN or inf (the first index), ``fs`` not the model's.
    """
    fs = check_fs(fs, "fs")
    for name, x in (("u", u), ("y", y)):
        if x is None:
            continue
        check_floating(check_tensor(x, name), name)
        if x.dim() != 1 or x.shape[0] < 2:
            raise ValueError(f"{name} must have shape (time,) with time >= 2, got shape "
                             f"{tuple(x.shape)}")
        check_finite(x, name)
    if y is not None and y.shape != u.shape:
        raise ValueError(f"y must have the shape of u {tuple(u.shape)}, got shape "
                         f"{tuple(y.shape)}")
    if not math.isclose(fs, model.fs, rel_tol=1e-9):
        raise ValueError(f"fs = {fs} Hz (the data's sampling frequency) differs from the "
                         f"model's fs = {model.fs} Hz: a discrete-time model is tied to its "
                         "sampling; build the model with the data's fs")


@torch.no_grad()
def simulate(model: nn.Module, u: Tensor, *, fs: float, periods: int = 1) -> Tensor:
    """Free-run simulation from rest: y (time,) for u (time,).

    ``periods > 1`` treats u as one period of a periodic input: the model runs ``periods``
    periods and the last one is returned (the periodic steady state).
    """
    check_record(model, u, fs=fs)
    check_int(periods, "periods", minimum=1)
    y, state = model(u.unsqueeze(0), None)
    for _ in range(periods - 1):
        y, state = model(u.unsqueeze(0), state)
    return y[0]


def _window_starts(model: nn.Module, u: Tensor, K: int, W: int) -> tuple[Tensor, Tensor]:
    """A free run from rest over ``u``: the states entering the K windows and the output
    (NaN from where the run stopped being finite)."""
    with torch.no_grad():
        y0, s = model(u[:1].unsqueeze(0), None)
        starts, ys = [], [y0[0]]
        bounds = [1 + j * W for j in range(K + 1)]
        if bounds[-1] < u.shape[0]:
            bounds.append(u.shape[0])
        for j, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            if j < K:
                starts.append(s[0])
            if not bool(torch.isfinite(s).all()):  # an unstable model: no further run
                ys.append(u.new_full((b - a,), math.nan))
                continue
            yj, s = model(u[a:b].unsqueeze(0), s)
            ys.append(yj[0])
    return torch.stack(starts), torch.cat(ys)


def fit_windows(model: nn.Module, u: Tensor, y: Tensor, *, fs: float, window: int,
                iterations: int, validation: int = 0, lr: float = 1e-3,
                optimizer: str = "adam", eval_every: int = 50, time_limit: float | None = None,
                log: Callable[[str], None] | None = None) -> WindowFit:
    """Fit ``model`` to one record by windows with carried states (module docstring).

    Args:
        model: ``model(u (batch, time), state) -> (y, state)``, with ``fs`` and ``state_size``.
        u, y: the record, (time,), float64.
        fs: the record's sampling frequency (Hz); must be the model's.
        window: samples per window W (the truncation of the gradient through time).
        iterations: optimizer steps (Adam steps, or L-BFGS steps of up to 10 evaluations).
        validation: the last samples held out for early stopping (0: none, keep the last).
        lr: learning rate (Adam: cosine-annealed from lr to lr / 100).
        optimizer: ``"adam"`` or ``"lbfgs"``.
        eval_every: iterations between validations (a free run of the whole record).
        time_limit: stop after this many seconds (checked at validations).
        log: called with one line per validation.

    Returns:
        :class:`WindowFit`; the model holds the kept parameters.

    Raises:
        ValueError: bad record (:func:`check_record`), a window longer than the training part.
    """
    check_record(model, u, y, fs=fs)
    check_int(validation, "validation", minimum=0)
    check_int(iterations, "iterations", minimum=0)
    check_int(eval_every, "eval_every", minimum=1)
    check_choice(optimizer, "optimizer", ("adam", "lbfgs"))
    n_train = u.shape[0] - validation
    if n_train < 2:
        raise ValueError(f"validation = {validation} leaves {n_train} training samples of "
                         f"the record's {u.shape[0]}")
    if isinstance(window, bool) or not isinstance(window, int) or not 1 <= window < n_train:
        raise ValueError(f"window must be an int in [1, {n_train - 1}] (the training part of "
                         f"the record has {n_train} samples, the first is the rest state), "
                         f"got {window!r}")
    W, K = window, (n_train - 1) // window
    scale = float(y[:n_train].std())
    U = u[1: 1 + K * W].reshape(K, W)
    Y = y[1: 1 + K * W].reshape(K, W)
    params = [p for p in model.parameters() if p.requires_grad]
    if optimizer == "adam":
        opt: torch.optim.Optimizer = torch.optim.Adam(params, lr=lr)
        sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(iterations, 1), lr / 100)
    else:
        opt = torch.optim.LBFGS(params, lr=lr, max_iter=10, history_size=30,
                                line_search_fn="strong_wolfe")
    start = time.perf_counter()
    best: tuple[float, dict[str, Tensor] | None] = (math.inf, None)
    history: list[tuple[int, float, float]] = []
    starts = finals = None
    last = math.nan

    def validate(it: int) -> bool:
        nonlocal starts, best
        new_starts, y_free = _window_starts(model, u, K, W)
        part = slice(n_train, None) if validation else slice(0, n_train)
        val = float((y_free[part] - y[part]).square().mean().sqrt())
        if bool(torch.isfinite(new_starts).all()) or starts is None:
            starts = new_starts
        if not math.isfinite(val):
            val = math.inf
        history.append((it, last, val))
        if val < best[0] or best[1] is None:
            best = (val, copy.deepcopy(model.state_dict()))
        if log is not None:
            log(f"  it {it:5d}  window rmse {last:.4g}  validation rmse {val:.4g}  "
                f"{time.perf_counter() - start:.0f} s")
        return time_limit is not None and time.perf_counter() - start > time_limit

    def closure() -> Tensor:
        nonlocal finals
        opt.zero_grad()
        y_hat, out = model(U, starts)
        loss = ((y_hat - Y) / scale).square().mean()
        if not bool(torch.isfinite(loss) and torch.isfinite(out).all()):  # unstable:
            return loss.detach().new_tensor(_REJECTED)  # a large loss (inf makes L-BFGS NaN)
        loss.backward()
        finals = out
        return loss

    stop = validate(0)
    it = 0
    while it < iterations and not stop:
        loss = opt.step(closure)
        if optimizer == "adam":
            sched.step()
        it += 1
        last = math.sqrt(float(loss.detach())) * scale
        if not math.isfinite(last):  # Adam stepped into an unstable model: keep the best
            break
        with torch.no_grad():
            first = model(u[:1].unsqueeze(0), None)[1]
            starts = torch.cat([first, finals[:-1].detach()])
        if it % eval_every == 0 or it == iterations:
            stop = validate(it)
    if best[1] is not None:
        model.load_state_dict(best[1])
    return WindowFit(best[0], it, time.perf_counter() - start, history)
