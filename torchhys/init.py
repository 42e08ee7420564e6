"""Initializations of the one-hidden-layer inverse-hysteresis network."""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from torchhys._checks import check_choice, check_nonnegative, check_same_shape, check_tensor

__all__ = ["INITS", "initialize", "least_squares_output"]

INITS = ("default", "nguyen_widrow")


@torch.no_grad()
def nguyen_widrow(hidden: nn.Linear, output: nn.Linear, *, scale: float = 1.0) -> None:
    """Nguyen-Widrow initialization of ``hidden`` for standardized inputs.

    Each hidden unit gets a random direction of length ``beta = 0.7 H^(1/F) scale``
    (``H`` units, ``F`` inputs) and a bias uniform in ``[-beta, beta]``, so that the units'
    active regions tile the input range instead of all sitting near the origin (PyTorch's
    default for ``F = 2`` or ``3`` inputs gives nearly linear, nearly identical sigmoid
    units). The output layer keeps PyTorch's uniform weights and starts at a zero bias (the
    normalized output's mean).

    References:
        D. Nguyen and B. Widrow, "Improving the learning speed of 2-layer neural networks by
        choosing initial values of the adaptive weights", IJCNN 1990.
    """
    n_hidden, n_in = hidden.weight.shape
    beta = 0.7 * n_hidden ** (1.0 / n_in) * scale
    w = torch.rand_like(hidden.weight) * 2 - 1
    w = w / w.norm(dim=1, keepdim=True).clamp_min(1e-12) * beta
    hidden.weight.copy_(w)
    hidden.bias.copy_((torch.rand_like(hidden.bias) * 2 - 1) * beta)
    bound = 1.0 / math.sqrt(n_hidden)
    output.weight.uniform_(-bound, bound)
    output.bias.zero_()


def initialize(net: nn.Module, init: str) -> None:
    """Apply the named initialization (``"default"``: PyTorch's, left as is) to ``net``.

    ``net`` must have ``hidden`` and ``output`` ``nn.Linear`` layers (as
    :class:`torchhys.InverseHysteresisNet`) for ``"nguyen_widrow"``.
    """
    check_choice(init, "init", INITS)
    if init == "default":
        return
    hidden, output = getattr(net, "hidden", None), getattr(net, "output", None)
    if not (isinstance(hidden, nn.Linear) and isinstance(output, nn.Linear)):
        raise ValueError(
            f"init={init!r} needs a network with nn.Linear 'hidden' and 'output' layers, "
            f"got {type(net).__name__}"
        )
    nguyen_widrow(hidden, output)


@torch.no_grad()
def least_squares_output(net: nn.Module, x: Tensor, y: Tensor, *, ridge: float = 1e-6) -> None:
    """Set the output layer of ``net`` to the ridge least-squares fit of the target over its
    hidden layer's activations on ``(x, y)``; the hidden layer is kept (a network whose
    output follows a record without a training run: the C example, the export tests).

    ``net``: an :class:`~torchhys.InverseHysteresisNet` whose normalization is fitted
    (``fit_normalization``); ``x``, ``y``: (time,) or (batch, time), every sample counted.
    Over the activations ``h`` of the normalized features and the normalized target ``t`` it
    solves ``(A^T A + ridge I) w = A^T t`` with ``A = [h 1]``, in the network's dtype. (A
    network with an identity activation has an affine readout, solved without ridge by
    :func:`torchhys.selection.candidates.solve_readout`.)"""
    check_same_shape(check_tensor(y, "y"), check_tensor(x, "x"), "y", "x")
    ridge = check_nonnegative(ridge, "ridge")
    feats, _ = net.features(x)
    f = feats.reshape(-1, feats.shape[-1])
    h = net.activation(net.hidden((f - net.in_mean) / net.in_std))
    a = torch.cat([h, torch.ones(h.shape[0], 1, dtype=h.dtype, device=h.device)], 1)
    target = ((y.to(h.dtype) - net.out_mean) / net.out_std).reshape(-1)
    eye = torch.eye(a.shape[1], dtype=a.dtype, device=a.device)
    w = torch.linalg.solve(a.T @ a + ridge * eye, a.T @ target)
    net.output.weight.copy_(w[:-1][None])
    net.output.bias.copy_(w[-1:])
