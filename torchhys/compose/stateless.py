"""Steps of torch's stateless layers: ``nn.Linear`` and the elementwise modules (activations
such as ``nn.Tanh``, ``nn.ReLU``, ``nn.GELU``, ``nn.Sigmoid``, ``nn.Identity``, ...).

A stateless layer acts on each sample alone, so its step is the layer itself, copied
(detached) in the step's dtype, on x (batch, n_inputs) -> (batch, n_outputs), with no state
(``state_spec = []``). Inside a composition (:func:`~torchhys.compose.compose`) such layers
run as they are; these steps are for using one on its own.
"""

# no `from __future__ import annotations`: TorchScript reads the step's class annotations
import copy

import torch
from torch import Tensor, nn

from torchhys._checks import check_int
from torchhys.step import OperatorStep

__all__ = ["ELEMENTWISE", "StatelessStep", "stateless_step"]

#: the elementwise torch modules a :class:`StatelessStep` takes without a width
ELEMENTWISE: tuple[type, ...] = (
    nn.Identity, nn.Tanh, nn.Sigmoid, nn.ReLU, nn.LeakyReLU, nn.ELU, nn.SELU, nn.CELU,
    nn.GELU, nn.SiLU, nn.Softplus, nn.Softsign, nn.Hardtanh, nn.ReLU6, nn.Hardsigmoid,
    nn.Hardswish, nn.Mish, nn.Tanhshrink, nn.Softshrink, nn.Hardshrink, nn.LogSigmoid,
)


class StatelessStep(OperatorStep):
    """A stateless layer as a step: ``forward(x, [])`` -> (``module(x)``, []).

    Args:
        module: the layer (copied, detached, in ``dtype``).
        n_inputs: columns of x.
        n_outputs: columns of the layer's output.
        dtype: the step's dtype (default: the layer's, or the default dtype).
    """

    def __init__(self, module: nn.Module, n_inputs: int, n_outputs: int,
                 dtype: torch.dtype | None = None) -> None:
        super().__init__()
        self.module = copy.deepcopy(module)
        for p in self.module.parameters():
            p.requires_grad_(False)
        if dtype is not None:
            self.module.to(dtype)
        self.n_inputs = check_int(n_inputs, "n_inputs", minimum=1)
        self.n_outputs = check_int(n_outputs, "n_outputs", minimum=1)
        self.state_spec = []

    def forward(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        return self.module(x), state


def stateless_step(module: nn.Module, dtype: torch.dtype | None = None, *,
                   width: int | None = None) -> StatelessStep:
    """The step of an ``nn.Linear`` (its widths are its own) or of an elementwise module of
    :data:`ELEMENTWISE` (``width`` columns in and out, default 1).

    Raises:
        TypeError: another kind of module (named, with what is supported).
    """
    if isinstance(module, nn.Linear):
        return StatelessStep(module, module.in_features, module.out_features, dtype)
    if isinstance(module, ELEMENTWISE):
        n = 1 if width is None else width
        return StatelessStep(module, n, n, dtype)
    raise TypeError(f"{type(module).__name__} has no stateless step: nn.Linear and the "
                    "elementwise modules of torchhys.compose.stateless.ELEMENTWISE have one")
