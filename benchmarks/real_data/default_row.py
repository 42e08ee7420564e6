"""The ``default`` row: the model that a ``torchhys fit`` config (``configs/measured.yaml``)
chooses, its candidates scored and trained as the config says."""

from __future__ import annotations

import inspect
import math
import time
from pathlib import Path

import torch
from torch import Tensor

from torchhys import InverseHysteresisNet
from torchhys.cli.train import read_config
from torchhys.deploy.streaming import default_limits
from torchhys.identification.errors import FitError
from torchhys.identification.specs import build_operators, fit_data_dependent
from torchhys.init import initialize
from torchhys.optim.named import OPTIMIZERS
from torchhys.training.folds import RECORDING, fold_masks
from torchhys.training.module import InverseHysteresisModule
from torchhys.training.selection import CandidateScore, best, standard_error

from .datasets import F64, ROOT, Split
from .scoring import Budget, Fitted, holdout

CONFIG = ROOT / "configs" / "measured.yaml"


def _config_model(path: Path) -> tuple[dict, dict, torch.dtype, int]:
    """The model section (with the module's defaults), trainer section, dtype and seed, read
    as ``torchhys fit`` reads the file (jsonargparse's YAML loader: ``1e-8`` is a number)."""
    cfg = read_config(path)
    defaults = {k: p.default for k, p in
                inspect.signature(InverseHysteresisModule.__init__).parameters.items()
                if p.default is not inspect.Parameter.empty}
    trainer = cfg.get("trainer") or {}
    dtype = F64 if str(trainer.get("precision", "32")).startswith("64") else torch.float32
    return {**defaults, **cfg["model"]}, trainer, dtype, int(cfg.get("seed_everything", 0))


def _train_config(path: Path, x: Tensor, y: Tensor, w: int, budget: Budget,
                  overrides: dict | None = None, held: Tensor | None = None,
                  ) -> tuple[InverseHysteresisNet, int, int]:
    """Build the config's network (its model section with a candidate's ``overrides``), fit
    its data-dependent operators and normalization on (x, y) (rows, time) and train it on
    samples [w, T), without the samples ``held`` ((rows, time) bool: a cross-validation
    fold's block, the states running through it): the net, epochs done, epochs asked."""
    m, trainer, dtype, seed = _config_model(path)
    m = {**m, **(overrides or {})}
    torch.manual_seed(seed)
    ops, fitters = build_operators(m["operator"], m["operator_kwargs"])
    net = InverseHysteresisNet(ops, m["hidden"], activation=m["activation"])
    initialize(net, m["init"])
    net.to(dtype)
    x, y = x.to(dtype), y.to(dtype)
    known = None if held is None else ~held  # the samples the fits may use
    fit_data_dependent(net.operators, fitters, x, y, warmup=w, mask=known)
    net.fit_normalization(x, y, mask=known)
    mask = torch.zeros_like(x, dtype=torch.bool)
    mask[:, w:] = True
    if held is not None:
        mask &= ~held
    fixed = not any(p.requires_grad for p in net.operators.parameters())
    with torch.no_grad():
        feats = net.features(x)[0] if fixed else None
    kwargs = dict(m["optimizer_kwargs"] or {})
    if m["optimizer"] != "cg":
        kwargs.setdefault("lr", m["lr"])
    if m["optimizer"] == "lbfgs":
        kwargs.setdefault("line_search_fn", "strong_wolfe")
    opt = OPTIMIZERS[m["optimizer"]]([p for p in net.parameters() if p.requires_grad], **kwargs)

    def closure() -> Tensor:
        opt.zero_grad()
        out = net.head(feats) if fixed else net(x)[0]
        loss = (out - y)[mask].square().mean()
        loss.backward()
        return loss

    epochs = int(trainer.get("max_epochs") or 1000)
    if budget.default_epochs is not None:
        epochs = min(epochs, budget.default_epochs)
    start, done = time.perf_counter(), 0
    while done < epochs and time.perf_counter() - start < budget.seconds:
        opt.step(closure)
        done += 1
    return net, done, epochs


def _describe(m: dict) -> str:
    specs = m["operator"] if isinstance(m["operator"], list) else [m["operator"]]
    names = "+".join(str(s.get("name", s.get("fit")))
                     + (f"({s['direction']})" if "direction" in s else "")
                     if isinstance(s, dict) else str(s) for s in specs)
    return f"{names} + {m['hidden']} {m['activation']}"


def _score(config: Path, overrides: dict, x: Tensor, y: Tensor, w: int, budget: Budget,
           cv: int | str | None, mode: str | None = None) -> tuple[float, float, bool]:
    """A candidate's validation MSE and its standard error, as ``torchhys fit`` scores it
    with ``model.select_cv`` = ``cv``: None, on the last quarter of the scored samples of
    every training row, fitted before it; ``k``, by blocked cross-validation inside the
    training rows (:func:`~torchhys.training.folds.fold_masks`: each fold fitted on
    the whole rows without its block's targets, the states running through it);
    ``"recording"``, each training row held out once, fitted on the others; with ``mode``
    ``"rolling"``, each block (row) after the first scored by a fit of those before it
    (for blocks, ``fold_masks(..., rolling=True)``). Returns the MSE
    and its standard error, NaN (never chosen, as ``torchhys fit`` scores it) when a fit
    fails (``FitError``) or the MSE is not finite, and whether a training stopped at the
    budget's time cap."""
    if cv is None:
        c = holdout(x.shape[1], w)
        folds = [(x[:, :c], y[:, :c], (slice(None), slice(c, None)), None)]
    elif cv == RECORDING:
        if x.shape[0] < 2:
            raise ValueError(f"model.select_cv={RECORDING!r} holds each training recording out "
                             f"once, but the protocol has {x.shape[0]} training row")
        if mode == "rolling":
            fits = [(list(range(r)), r) for r in range(1, len(x))]
        else:
            fits = [([j for j in range(len(x)) if j != r], r) for r in range(len(x))]
        folds = [(x[rest], y[rest], (slice(r, r + 1), slice(w, None)), None)
                 for rest, r in fits]
    else:
        mask = torch.zeros_like(x, dtype=torch.bool)
        mask[:, w:] = True
        folds = []
        rolling = mode == "rolling"
        for f in range(cv - 1 if rolling else cv):
            fitted, held = fold_masks(mask, cv, f, rolling=rolling)
            folds.append((x, y, held, mask & ~fitted))
    errors, capped = [], False
    for fx, fy, scored, held in folds:
        try:
            net, done, epochs = _train_config(config, fx, fy, w, budget, overrides, held)
        except FitError:
            return math.nan, math.nan, capped
        capped |= done < epochs
        dtype = next(net.parameters()).dtype
        with torch.no_grad():
            e = net(x.to(dtype))[0].to(F64) - y
        errors.append(e[scored].square().reshape(-1))
    e2 = torch.cat(errors)
    mse = float(e2.mean())
    if not math.isfinite(mse):
        return math.nan, math.nan, capped
    return mse, standard_error(e2), capped


def default_net(split: Split, budget: Budget, config: Path = CONFIG
                ) -> tuple[InverseHysteresisNet, str, float]:
    """The network of :func:`default` (trained as it says), its description and its
    hold-out RMSE."""
    x, y, w = split.x, split.y, split.warmup
    m = _config_model(config)[0]
    candidates = m.pop("select", None) or [{}]
    cv = m.pop("select_cv", None)
    mode = m.pop("select_cv_mode", None)
    rule = m.pop("select_rule", None) or "min"
    scores, capped_cv = [], False
    for i, overrides in enumerate(candidates):
        mse, se, capped = _score(config, overrides, x, y, w, budget, cv, mode)
        scores.append(CandidateScore(i, overrides, mse, val_se=se))  # NaN: never chosen
        capped_cv |= capped
    if all(math.isnan(s.val_mse) for s in scores):
        raise FitError("no candidate of the config could be fitted")
    chosen = best(scores, rule)  # as torchhys fit chooses (the first candidate NaN or not)
    order = [chosen] + sorted((s for s in scores if s is not chosen
                               and not math.isnan(s.val_mse)), key=lambda s: s.val_mse)
    failed, refit = 0, None
    for s in order:  # the chosen candidate, or the best one whose refit succeeds
        try:
            refit = _train_config(config, x, y, w, budget, candidates[s.index])
            i = s.index
            break
        except FitError:
            failed += 1
    if refit is None:
        raise FitError("no candidate of the config could be refitted")
    net, done, epochs = refit
    validation, score = "", math.sqrt(s.val_mse)
    if cv is not None:  # the row's hold-out RMSE, as the other rows'
        how = f"{cv} rolling" if mode == "rolling" else f"{cv}"
        validation = f", select_cv {how} RMSE {score:.4g}"
        held = _score(config, candidates[i], x, y, w, budget, None)[0]
        score = math.sqrt(held) if math.isfinite(held) else math.inf
    capped = f" (capped at {budget.seconds:g} s)" if done < epochs else ""
    if capped_cv:
        capped += f" (a validation training capped at {budget.seconds:g} s)"
    note = f" ({failed} failed refits)" if failed else ""
    label = f"candidate {i}{note}: " if len(candidates) > 1 else ""
    choice = (f"{config.name}: {label}{_describe({**m, **candidates[i]})}, {m['optimizer']} "
              f"{done} epochs{capped}{validation}")
    return net, choice, score


def default(split: Split, budget: Budget, config: Path = CONFIG) -> Fitted:
    """The model section of a ``torchhys fit`` config, trained as its trainer section says
    on the whole training part. With ``model.select``, every candidate is scored as
    ``torchhys fit`` scores it (:func:`_score`: on the hold-out, or by the cross-validation
    of the config's ``select_cv``), the config's ``select_rule`` chooses one (a candidate
    that cannot be fitted is skipped), and it is refitted on the whole training part;
    without, the hold-out RMSE comes from a second fit before it. The row's hold-out RMSE
    is that of the chosen candidate fitted before the hold-out (as every row's, for
    ``selected``). Its prediction is the network's output saturated to the training target
    range (the exported command limits; :func:`default_net` gives the network, as
    ``benchmarks/deploy_safety.py`` scores it through the exported compensator's input clamp
    and direction guard); the candidates are scored without it, as ``torchhys fit`` scores
    them."""
    net, choice, score = default_net(split, budget, config)
    dtype = next(net.parameters()).dtype
    low, high = default_limits(net)  # the exported command limits
    return Fitted(lambda v: net(v.to(dtype))[0].to(F64).clamp(low, high), choice, score)
