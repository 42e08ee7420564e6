"""The ``default`` row: the model that a ``torchhys fit`` config (``configs/measured.yaml``)
chooses, its candidates scored and trained as the config says."""

from __future__ import annotations

import inspect
import math
from pathlib import Path

import torch
from torch import Tensor

from torchhys import InverseHysteresisNet
from torchhys.cli.train import read_config
from torchhys.deploy.ranges import default_limits
from torchhys.identification.errors import FitError
from torchhys.selection import select
from torchhys.selection.candidates import candidate_spec, fit_candidate, model_base
from torchhys.selection.folds import RECORDING
from torchhys.selection.run import record
from torchhys.training.module import InverseHysteresisModule

from .datasets import F64, ROOT, Split
from .scoring import Budget, Fitted

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


def _describe(m: dict) -> str:
    specs = m["operator"] if isinstance(m["operator"], list) else [m["operator"]]
    names = "+".join(str(s.get("name", s.get("fit")))
                     + (f"({s['direction']})" if "direction" in s else "")
                     if isinstance(s, dict) else str(s) for s in specs)
    return f"{names} + {m['hidden']} {m['activation']}"


def _options(config: Path, budget: Budget) -> dict:
    """:func:`~torchhys.selection.select`'s options as ``torchhys fit`` runs the config
    (its dtype, seed and epochs; the budget's caps on them)."""
    _, trainer, dtype, seed = _config_model(config)
    epochs = int(trainer.get("max_epochs") or 1000)
    if budget.default_epochs is not None:
        epochs = min(epochs, budget.default_epochs)
    return {"dtype": dtype, "seed": seed, "epochs": epochs, "seconds": budget.seconds,
            "warn_coverage": False}


def _check_rows(x: Tensor, cv: int | str | None) -> None:
    if cv == RECORDING and x.shape[0] < 2:
        raise ValueError(f"model.select_cv={RECORDING!r} holds each training recording out "
                         f"once, but the protocol has {x.shape[0]} training row")


def _score(config: Path, overrides: dict, x: Tensor, y: Tensor, w: int, budget: Budget,
           cv: int | str | None, mode: str | None = None) -> tuple[float, float, bool]:
    """A candidate's validation MSE and its standard error, as ``torchhys fit`` scores it
    with ``model.select_cv`` = ``cv`` (:func:`torchhys.selection.select`; None: on the last
    quarter of the scored samples of every training row, fitted before it), NaN when a fit
    fails or the MSE is not finite, and False (a candidate's training is not reported
    capped)."""
    _check_rows(x, cv)
    m = _config_model(config)[0]
    result = select([overrides], x, y, base=model_base(m), warmup=w, cv=cv, mode=mode, refit=False,
                    **_options(config, budget))
    return result.scores[0].val_mse, result.scores[0].val_se, False


def default_net(split: Split, budget: Budget, config: Path = CONFIG
                ) -> tuple[InverseHysteresisNet, str, float]:
    """The network of :func:`default` (chosen and fitted by
    :func:`torchhys.selection.run` as ``torchhys fit`` runs the config), its description
    and its hold-out RMSE."""
    x, y, w = split.x, split.y, split.warmup
    m = _config_model(config)[0]
    candidates = m.pop("select", None) or [{}]
    cv = m.pop("select_cv", None)
    mode = m.pop("select_cv_mode", None)
    rule = m.pop("select_rule", None) or "min"
    _check_rows(x, cv)
    options = _options(config, budget)
    try:
        result = select(candidates, x, y, base=model_base(m), warmup=w, cv=cv, mode=mode, rule=rule,
                        refit=False, **options)
    except ValueError as err:
        if "NaN" in str(err):
            raise FitError("no candidate of the config could be fitted") from None
        raise
    scores, chosen = result.scores, result.chosen
    order = [chosen] + sorted((s for s in scores if s is not chosen
                               and not math.isnan(s.val_mse)), key=lambda s: s.val_mse)
    data = record(x, y, warmup=w)
    train, fit, warmup = data.whole()
    failed, net = 0, None
    for s in order:  # the chosen candidate, or the best one whose refit succeeds
        try:
            spec = candidate_spec(model_base(m), candidates[s.index])
            net = fit_candidate(spec, train, fit, warmup=warmup, dtype=options["dtype"],
                                seed=options["seed"], epochs=options["epochs"],
                                seconds=options["seconds"])
            i = s.index
            break
        except FitError:
            failed += 1
    if net is None:
        raise FitError("no candidate of the config could be refitted")
    validation, score = "", math.sqrt(s.val_mse)
    if cv is not None:  # the row's hold-out RMSE, as the other rows'
        how = f"{cv} rolling" if mode == "rolling" else f"{cv}"
        validation = f", select_cv {how} RMSE {score:.4g}"
        held = _score(config, candidates[i], x, y, w, budget, None)[0]
        score = math.sqrt(held) if math.isfinite(held) else math.inf
    note = f" ({failed} failed refits)" if failed else ""
    label = f"candidate {i}{note}: " if len(candidates) > 1 else ""
    choice = (f"{config.name}: {label}{_describe({**m, **candidates[i]})}, {m['optimizer']} "
              f"{options['epochs']} epochs{validation}")
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
