"""The rows of the hysteresis model families: each runs its family's own search of its
options (:data:`torchhys.registry.SEARCHES`: sign, direction, penalty over the budget's
sizes) on the scaled training part, chosen on the hold-out inside it (the package's
docstring says each row's grid); here only the scaling, the grids and the choice's text."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

from torchhys import EIHO, Backlash, Drift, InverseHysteresisNet, JilesAtherton, fit_jiles_atherton
from torchhys.identification._family_spec import PENALTIES
from torchhys.identification.fitting import play_width_grid
from torchhys.identification.preisach import SMOOTHNESS
from torchhys.identification.stop_pi import StopSetting, fit_stop_setting, stop_pi_settings
from torchhys.registry import FAMILIES, SEARCHES, Searched

from .datasets import F64, Split
from .scoring import Budget, Fitted, NotApplicable, Scaled, _rmse, holdout, scaled

RIDGES = PENALTIES
"""The ridge grid of every row: the config families' ``"auto"`` grid."""
__all__ = ["RIDGES", "SMOOTHNESS", "eiho_net", "generalized_pi", "jiles_atherton",
           "pi_constrained", "pi_ls", "preisach", "stop_pi", "stop_pi_drift"]


def _search(family: str, split: Split, **grid: Any) -> tuple[Scaled, Searched]:
    """The family's search on the scaled training part, its hold-out the last quarter of
    the scored samples of every row."""
    d = scaled(split)
    return d, SEARCHES[family](d.x, d.y, d.warmup, d.cut, **grid)


def _how(options: dict[str, Any]) -> str:
    return "inverse of forward" if options["direction"] == "inverse" else "direct"


def pi_constrained(split: Split, budget: Budget) -> Fitted:
    d, s = _search("pi_nonneg", split, n_widths=budget.pi_n, powers=budget.powers)
    o = s.options
    return d.fitted(s.predict, f"{_how(o)}, n={o['n_widths']}, power={o['power']:g}, "
                               f"ridge={o['ridge']:g}, sign={o['sign']:+.0f}", s.holdout)


def pi_ls(split: Split, budget: Budget) -> Fitted:
    d, s = _search("pi_ls", split, n_widths=budget.pi_n, powers=budget.powers)
    o = s.options
    return d.fitted(s.predict, f"n={o['n_widths']}, power={o['power']:g}, ridge={o['ridge']:g}",
                    s.holdout)


def generalized_pi(split: Split, budget: Budget) -> Fitted:
    d, s = _search("gpi", split, n_widths=budget.pi_n, powers=budget.powers,
                   units=budget.gpi_units, epochs=budget.gpi_epochs)
    o = s.options
    note = f" ({s.skipped} better refit(s) diverged)" if s.skipped else ""
    return d.fitted(s.predict, f"{_how(o)}, n={o['n_widths']}, power={o['power']:g}, "
                               f"ridge={o['ridge']:g}, units={o['units']}, "
                               f"sign={o['sign']:+.0f}, lbfgs={o['epochs']}{note}", s.holdout)


def preisach(split: Split, budget: Budget) -> Fitted:
    d, s = _search("preisach", split, levels=budget.preisach_n)
    o = s.options
    return d.fitted(s.predict, f"n={o['n']}, smoothness={o['smoothness']:g}, "
                               f"sign={o['sign']:+.0f}", s.holdout)


def _stop_choice(setting: StopSetting) -> str:
    n, power, segments, sign, ridge = setting
    return (f"n={n}, power={power:g}, segments={segments}, ridge={ridge:g}, "
            f"sign={sign:+.0f}")


def _stop_grid(budget: Budget) -> dict[str, tuple]:
    return {"n_widths": budget.stop_n, "powers": budget.stop_powers,
            "segments": budget.stop_segments}


def stop_pi(split: Split, budget: Budget) -> Fitted:
    """The ``stop_pi`` family's search (non-negative slopes, of the target or of its
    negative: a non-negative model's loops run clockwise only): thresholds on
    ``play_width_grid`` (up to the input's span), their number, the grid power, the
    segments, the sign and the ridge chosen on the hold-out."""
    d, s = _search("stop_pi", split, **_stop_grid(budget))
    setting = StopSetting(**{k: v for k, v in s.options.items() if k != "fit"})
    return d.fitted(s.predict, _stop_choice(setting), s.holdout)


def _drift(d: Scaled, end: int) -> Drift:
    """The configs' ``drift`` family (:data:`torchhys.registry.FAMILIES`:
    :func:`~torchhys.fit_drift`, a free slope, ``DRIFT_SCALES`` spans of the scored input)
    fitted on the samples before ``end``."""
    _, fit = FAMILIES["drift"]({"fit": "drift"})
    return fit(d.x[:, :end], d.y[:, :end], d.warmup)


def _stop_pi_drift(d: Scaled, setting: StopSetting, drift: Drift,
                   end: int) -> Callable[[Tensor], Tensor]:
    """The stops of the ``stop_pi`` family's ``setting`` fitted on the samples before ``end``
    beside ``drift`` (fitted on the same samples, :func:`_drift`), then a least-squares
    affine readout of the two outputs on those samples."""
    x, y, w = d.x[:, :end], d.y[:, :end], d.warmup
    stops = fit_stop_setting(d.x, d.y, w, setting, end)

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
    whole, each setting's ridge as the ``stop_pi`` family's search chooses it (on the stops
    alone, :func:`~torchhys.identification.stop_pi.stop_pi_settings`)."""
    d = scaled(split)
    drift = _drift(d, d.cut)  # the same for every setting of the stops
    score, setting = min((d.score(_stop_pi_drift(d, setting, drift, d.cut)), setting)
                         for setting, _ in stop_pi_settings(d.x, d.y, d.warmup, d.cut,
                                                            **_stop_grid(budget)))
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
