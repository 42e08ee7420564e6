"""One candidate of model selection built and fitted on tensors, without Lightning.

A candidate is a dict of model arguments (:data:`MODEL_DEFAULTS` for those it leaves out):
the operators (a spec, a list of specs, the model families ``{fit: NAME}`` identified on the
training data, or None: the plain network), the network that reads them (``hidden``,
``activation``, ``init``) and how that network is trained (``optimizer``, ``lr``,
``optimizer_kwargs``). :func:`fit_candidate` builds it from a seed, fits its data-dependent
operators and normalization on the fit samples, then its readout:

- solved by least squares (:func:`solve_readout`) where the candidate is *direct*
  (:func:`is_direct`: an identity activation over operators without trainable parameters,
  trained by a closure optimizer: its training is a linear least-squares problem, which the
  optimizer would only approach);
- else trained full batch by its optimizer for ``epochs`` steps (:func:`train_full_batch`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from typing import Any

import torch
from torch import Tensor

from torchhys._finite import check_learning_rate, check_normalization
from torchhys.identification.specs import build_operators, fit_data_dependent
from torchhys.init import initialize
from torchhys.networks import InverseHysteresisNet
from torchhys.optim.named import (
    CLOSURE_OPTIMIZERS,
    OPTIMIZERS,
    check_optimizer_kwargs,
    optimizer_arguments,
)
from torchhys.selection.folds import Batch

__all__ = ["MODEL_DEFAULTS", "build_candidate", "candidate_spec", "fit_candidate",
           "is_direct", "model_base", "solve_readout", "squared_errors", "steps_readout",
           "train_full_batch"]

MODEL_DEFAULTS: dict[str, Any] = {
    "operator": None, "hidden": 1, "activation": "identity", "operator_kwargs": None,
    "init": "default", "optimizer": "lbfgs", "lr": 1.0,
    "optimizer_kwargs": {"max_iter": 20, "tolerance_grad": 1e-12, "tolerance_change": 1e-15},
    "schedule": None, "condition_degree": None,
}
"""A candidate's model arguments where it gives none: an affine readout trained by L-BFGS,
the model section of ``configs/measured.yaml``. ``condition_degree``: None, a model that does
not see the record's operating conditions; k >= 1, a network that takes them, its features'
products with their Legendre basis of total degree k
(:class:`~torchhys.InverseHysteresisNet`'s ``n_conditions``)."""


def model_base(model: Mapping[str, Any]) -> dict[str, Any]:
    """The model arguments of a config's model section that a candidate takes (the keys of
    :data:`MODEL_DEFAULTS`; the section's selection options and others left out)."""
    return {k: model[k] for k in MODEL_DEFAULTS if k in model}


def candidate_spec(base: Mapping[str, Any] | None, overrides: Mapping[str, Any]) -> dict:
    """The model arguments of a candidate: :data:`MODEL_DEFAULTS`, then ``base``, then the
    candidate's ``overrides``; a key that is no model argument is a ``ValueError`` naming
    it."""
    spec = {**MODEL_DEFAULTS, **dict(base or {}), **dict(overrides)}
    unknown = sorted(set(spec) - set(MODEL_DEFAULTS))
    if unknown:
        raise ValueError(f"{', '.join(map(repr, unknown))}: not a model argument of a "
                         f"candidate; valid: {sorted(MODEL_DEFAULTS)}")
    check_optimizer_kwargs(spec["optimizer"], spec["optimizer_kwargs"])
    if spec["schedule"] not in (None, "cosine") or (spec["schedule"] and spec["optimizer"]
                                                    in CLOSURE_OPTIMIZERS):
        raise ValueError(f"schedule must be None or 'cosine' (with optimizer='adam'), got "
                         f"{spec['schedule']!r} with optimizer={spec['optimizer']!r}")
    degree = spec["condition_degree"]
    if degree is not None and (isinstance(degree, bool) or not isinstance(degree, int)
                               or degree < 1):
        raise ValueError(f"condition_degree must be None (the conditions not seen) or an int "
                         f">= 1, got {degree!r}")
    return spec


def build_candidate(spec: Mapping[str, Any], *, dtype: torch.dtype = torch.float64,
                    seed: int | None = 0, n_conditions: int = 0,
                    ) -> tuple[InverseHysteresisNet, dict]:
    """The candidate's network, initialized from ``seed`` (None: the generator as it is),
    and the fitters of its model families
    (:func:`~torchhys.identification.specs.build_operators`); with ``condition_degree``,
    a network of the record's ``n_conditions``."""
    if seed is not None:
        torch.manual_seed(seed)
    ops, fitters = build_operators(spec["operator"], spec["operator_kwargs"])
    degree = spec.get("condition_degree")
    n = n_conditions if degree is not None else 0
    if degree is not None and n == 0:
        raise ValueError(f"condition_degree={degree}: the candidate takes operating conditions, "
                         "but the record has none (data.condition_columns)")
    net = InverseHysteresisNet(ops, spec["hidden"], activation=spec["activation"],
                               n_conditions=n, condition_degree=degree or 1)
    initialize(net, spec["init"])
    return net.to(dtype), fitters


def is_direct(spec: Mapping[str, Any], net: InverseHysteresisNet | None = None) -> bool:
    """Whether the candidate's readout is solved by least squares: an identity activation,
    operators without trainable parameters, a closure optimizer (L-BFGS, CG). Without
    ``net``, only the candidate's operators are built to ask (no network, no seed)."""
    if spec["activation"] != "identity" or spec["optimizer"] not in CLOSURE_OPTIMIZERS:
        return False
    ops = (net.operators if net is not None
           else build_operators(spec["operator"], spec["operator_kwargs"])[0])
    return not any(p.requires_grad for op in ops for p in op.parameters())


def steps_readout(max_epochs: int | None, limit_train_batches: float | int | None = None) -> bool:
    """Whether a Lightning trainer of these options steps a readout at all (``max_epochs``
    None: Lightning's default, 1000 or unlimited with ``max_time``; -1: unlimited), so that
    its least-squares solution (:func:`solve_readout`) is what the run converges to; not
    with ``max_epochs: 0`` or ``limit_train_batches: 0``."""
    return max_epochs != 0 and limit_train_batches not in (0, 0.0)


@torch.no_grad()
def solve_readout(net: InverseHysteresisNet, train: Batch) -> None:
    """Set the affine readout of ``net`` (identity activation) to the least-squares solution
    on the samples ``train.mask``: the first hidden unit carries it, the others are zero.

    Over the normalized features ``z`` and target ``t`` it solves ``min ||[z 1] theta -
    t||`` in float64 (``gelsd``: the minimum-norm solution where features are collinear)."""
    dtype = net.in_mean.dtype
    x, y = train.x.to(dtype), train.y.to(dtype)
    feats, _ = net.features(x, target=y, conditions=_seen(net, train))
    z = ((feats - net.in_mean) / net.in_std)[train.mask]
    t = ((y - net.out_mean) / net.out_std)[train.mask]
    design = torch.cat([z, torch.ones_like(z[:, :1])], 1).to(torch.float64)
    theta = torch.linalg.lstsq(design, t.to(torch.float64)[:, None],
                               driver="gelsd").solution[:, 0].to(dtype)
    for layer in (net.hidden, net.output):
        layer.weight.zero_()
        layer.bias.zero_()
    net.hidden.weight[0] = theta[:-1]
    net.hidden.bias[0] = theta[-1]
    net.output.weight[0, 0] = 1.0


def train_full_batch(net: InverseHysteresisNet, spec: Mapping[str, Any], train: Batch, *,
                     epochs: int, seconds: float | None = None) -> int:
    """Train ``net`` full batch on the samples ``train.mask`` by the candidate's optimizer:
    ``epochs`` steps (each of up to ``max_iter`` iterations for a closure optimizer), or
    fewer once ``seconds`` have passed; the steps done. The Lightning module's training of
    one full batch an epoch, step for step (the same loss, the same optimizer, ``schedule:
    cosine`` over ``epochs``): from the same seed it reaches the same weights.

    Raises:
        DivergedError: a learning rate the weights' dtype cannot hold
            (:func:`~torchhys._finite.check_learning_rate`)."""
    kwargs = optimizer_arguments(spec["optimizer"], spec["lr"], spec["optimizer_kwargs"])
    params = [p for p in net.parameters() if p.requires_grad]
    if "lr" in kwargs and params:  # one the weights' dtype holds, as the Lightning module
        check_learning_rate(kwargs["lr"], params[0].dtype, spec["optimizer"])
    opt = OPTIMIZERS[spec["optimizer"]](params, **kwargs)
    # "cosine": lr decays to 0 over the epochs, stepped after each (as Lightning's epochs)
    sched = (torch.optim.lr_scheduler.CosineAnnealingLR(opt, max(epochs, 1))
             if spec.get("schedule") == "cosine" else None)
    dtype = net.in_mean.dtype
    x, y, mask = train.x.to(dtype), train.y.to(dtype), train.mask
    c = _seen(net, train)
    fixed = not any(p.requires_grad for p in net.operators.parameters())
    with torch.no_grad():
        feats = net.features(x, target=y, conditions=c)[0] if fixed else None

    def closure() -> Tensor:
        opt.zero_grad()
        out = net.head(feats) if fixed else net(x, target=y, conditions=c)[0]
        loss = (out - y)[mask].square().mean()
        loss.backward()
        return loss

    start, done = time.perf_counter(), 0
    while done < epochs and (seconds is None or time.perf_counter() - start < seconds):
        if spec["optimizer"] in CLOSURE_OPTIMIZERS:
            opt.step(closure)
        else:
            closure()
            opt.step()
        if sched is not None:
            sched.step()
        done += 1
    return done


def fit_candidate(spec: Mapping[str, Any], train: Batch, fit: Batch, *, warmup: int = 0,
                  dtype: torch.dtype = torch.float64, seed: int | None = 0,
                  epochs: int = 10, seconds: float | None = None) -> InverseHysteresisNet:
    """The candidate fitted: built (:func:`build_candidate`), its model families and
    normalization fitted on ``fit`` (its first ``warmup`` samples left out of the families'
    least squares; the states run through the samples outside ``fit.mask``), then its
    readout solved (:func:`is_direct`) or trained (:func:`train_full_batch`) on ``train``.

    Raises:
        FitError: a model family that cannot be fitted to the data
            (:class:`~torchhys.identification.errors.FitError`).
    """
    n = 0 if fit.conditions is None else int(fit.conditions.shape[-1])
    net, fitters = build_candidate(spec, dtype=dtype, seed=seed, n_conditions=n)
    full = bool(fit.mask.all())
    mask = None if full else fit.mask
    fx, fy = fit.x.to(torch.float64), fit.y.to(torch.float64)
    fit_data_dependent(net.operators, fitters, fx, fy, warmup=warmup, mask=mask)
    net.fit_normalization(fx.to(dtype), fy.to(dtype), mask=mask, conditions=_seen(net, fit))
    check_normalization(net)
    if is_direct(spec, net):
        solve_readout(net, train)
    else:
        train_full_batch(net, spec, train, epochs=epochs, seconds=seconds)
    return net


@torch.no_grad()
def squared_errors(net: InverseHysteresisNet, val: Batch) -> Tensor:
    """The squared errors of ``net`` on the samples ``val.mask``, float64, flat in time
    order (row by row)."""
    dtype = net.in_mean.dtype
    out = net(val.x.to(dtype), target=val.y.to(dtype), conditions=_seen(net, val))[0]
    e = out.to(torch.float64) - val.y.to(torch.float64)
    return e.square()[val.mask]


def _seen(net: InverseHysteresisNet, batch: Batch) -> Tensor | None:
    """The batch's conditions in the network's dtype where the network takes them (None
    where it does not: a candidate that does not see the conditions)."""
    if not net.n_conditions:
        return None
    if batch.conditions is None:
        raise ValueError("the network takes operating conditions, the batch has none")
    return batch.conditions.to(net.in_mean.dtype)


def _mean(errors: Tensor) -> float:
    """The mean of ``errors``, NaN when empty."""
    return float(errors.mean()) if errors.numel() else math.nan
