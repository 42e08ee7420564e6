"""The rows of the hysteresis model families: each fitted on the scaled training part, its
settings chosen on the hold-out inside it (the package's docstring says each row's grid)."""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import numpy as np
import torch
from torch import Tensor

from torchhys import (
    EIHO,
    Backlash,
    Drift,
    InverseHysteresisNet,
    JilesAtherton,
    fit_generalized_pi,
    fit_jiles_atherton,
    fit_preisach,
    fit_stop_pi,
    select_penalty,
    select_stop_pi_ridge,
)
from torchhys.identification import specs  # noqa: F401 (loads the families into FAMILIES)
from torchhys.identification._family_spec import PENALTIES
from torchhys.identification.fitting import fit_prandtl_ishlinskii, play_width_grid, select_pi_ridge
from torchhys.registry import FAMILIES

from .datasets import F64, Split
from .scoring import Budget, Fitted, NotApplicable, Scaled, _rmse, holdout, scaled

RIDGES = PENALTIES
"""The ridge grid of every row: the config families' ``"auto"`` grid."""
SMOOTHNESS = (0.0, 1e-8, 1e-6, 1e-4, 1e-2)


Choice = tuple[float, int, float, float]
"""(hold-out RMSE, number of widths, grid power, ridge); n = 0: no candidate."""


def _rising(d: Scaled, end: int) -> float:
    """+1 if the target rises with the input on the scored samples before ``end``, else -1."""
    xs, ys = d.x[:, d.warmup:end], d.y[:, d.warmup:end]
    return 1.0 if float(((xs - xs.mean()) * ys).sum()) >= 0 else -1.0


def _pi_choice(d: Scaled, budget: Budget, nonnegative: bool, sign: float = 1.0) -> Choice:
    """The best PI model of ``sign`` x target from the input (ridge by ``select_pi_ridge``)."""
    best = (math.inf, 0, 0.0, 0.0)
    for n in budget.pi_n:
        for power in budget.powers:
            widths = play_width_grid(d.x, n, power=power)
            ridge, scores = select_pi_ridge(d.x, sign * d.y, widths, RIDGES,
                                            nonnegative=nonnegative, validation=d.validation,
                                            warmup=d.warmup)
            best = min(best, (scores[ridge], n, power, ridge))
    return best


def _inverse_pi(d: Scaled, sign: float, n: int, power: float, ridge: float,
                end: int) -> Callable:
    """``sign`` x the exact inverse of the non-negative PI model of the input from ``sign`` x
    target, fitted on samples [warmup, end) of every row (widths from the span there)."""
    t = sign * d.y[:, :end]
    forward = fit_prandtl_ishlinskii(t, d.x[:, :end], play_width_grid(t, n, power=power),
                                     ridge=ridge, warmup=d.warmup, nonnegative=True)
    inverse = forward.inverse()
    return lambda v: sign * inverse(v)[0]


def _inverse_pi_choice(d: Scaled, budget: Budget, sign: float) -> Choice:
    best = (math.inf, 0, 0.0, 0.0)
    for n in budget.pi_n:
        for power in budget.powers:
            for ridge in RIDGES:
                try:
                    f = _inverse_pi(d, sign, n, power, ridge, d.cut)
                except ValueError:  # no strictly increasing loading curve: no inverse
                    continue
                best = min(best, (d.score(f), n, power, ridge))
    return best


def pi_constrained(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    best = min((_pi_choice(d, budget, True, sign), False, sign) for sign in (1.0, -1.0))
    best = min(best, *((_inverse_pi_choice(d, budget, sign), True, sign)
                       for sign in (1.0, -1.0)))
    (score, n, power, ridge), inverse, sign = best
    text = f"n={n}, power={power:g}, ridge={ridge:g}, sign={sign:+.0f}"
    if inverse:
        f = _inverse_pi(d, sign, n, power, ridge, d.x.shape[1])
        return d.fitted(f, f"inverse of forward, {text}", score)
    model = fit_prandtl_ishlinskii(d.x, sign * d.y, play_width_grid(d.x, n, power=power),
                                   ridge=ridge, warmup=d.warmup, nonnegative=True)
    return d.fitted(lambda v: sign * model(v)[0], f"direct, {text}", score)


def pi_ls(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    score, n, power, ridge = _pi_choice(d, budget, nonnegative=False)
    model = fit_prandtl_ishlinskii(d.x, d.y, play_width_grid(d.x, n, power=power), ridge=ridge,
                                   warmup=d.warmup)
    return d.fitted(lambda v: model(v)[0], f"n={n}, power={power:g}, ridge={ridge:g}", score)


def _gpi(d: Scaled, inverse: bool, n: int, power: float, ridge: float, units: int, end: int,
         epochs: int) -> Callable[[Tensor], Tensor]:
    """Generalized PI model of t = sign x target from the input, fitted on samples [0, end)
    of every row, or the inverse of one of the input from t; ``sign`` makes t rise with the
    input."""
    sign = _rising(d, end)
    t = sign * d.y[:, :end]
    u, out = (t, d.x[:, :end]) if inverse else (d.x[:, :end], t)
    model = fit_generalized_pi(u, out, play_width_grid(u, n, power=power), units=units,
                               ridge=ridge, lbfgs_epochs=epochs, warmup=d.warmup)
    if not inverse:
        return lambda v: sign * model(v)[0]
    exact = model.bounded_inverse(u)  # g^-1 within the PI part's training range +- half
    return lambda v: sign * exact(v)[0]


def generalized_pi(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    sign = _rising(d, d.cut)
    candidates = []
    for inverse, (_, n, power, ridge) in ((False, _pi_choice(d, budget, True, sign)),
                                          (True, _inverse_pi_choice(d, budget, sign))):
        for units in budget.gpi_units if n else ():
            try:
                score = d.score(_gpi(d, inverse, n, power, ridge, units, d.cut,
                                     budget.gpi_epochs))
            except (FloatingPointError, ValueError):  # diverged, or no inverse
                continue
            candidates.append((score, inverse, n, power, ridge, units))
    for k, (score, inverse, n, power, ridge, units) in enumerate(sorted(candidates)):
        try:  # the best candidate whose refit on the whole training part converges
            f = _gpi(d, inverse, n, power, ridge, units, d.x.shape[1], budget.gpi_epochs)
        except FloatingPointError:
            continue
        how = "inverse of forward" if inverse else "direct"
        note = f" ({k} better refit(s) diverged)" if k else ""
        return d.fitted(f, f"{how}, n={n}, power={power:g}, ridge={ridge:g}, units={units}, "
                           f"sign={_rising(d, d.x.shape[1]):+.0f}, "
                           f"lbfgs={budget.gpi_epochs}{note}", score)
    raise FloatingPointError("every generalized PI candidate diverged")


def preisach(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    best = (math.inf, 0, 0.0, 0.0)
    for n in budget.preisach_n:
        for sign in (1.0, -1.0):
            p, scores = select_penalty(d.x, sign * d.y, list(SMOOTHNESS), kind="smoothness",
                                       validation=d.validation, n=n, warmup=d.warmup)
            best = min(best, (scores[p], n, sign, p))
    score, n, sign, p = best
    model = fit_preisach(d.x, sign * d.y, n=n, smoothness=p, warmup=d.warmup)
    return d.fitted(lambda v: sign * model(v)[0], f"n={n}, smoothness={p:g}, sign={sign:+.0f}",
                    score)


StopSetting = tuple[int, float, int, float, float]
"""(number of thresholds, grid power, segments, sign, ridge) of the stop-type rows."""


def _stop_settings(d: Scaled, budget: Budget) -> Iterator[tuple[StopSetting, float]]:
    """Every setting of the stop-type grid, each with the ridge ``select_stop_pi_ridge``
    chooses for the stops alone on the hold-out, and that ridge's hold-out RMSE."""
    for n in budget.stop_n:
        for power in (1.0, 2.0):
            thresholds = play_width_grid(d.x[:, d.warmup:], n, power=power)
            for segments in budget.stop_segments:
                for sign in (1.0, -1.0):
                    ridge, scores = select_stop_pi_ridge(
                        d.x, sign * d.y, thresholds, RIDGES, segments=segments,
                        validation=d.validation, warmup=d.warmup)
                    yield (n, power, segments, sign, ridge), scores[ridge]


def _stop_choice(setting: StopSetting) -> str:
    n, power, segments, sign, ridge = setting
    return (f"n={n}, power={power:g}, segments={segments}, ridge={ridge:g}, "
            f"sign={sign:+.0f}")


def stop_pi(split: Split, budget: Budget) -> Fitted:
    """``fit_stop_pi`` (non-negative slopes) of the target or of its negative (a non-negative
    model's loops run clockwise only); thresholds on ``play_width_grid`` (up to the input's
    span), their number, the grid power, the segments, the sign and the ridge chosen on the
    hold-out."""
    d = scaled(split)
    score, setting = min((score, setting) for setting, score in _stop_settings(d, budget))
    n, power, segments, sign, ridge = setting
    model = fit_stop_pi(d.x, sign * d.y, play_width_grid(d.x[:, d.warmup:], n, power=power),
                        segments=segments, ridge=ridge, warmup=d.warmup)
    return d.fitted(lambda v: sign * model(v)[0], _stop_choice(setting), score)


def _drift(d: Scaled, end: int) -> Drift:
    """The configs' ``drift`` family (:data:`torchhys.registry.FAMILIES`:
    :func:`~torchhys.fit_drift`, a free slope, ``DRIFT_SCALES`` spans of the scored input)
    fitted on the samples before ``end``."""
    _, fit = FAMILIES["drift"]({"fit": "drift"})
    return fit(d.x[:, :end], d.y[:, :end], d.warmup)


def _stop_pi_drift(d: Scaled, setting: StopSetting, drift: Drift,
                   end: int) -> Callable[[Tensor], Tensor]:
    """The stops (as the ``stop_pi`` row fits them) fitted on the samples before ``end``
    beside ``drift`` (fitted on the same samples, :func:`_drift`), then a least-squares
    affine readout of the two outputs on those samples."""
    n, power, segments, sign, ridge = setting
    x, y, w = d.x[:, :end], d.y[:, :end], d.warmup
    stops = fit_stop_pi(x, sign * y, play_width_grid(d.x[:, w:], n, power=power),
                        segments=segments, ridge=ridge, warmup=w)

    def features(v: Tensor) -> Tensor:
        return torch.stack([stops(v)[0], drift(v)[0], torch.ones_like(v)], -1)

    with torch.no_grad():
        coef = torch.linalg.lstsq(features(x)[:, w:].reshape(-1, 3).to(F64),
                                  y[:, w:].reshape(-1, 1).to(F64)).solution[:, 0]
    return lambda v: features(v).to(F64) @ coef


def stop_pi_drift(split: Split, budget: Budget) -> Fitted:
    """The stop-type PI model beside a drift of the accumulated input variation (the
    ``[stop_pi, drift]`` candidate of ``configs/measured.yaml``, its readout by least
    squares): the stops' number, grid power, segments and sign chosen on the hold-out of the
    whole, each setting's ridge as the ``stop_pi`` row chooses it (on the stops alone)."""
    d = scaled(split)
    drift = _drift(d, d.cut)  # the same for every setting of the stops
    score, setting = min((d.score(_stop_pi_drift(d, setting, drift, d.cut)), setting)
                         for setting, _ in _stop_settings(d, budget))
    end = d.x.shape[1]
    return d.fitted(_stop_pi_drift(d, setting, _drift(d, end), end), _stop_choice(setting),
                    score)



def jiles_atherton(split: Split, budget: Budget) -> Fitted:
    """The inverse Jiles-Atherton model (B in T -> H in A/m), physical units: fitted on the
    part before the hold-out for the hold-out RMSE, then on the whole training part."""
    if not split.magnetic:
        raise NotApplicable("B -> H records only")

    def fit(x: Tensor, y: Tensor) -> JilesAtherton:
        return fit_jiles_atherton(x, y, warmup=split.warmup, starts=budget.ja_starts,
                                  iterations=budget.ja_iterations)

    cut = holdout(split.x.shape[1], split.warmup)
    with torch.no_grad():
        score = _rmse(fit(split.x[:, :cut], split.y[:, :cut])(split.x)[0][:, cut:],
                      split.y[:, cut:])
    model = fit(split.x, split.y)
    return Fitted(lambda v: model(v)[0], model.extra_repr(), score)


# --- networks -----------------------------------------------------------------------------
def _eiho_net(x: Tensor, threshold: float | str) -> InverseHysteresisNet:
    torch.manual_seed(0)
    widths = 0.4 * play_width_grid(x, 16, power=1.0)
    ops = [EIHO(a=1.0, rule="recent", output="branch", threshold=threshold), Backlash(widths)]
    return InverseHysteresisNet(ops, 16).double()


def _train_head(net: InverseHysteresisNet, x: Tensor, y: Tensor, warmup: int, end: int,
                steps: int) -> list[float]:
    """Fit the normalization, then L-BFGS-train the head on samples [warmup, end) of every
    row (steps of up to 20 iterations); the RMSE on [end, T) after each step."""
    net.fit_normalization(x[:, :end], y[:, :end])
    with torch.no_grad():
        feats, _ = net.features(x)
    params = [p for p in net.parameters() if p.requires_grad]
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=20, history_size=50,
                            line_search_fn="strong_wolfe", tolerance_grad=1e-12,
                            tolerance_change=1e-15)
    ft, yt = feats[:, warmup:end], y[:, warmup:end]

    def closure() -> Tensor:
        opt.zero_grad()
        loss = (net.head(ft) - yt).square().mean()
        loss.backward()
        return loss

    curve = []
    for _ in range(steps):
        opt.step(closure)
        if end < x.shape[1]:
            with torch.no_grad():
                curve.append(_rmse(net.head(feats[:, end:]), y[:, end:]))
    return curve


def eiho_net(split: Split, budget: Budget) -> Fitted:
    d = scaled(split)
    best = (math.inf, 0, 0.0)
    for threshold in (0.0, "auto"):
        curve = _train_head(_eiho_net(d.x, threshold), d.x, d.y, d.warmup, d.cut,
                            budget.net_steps)
        k = int(np.argmin(curve))
        best = min(best, (curve[k], k + 1, threshold), key=lambda b: b[0])
    score, steps, threshold = best
    net = _eiho_net(d.x, threshold)
    _train_head(net, d.x, d.y, d.warmup, d.x.shape[1], steps)
    return d.fitted(lambda v: net(v)[0], f"threshold={threshold}, lbfgs_steps={steps}x20",
                    score)
