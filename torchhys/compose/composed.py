"""A user's module of hysteresis operators, recurrent layers and elementwise maths as one
deployable model: :func:`compose` and :class:`Composed`.

``compose(module)`` traces ``module`` (x (batch, time) -> y (batch, time)) with ``torch.fx``,
keeping its stateful layers whole (:mod:`torchhys.compose._leaves`), checks it (one pass on
an example, then the module against its per-sample step, node by node) and returns a
:class:`Composed`: an ``nn.Module`` whose ``forward`` is the module's (it trains as the
module does) and which implements :class:`~torchhys.protocols.Deployable`, so the
:class:`~torchhys.deploy.streaming.StreamingCompensator` and every export take it.
"""

from __future__ import annotations

import math

import torch
import torch.fx as fx
from torch import Tensor, nn

from torchhys._checks import as_batched_sequence, fitted_samples
from torchhys.compose._check import _first_line, check_causal, check_graph, shape_pass
from torchhys.compose._leaves import Tracer
from torchhys.compose.graph import ComposedStep, build_step, leaf_tails
from torchhys.deploy.ranges import RANGES, training_ranges

__all__ = ["Composed", "LastFeature", "compose"]


#: the example the checks run on: batch and time
EXAMPLE = (2, 16)


def _dtype(module: nn.Module) -> torch.dtype:
    for t in (*module.parameters(), *module.buffers()):
        if t.is_floating_point():
            return t.dtype
    return torch.get_default_dtype()


class LastFeature(nn.Module):
    """The compensator's head of a composition: features ``[x, y]`` (batch, 2) -> the
    composed step's output y (batch, 1), the last column."""

    def forward(self, features: Tensor) -> Tensor:
        return features.narrow(1, features.shape[1] - 1, 1)


def _trace(module: nn.Module) -> fx.Graph:
    try:
        return Tracer().trace(module)
    except Exception as err:  # torch.fx's errors on data-dependent Python code
        raise ValueError(f"{type(module).__name__} cannot be traced by torch.fx "
                         f"({type(err).__name__}: {_first_line(err)}): its forward must not "
                         "branch on or iterate over tensor values") from err


class Composed(nn.Module):
    """A user's module as a deployable model (see the module docstring and
    ``docs/composing.md``).

    Args:
        module: the user's ``nn.Module``, x (batch, time) -> y (batch, time); kept (not
            copied): ``Composed(module)(x) == module(x)`` and its parameters are the module's.
        x, y: training input and target (batch, time) or (time,), optional: their ranges are
            recorded (:meth:`record_ranges`) for the compensator's default limits, input clamp
            and direction guard.

    Members of :class:`~torchhys.protocols.Deployable`: :meth:`streaming_steps` (one
    :class:`~torchhys.compose.graph.ComposedStep`) and :meth:`streaming_head`
    (:class:`LastFeature`).

    Raises:
        ValueError: a module that cannot be traced, a layer that cannot stream (a
            bidirectional RNN, a non-causal operator, attention), shapes that do not match,
            a node that is not causal (each naming the node), ``x`` without ``y``.
        TypeError: ``module`` is not an ``nn.Module``, a stateful layer without a step.
    """

    def __init__(self, module: nn.Module, *, x: Tensor | None = None,
                 y: Tensor | None = None) -> None:
        super().__init__()
        if not isinstance(module, nn.Module):
            raise TypeError(f"module must be an nn.Module, got {type(module).__name__}")
        self.module = module
        dtype = _dtype(module)
        for name in RANGES:
            self.register_buffer(name, torch.full((), math.nan, dtype=dtype))
        self._graph = _trace(module)
        check_graph(self._graph, module)
        if x is not None or y is not None:
            if x is None or y is None:
                raise ValueError("x and y must be given together (training input and target)")
            self.record_ranges(x, y)
        self.check()

    def forward(self, x: Tensor) -> Tensor:
        """The module's output: x (batch, time) -> y (batch, time)."""
        return self.module(x)

    def __getstate__(self) -> dict:
        """Pickled (``torch.save``, ``copy.deepcopy``) without the traced graph, which
        :meth:`__setstate__` traces again."""
        state = dict(self.__dict__)
        state.pop("_graph", None)
        return state

    def __setstate__(self, state: dict) -> None:
        super().__setstate__(state)
        self._graph = _trace(self.module)

    def _example(self, dtype: torch.dtype) -> Tensor:
        """A random walk of shape :data:`EXAMPLE` in the recorded input range (else [-1, 1])."""
        g = torch.Generator().manual_seed(0)
        w = torch.randn(EXAMPLE, generator=g, dtype=torch.float64).cumsum(1)
        lo, hi = float(self.in_min), float(self.in_max)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            lo, hi = -1.0, 1.0
        return (lo + (hi - lo) * torch.sigmoid(w)).to(dtype)

    def check(self) -> None:
        """Run the module on an example (:data:`EXAMPLE`, the module's dtype) and its composed
        step sample by sample, node by node (run when composed; again after training where
        the weights may have made a layer fail).

        Raises:
            ValueError: naming the first node whose shape or per-sample value differs.
        """
        dtype = _dtype(self.module)
        x = self._example(dtype)
        shapes = shape_pass(self._graph, self.module, x)
        self._tails = leaf_tails(self._graph, self.module, shapes)
        step, env = build_step(self._graph, self.module, self._tails, dtype)
        check_causal(self._graph, self.module, shapes, step, env, x)

    def record_ranges(self, x: Tensor, y: Tensor, *, mask: Tensor | None = None) -> None:
        """Record the training data's ranges as the compensator reads them
        (:mod:`torchhys.deploy.ranges`): ``in_min``, ``in_max`` of x, ``out_min``,
        ``out_max`` of y and ``trend``, their correlation coefficient (as
        :meth:`~torchhys.InverseHysteresisNet.fit_normalization` does); the member of
        :class:`~torchhys.protocols.SequenceModel` that the full-batch fit and the Lightning
        module call on the training data.

        Args:
            x, y: (batch, time) or (time,), the same shape, finite, not constant.
            mask: the samples the ranges are taken over, bool, the shape of x (batch, time)
                (False: left out, e.g. a held-out block or a row's padding); None: all.

        Raises:
            ValueError: other shapes, fewer than 2 samples, a constant x or y, a bad mask.
        """
        xb, _ = as_batched_sequence(x, "x")
        yb, _ = as_batched_sequence(y, "y")
        if yb.shape != xb.shape:
            raise ValueError(f"y must have the shape of x {tuple(xb.shape)}, got {tuple(y.shape)}")
        xs, ys = xb.detach().double(), yb.detach().double()
        if mask is not None:
            m = fitted_samples(mask, tuple(xb.shape), 0).to(xb.device)
            xs, ys = xs[m], ys[m]
        xs, ys = xs.flatten(), ys.flatten()
        if xs.numel() < 2:
            raise ValueError(f"x must hold at least 2 samples, got shape {tuple(x.shape)}"
                             + ("" if mask is None else f" with {xs.numel()} in its mask"))
        for name, v in (("x", xs), ("y", ys)):
            if float(v.std()) == 0.0:
                raise ValueError(f"{name} is constant (std 0): it has no range to record")
        for name, value in zip(RANGES, training_ranges(xs, ys), strict=True):
            getattr(self, name).fill_(value)

    def composed_step(self, dtype: torch.dtype) -> ComposedStep:
        """The composed step with the current weights (detached) in ``dtype``."""
        step, _ = build_step(self._graph, self.module, self._tails, dtype)
        return step

    def streaming_steps(self, dtype: torch.dtype) -> list[ComposedStep]:
        """``[self.composed_step(dtype)]`` (:class:`~torchhys.protocols.Deployable`)."""
        return [self.composed_step(dtype)]

    def streaming_head(self, dtype: torch.dtype) -> nn.Module:
        """:class:`LastFeature`: the compensator's features ``[x, y]`` -> y (batch, 1)."""
        return LastFeature()


def compose(module: nn.Module, *, x: Tensor | None = None,
            y: Tensor | None = None) -> Composed:
    """``module`` (x (batch, time) -> y (batch, time)) of hysteresis operators, recurrent
    layers and elementwise maths as a deployable :class:`Composed` (see its docstring)::

        model = compose(MyModel(), x=x_train, y=y_train)
        comp = StreamingCompensator(model)

    Raises:
        ValueError, TypeError: as :class:`Composed`.
    """
    return Composed(module, x=x, y=y)
