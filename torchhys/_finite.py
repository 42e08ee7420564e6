"""Non-finite numbers in a fit, caught where they enter: the training data's scale (read),
the fitted normalization (set-up), the loss and the weights (after every training step),
and the weights and the output of a checkpoint's network (export).

A fit whose loss or weights become NaN or infinite has diverged: it stops with
:class:`DivergedError` (a ``ValueError``: one line from the command), naming the epoch and
the likely causes, before its checkpoint is saved; ``torchhys export`` refuses a checkpoint
whose weights are not finite (:func:`check_weights`) or whose network's output is not
finite across its training input range (:func:`check_output`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

NORMALIZATION = ("in_mean", "in_std", "out_mean", "out_std")
"""The network's normalization buffers (fitted once on the training data)."""


class DivergedError(ValueError):
    """A fit whose training loss or weights became NaN or infinite."""


def check_scale(values: np.ndarray, what: str, error: type[Exception] = ValueError) -> None:
    """Refuse data whose mean or standard deviation (what the network's normalization is
    fitted from) is not finite in float64: values beyond about 1e154 in magnitude.

    Args:
        values: the column's training samples.
        what: the file and column, for the message (``"data.csv: data.input_column 'x'"``).
        error: the exception raised (a ``DataFileError`` for a file).
    """
    with np.errstate(over="ignore", invalid="ignore"):
        mean, std = float(np.mean(values)), float(np.std(values))
    if math.isfinite(mean) and math.isfinite(std):
        return
    big = float(np.max(np.abs(values)))
    raise error(f"{what} holds values up to {big:.3g} in magnitude: its mean and standard "
                f"deviation (the network's normalization) are not finite in float64 (mean "
                f"{mean:.3g}, std {std:.3g}); rescale the column (e.g. other units)")


def first_nonfinite(tensors: Mapping[str, Any]) -> str | None:
    """The name of the first floating-point tensor of ``tensors`` holding a NaN or an
    infinity, with its count (``"hidden.weight (12 of 24 values)"``); None: all finite."""
    for name, t in tensors.items():
        if isinstance(t, Tensor) and t.is_floating_point():
            bad = int((~torch.isfinite(t.detach())).sum())
            if bad:
                return f"{name} ({bad} of {t.numel()} values)"
    return None


def check_normalization(net: nn.Module) -> None:
    """Refuse a normalization fitted to non-finite statistics (data too large for the
    network's dtype: float32 holds magnitudes up to about 3.4e38)."""
    buffers = dict(net.named_buffers())
    bad = first_nonfinite({k: buffers[k] for k in NORMALIZATION if k in buffers})
    if bad is not None:
        dtype = str(buffers["in_mean"].dtype).replace("torch.", "")
        raise ValueError(f"the normalization fitted on the training data is not finite in "
                         f"{dtype}: {bad}; the data's values are too large for it: rescale "
                         "the data (e.g. other units), or train in float64 "
                         "(trainer.precision 64-true)")


def check_learning_rate(lr: Any, dtype: torch.dtype, optimizer: str) -> None:
    """Refuse a learning rate that is not a finite number the weights' ``dtype`` holds
    (float32: up to about 3.4e38): the first step would overflow."""
    if isinstance(lr, bool) or not isinstance(lr, (int, float)):
        return  # the optimizer's own check names it
    largest = torch.finfo(dtype).max
    if not (math.isfinite(lr) and abs(lr) <= largest):
        name = str(dtype).replace("torch.", "")
        raise DivergedError(f"model.lr {lr!r} (optimizer {optimizer!r}) is not a finite number "
                            f"in the weights' {name} (largest {largest:.3g}): the first step "
                            "would overflow; a learning rate such as 1e-2")


def check_training(module: Any, loss: Tensor | None) -> None:
    """Stop a fit whose training loss or weights are not finite (after a training step).

    Args:
        module: the :class:`~torchhys.training.InverseHysteresisModule` (its epoch, its
            optimizer's name and learning rate, its parameters).
        loss: the step's training loss (None: not known).

    Raises:
        DivergedError: one line naming the epoch (Lightning's, counted from 0), what is
            not finite and the likely causes.
    """
    params = dict(module.named_parameters())
    flags = [torch.isfinite(p.detach()).all() for p in params.values()]
    if loss is not None:
        flags.append(torch.isfinite(loss.detach()).all())
    if not flags or bool(torch.stack([f.to(flags[0].device) for f in flags]).all()):
        return  # one synchronization a step on a GPU
    bad_loss = loss is not None and not bool(torch.isfinite(loss.detach()).all())
    bad = first_nonfinite(params)
    what = []
    if bad_loss:
        what.append(f"the training loss is {float(loss.detach().reshape(-1)[0]):g}")
    if bad is not None:
        what.append(f"the weights {bad} are not finite")
    hp = module.hparams
    optimizer = hp.get("optimizer", "?")
    lr = "" if optimizer == "cg" else f", model.lr {hp.get('lr')!r}"
    raise DivergedError(
        f"the fit diverged in epoch {module.current_epoch}: {' and '.join(what)}; likely "
        f"causes: a learning rate too large (model.optimizer {optimizer!r}{lr}: lower it), "
        "or data at a scale the network cannot hold (check the data's magnitudes and units); "
        "no checkpoint of this epoch was saved")


def check_weights(net: nn.Module, where: str) -> None:
    """Refuse a network whose weights or normalization hold a NaN or an infinity (a
    diverged fit), naming the first (operators' buffers are not looked at: some hold
    infinite bounds by design).

    Args:
        net: the network, its checkpoint loaded.
        where: the file, for the message (``"--ckpt run/last.ckpt"``).
    """
    buffers = dict(net.named_buffers())
    bad = first_nonfinite({**dict(net.named_parameters()),
                           **{k: buffers[k] for k in NORMALIZATION if k in buffers}})
    if bad is not None:
        raise ValueError(f"{where}: the weight {bad} is not finite (a diverged fit): the "
                         "compensator would hold its initial command; fit again (a smaller "
                         "model.lr, data in other units)")


OUTPUT_BOUND = 1e6
"""How far (in the training output's standard deviations, from its mean) a network's output
over its training input range may lie before :func:`check_output` refuses it: a fitted
network's output stays within a few; 1e6 is reached only by weights blown up by a diverging
step (a learning rate such as 1e300 leaves weights near 1e300)."""


def check_output(net: nn.Module, where: str, samples: int = 64) -> None:
    """Refuse a network whose output over its training input range is not finite (weights
    finite but so large that the output overflows) or lies more than :data:`OUTPUT_BOUND`
    of the training output's standard deviations (``out_std``) from its mean (``out_mean``):
    a fit stopped as it diverged. A sequence model (a :class:`~torchhys.compose.Composed`,
    no ``out_std``) is run on the range as one sequence (batch 1); only its finiteness is
    checked. A network of operating conditions is run at their training ranges' ends and
    middle (one row each). Nothing is checked for a model that records no input range."""
    lo, hi = float(net.in_min), float(net.in_max)
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return
    dtype = net.in_min.dtype
    x = torch.linspace(lo, hi, samples, dtype=torch.float64).to(dtype)
    x = torch.cat([x, x.flip(0)])
    sequence = not hasattr(net, "out_std")  # a sequence model (a Composed): y = net(x)
    n = 0 if sequence else int(getattr(net, "n_conditions", 0) or 0)
    with torch.no_grad():
        if n:  # rows at the conditions' low end, middle and high end
            lo_c, hi_c = net.cond_min.to(dtype), net.cond_max.to(dtype)
            c = torch.stack([lo_c, (lo_c + hi_c) / 2, hi_c])[:, None, :].expand(3, x.numel(), n)
            y = net(x.expand(3, -1), conditions=c)[0]
        else:
            y = net(x[None])[0] if sequence else net(x)[0]
    bad = int((~torch.isfinite(y)).sum())
    if not bad and hasattr(net, "out_mean") and hasattr(net, "out_std"):
        mean, std = float(net.out_mean), float(net.out_std)
        far = float((y.double() - mean).abs().max()) / max(std, 1e-300)
        if math.isfinite(mean) and std > 0 and far > OUTPUT_BOUND:
            raise ValueError(f"{where}: the network's output across its training input range "
                             f"lies {far:.3g} standard deviations of the training output from "
                             f"its mean (more than {OUTPUT_BOUND:g}: a diverged fit's weights); "
                             "fit again (a smaller model.lr, data in other units)")
    if bad:
        big = max(float(p.detach().abs().max()) for p in net.parameters())
        raise ValueError(f"{where}: the {'model' if sequence else 'network'}'s output is not "
                         f"finite at {bad} of "
                         f"{y.numel()} inputs across its training input range (weights up to "
                         f"{big:.3g} in magnitude: a diverged fit); fit again (a smaller "
                         "model.lr, data in other units)")
