"""Shared set-up of the PowellBealeCG tests."""

from __future__ import annotations

from collections.abc import Callable

import torch

from torchhys.optim import PowellBealeCG


def make(fun: Callable[[torch.Tensor], torch.Tensor], x0: torch.Tensor, **options):
    """A parameter at ``x0``, a PowellBealeCG over it and the closure of ``fun``."""
    x = x0.clone().requires_grad_(True)
    opt = PowellBealeCG([x], **options)

    def closure():
        opt.zero_grad()
        loss = fun(x)
        loss.backward()
        return loss

    return x, opt, closure
