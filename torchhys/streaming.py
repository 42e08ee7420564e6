"""A deployable, sample-by-sample compensator built from a trained inverse model.

:class:`StreamingCompensator` turns an :class:`~torchhys.InverseHysteresisNet` (any causal
mix of :class:`~torchhys.EIHO`, :class:`~torchhys.ZhaoTanOperator`, :class:`~torchhys.Backlash`
and :class:`~torchhys.PrandtlIshlinskii` operators) or a
:class:`~torchhys.PrandtlIshlinskiiInverse` into a module that takes the desired output in
physical units, one sample at a time, and returns the saturated actuator command. It is
written for export (explicit tensor state, no data-dependent Python control flow): see
:mod:`torchhys.export`.

Safety: the command is saturated to ``[low, high]``; a NaN or inf input sample (or a
command that would not be finite) holds the last valid command, leaves the operator state
as it was and is counted (:meth:`StreamingCompensator.nonfinite_count`).
"""

import copy
import math
from collections.abc import Sequence

import torch
from torch import Tensor, nn

from torchhys._streaming_ops import BranchStep, PIStep, PlayStep
from torchhys.backlash import Backlash
from torchhys.eiho import EIHO, ZhaoTanOperator
from torchhys.networks import InverseHysteresisNet
from torchhys.prandtl_ishlinskii import PrandtlIshlinskii, PrandtlIshlinskiiInverse

__all__ = ["StreamingCompensator", "default_limits"]

#: Leading state tensors: F (batch, S) float, I (batch, K) long, started (batch, 1) bool.
N_SAFETY_STATE = 3


class _NetHead(nn.Module):
    """The network with its normalization folded into the layers: ``addmm``, activation, ``mm``.

    ``(f - mean) / std`` is folded into the hidden layer and ``out * std + mean`` into the
    output layer (in float64, then cast), which changes the result by float rounding only.
    The output bias rides on one extra hidden unit whose activation is exactly 1 (zero input
    weights, a bias where the activation saturates to 1 in the dtype: sigmoid, tanh, relu),
    so the output layer is one ``mm``. The hidden layer is an ``addmm`` of ``Yn`` (which
    TorchScript's executor runs as ``mm`` + ``add``, still cheaper than ``linear`` and its
    bias copy) plus one ``addcmul`` for a single other feature. For GELU (no such unit) the
    output layer is a ``linear``.
    """

    #: the extra unit has zero input weights: a NaN or inf sample makes it NaN (0 * inf),
    #: so a non-finite command catches the sample (for GELU: a zero-weight input column)
    sentinel: bool = True

    def __init__(self, net: InverseHysteresisNet) -> None:
        super().__init__()
        dtype = net.output.weight.dtype
        self.activation = copy.deepcopy(net.activation)
        with torch.no_grad():
            w1, b1 = net.hidden.weight.double(), net.hidden.bias.double()
            mean, std = net.in_mean.double(), net.in_std.double()
            w2, b2 = net.output.weight.double(), net.output.bias.double()
            o_mean, o_std = net.out_mean.double(), net.out_std.double()
            w1s = w1 / std
            b1f = b1 - w1 @ (mean / std)
            w2f, b2f = w2 * o_std, b2 * o_std + o_mean
            level = 40.0 if not isinstance(self.activation, nn.ReLU) else 1.0
            one = self.activation(torch.tensor([level], dtype=dtype))
            self.unit: bool = bool(one.item() == 1.0)
            if self.unit:
                w1s = torch.cat([w1s, w1s.new_zeros(1, w1s.shape[1])])
                b1f = torch.cat([b1f, b1f.new_full((1,), level)])
                w2f = torch.cat([w2f, b2f.reshape(1, 1)], 1)
                b2f = b2f.new_zeros(1)
            else:  # a zero-weight copy of the sample as the last input column
                w1s = torch.cat([w1s, w1s.new_zeros(w1s.shape[0], 1)], 1)
            # (hidden, network features): the source of ``columns``
            self.register_buffer("w1", w1s.to(dtype))
            self.register_buffer("b1", b1f.to(dtype))
            self.register_buffer("w2", w2f.to(dtype))
            self.register_buffer("w2t", w2f.t().contiguous().to(dtype))
            self.register_buffer("b2", b2f.to(dtype))
            # the compensator's input blocks (set by ``columns``)
            self.register_buffer("w_yt", w1s.new_zeros(0, w1s.shape[0]).to(dtype))
            self.register_buffer("w_et", w1s.new_zeros(0, w1s.shape[0]).to(dtype))
            self.register_buffer("w_e0", w1s.new_zeros(w1s.shape[0]).to(dtype))

    def columns(self, y_cols: list[int], e_cols: list[int], scales: list[float]) -> None:
        """Weights for the compensator's inputs: ``Yn`` (batch, len(y_cols)) and the appended
        (batch, 1) features, ``e_cols`` of them. Each entry is a network feature index, or
        -1 for a column of weight 0; ``scales`` (one per network feature) is a factor a step
        leaves to the network, folded into its weight column."""
        w = self.w1 if self.unit else self.w1[:, :-1]

        def block(cols: list[int]) -> Tensor:
            out = w.new_zeros(w.shape[0], len(cols))
            for j, c in enumerate(cols):
                if c >= 0:
                    out[:, j] = (w[:, c].double() * scales[c]).to(w.dtype)
            return out

        self.w_yt = block(y_cols).t().contiguous()
        self.w_et = block(e_cols).t().contiguous()
        self.w_e0 = self.w_et[0].clone() if len(e_cols) > 0 else w.new_zeros(w.shape[0])

    def forward(self, Yn: Tensor, feats: list[Tensor]) -> Tensor:
        """``Yn`` (batch, n) and (batch, 1) features -> (batch, 1)."""
        z = torch.addmm(self.b1, Yn, self.w_yt)
        if len(feats) == 1:  # (batch, 1) * (hidden,): no concatenation
            z = torch.addcmul(z, feats[0], self.w_e0)
        elif len(feats) > 1:
            z = torch.addmm(z, torch.cat(feats, 1), self.w_et)
        h = self.activation(z)
        if self.unit:
            return torch.mm(h, self.w2t)
        return torch.nn.functional.linear(h, self.w2, self.b2)


class _PIHead(nn.Module):
    """``u = w0 y + sum_i w_i z_i`` of an analytic Prandtl-Ishlinskii inverse: one ``mm``
    of ``Yn`` (the input's column and the plays)."""

    sentinel: bool = False
    unit: bool = False

    def __init__(self, inverse: PrandtlIshlinskiiInverse) -> None:
        super().__init__()
        self.register_buffer("w_y", torch.cat([inverse.linear_weight.detach().reshape(1),
                                               inverse.weights.detach()]).unsqueeze(1))

    def forward(self, Yn: Tensor, feats: list[Tensor]) -> Tensor:
        """``Yn`` (batch, 1 + n plays) -> (batch, 1)."""
        return torch.mm(Yn, self.w_y)


def _threshold(op: nn.Module) -> Tensor:
    th = op.threshold.detach()
    if bool(torch.isnan(th)):
        raise ValueError(
            f"{type(op).__name__} has threshold='auto' but was never calibrated: call "
            "calibrate_threshold(x) (or fit_normalization) before building a compensator"
        )
    return th


def _step_module(op: nn.Module, dtype: torch.dtype) -> nn.Module:
    branch = getattr(op, "output", "level") == "branch"  # re-based output f - f(x_e)
    if isinstance(op, EIHO):
        if op.per_segment:
            raise ValueError(
                "EIHO(a='segment') cannot be deployed: its per-segment coefficients come from "
                "the target's next extremum (not causal). Train with a fixed or learnable a."
            )
        r = 0.5 * _threshold(op).to(dtype)
        if hasattr(op, "anchor_slope"):  # a_d exp(k_d (x_e - c) / s), as EIHO.forward folds it
            with torch.no_grad():
                slope = op.anchor_slope / op.anchor_norm[1]
                a = op.coefficient() * torch.exp(-slope * op.anchor_norm[0])
            return BranchStep("eiho", op.rule, a.to(dtype), r, op.max_depth, op.eps, 1.0,
                              slope.to(dtype), branch=branch)
        a = op.coefficient().detach().to(dtype).reshape(-1).expand(2)
        return BranchStep("eiho", op.rule, a, r, op.max_depth, op.eps, 1.0, branch=branch)
    if isinstance(op, ZhaoTanOperator):
        r = 0.5 * (_threshold(op) / op.scale).to(dtype)
        return BranchStep("zhao_tan", op.rule, torch.ones(2, dtype=dtype), r, op.max_depth,
                          0.0, op.scale, branch=branch)
    if isinstance(op, Backlash):
        return PlayStep(0.5 * op.get_widths().detach().to(dtype))
    if isinstance(op, PrandtlIshlinskii):
        return PIStep(0.5 * op.get_widths().detach().to(dtype), op.weights.detach().to(dtype),
                      op.linear_weight.detach().to(dtype))
    raise TypeError(
        "StreamingCompensator supports EIHO, ZhaoTanOperator, Backlash and PrandtlIshlinskii "
        "operators, got "
        f"{type(op).__name__}"
    )


def default_limits(model: nn.Module) -> tuple[float, float]:
    """Command limits of a model: its recorded training-target range.

    Uses ``model.out_min`` / ``model.out_max`` (the training targets' range, recorded by
    :meth:`~torchhys.InverseHysteresisNet.fit_normalization`) when they are known, else,
    for a network saved before the range was recorded, ``out_mean +/- 3 out_std``.

    Raises:
        ValueError: the model records no output range (a :class:`PrandtlIshlinskiiInverse`,
            or a network whose normalization was never fitted): pass ``limits=``.
    """
    lo, hi = getattr(model, "out_min", None), getattr(model, "out_max", None)
    if isinstance(lo, Tensor) and isinstance(hi, Tensor):
        low, high = float(lo), float(hi)
        if math.isfinite(low) and math.isfinite(high) and low < high:
            return low, high
    if isinstance(model, InverseHysteresisNet):
        mean, std = float(model.out_mean), float(model.out_std)
        if not (mean == 0.0 and std == 1.0):
            return mean - 3.0 * std, mean + 3.0 * std
    raise ValueError(
        f"{type(model).__name__} records no training output range (normalization not fitted, "
        "or an analytic inverse): pass limits=(low, high) in command units"
    )


def _check_limits(limits: Sequence[float]) -> tuple[float, float]:
    if isinstance(limits, (str, bytes)) or len(limits) != 2:
        raise ValueError(f"limits must be a pair (low, high), got {limits!r}")
    low, high = (float(v) for v in limits)
    if not (math.isfinite(low) and math.isfinite(high) and low < high):
        raise ValueError(f"limits must be finite with low < high, got ({low}, {high})")
    return low, high


class StreamingCompensator(nn.Module):
    """A causal feedforward compensator, one sample at a time, in physical units.

    Args:
        model: a trained :class:`~torchhys.InverseHysteresisNet` (causal operators only) or
            a :class:`~torchhys.PrandtlIshlinskiiInverse`. Parameters are copied (detached).
        limits: ``(low, high)`` saturation of the command; default :func:`default_limits`.
        initial_command: command held before the first finite input (saturated).

    Methods (all exported):
        ``forward(x)``: x (time,) or (batch, time) -> u of the same shape, from a fresh state
        (does not touch the stored state). ``step(x_t)``: x_t (batch,) -> u_t (batch,),
        advancing the stored state. ``reset()``. ``nonfinite_count()``: (batch,) long.
        ``step_explicit(x_t, state) -> (u_t, state)`` and ``initial_state(batch)``: the same
        step with the state passed explicitly (a list of tensors, all zeros when fresh).

    Raises:
        ValueError: a non-causal operator (``EIHO(a="segment")``), an uncalibrated
            ``threshold="auto"``, bad ``limits``.
        TypeError: an unsupported model or operator.
    """

    templates: list[Tensor]
    state: list[Tensor]
    n_steps: int

    def __init__(
        self, model: InverseHysteresisNet | PrandtlIshlinskiiInverse, *,
        limits: Sequence[float] | None = None, initial_command: float = 0.0,
    ) -> None:
        super().__init__()
        if isinstance(model, InverseHysteresisNet):
            dtype = model.output.weight.dtype
            ops = [_step_module(op, dtype) for op in model.operators]
            self.head = _NetHead(model)
        elif isinstance(model, PrandtlIshlinskiiInverse):
            dtype = model.weights.dtype
            if model.widths.numel() == 0:
                raise ValueError("a purely linear PrandtlIshlinskiiInverse needs no compensator")
            ops = [PlayStep(0.5 * model.widths.detach().to(dtype))]
            self.head = _PIHead(model)
        else:
            raise TypeError(
                "StreamingCompensator needs an InverseHysteresisNet or a "
                f"PrandtlIshlinskiiInverse, got {type(model).__name__}"
            )
        low, high = _check_limits(default_limits(model) if limits is None else limits)
        self.ops = nn.ModuleList(ops)
        self.register_buffer("low", torch.tensor(low, dtype=dtype))
        self.register_buffer("high", torch.tensor(high, dtype=dtype))
        u0 = min(max(float(initial_command), low), high)
        # with u0 = +0.0 the fresh held column (zero) is the initial command
        self.u0_zero: bool = u0 == 0.0 and math.copysign(1.0, u0) > 0
        self.sentinel: bool = bool(self.head.sentinel)
        self.head_unit: bool = bool(getattr(self.head, "unit", False))
        self.register_buffer("u0", torch.tensor(u0, dtype=dtype))
        self._layout(ops, dtype)
        self.state = self.initial_state(1)
        self.n_steps = 0

    def _layout(self, ops: list[nn.Module], dtype: torch.dtype) -> None:
        """Place every step's columns in the packed state ``[F, I, started(, F64)]``.

        ``F = [last x, Y, op blocks..., held command]`` with ``Y = [x, all plays of x]``
        (the plays of every step, the EIHO's turning-point detectors included) and ``I =
        [nonfinite count, op blocks...]``. ``keep`` marks the ``F`` columns that a fresh row
        does not anchor at its first finite sample; ``w_started``/``w_fresh`` give each column
        its half-width in the compensator's one ``clamp`` (plays: their own; every other
        column: the dtype's largest finite value, which leaves it as it is; anchored
        columns: 0 until the row has started, which sets them to the sample).
        """
        n_y = 1 + sum(op.n_play for op in ops)
        y, f, i, g = 1, 1 + n_y, 1, 0
        keep_y: list[bool] = [True]
        keep_f: list[bool] = []
        sizes = [1, n_y]
        for op in ops:
            op.place(y, f, i, g)
            op.p0 = len(sizes)
            sizes += op.pieces()
            ay, af = op.anchors()
            keep_y += [not v for v in ay]
            keep_f += [not v for v in af]
            y, f, i, g = y + op.n_play, f + op.n_float, i + op.n_int, g + op.n_f64
        self.sizes: list[int] = sizes + [1]
        # the network reads all of Yn (weight 0 for detectors and PI plays) and each other
        # step's (batch, 1) feature
        y_cols, e_cols, scales, k = [0] + [-1] * (n_y - 1), [], [1.0], 1
        for op in ops:
            for j, c in enumerate(op.network_columns()):
                if c < 0:
                    y_cols[op.y0 + j] = k
                else:
                    e_cols.append(k)
                scales.append(getattr(op, "feature_scale", 1.0))
                k += 1
        self.sentinel_column: bool = self.sentinel and not self.head_unit
        if self.sentinel_column:  # the sample, weight 0
            e_cols.append(-1)
        if isinstance(self.head, _NetHead):
            self.head.columns(y_cols, e_cols, scales)
        self.n_y: int = n_y
        # the (batch,) sample is needed by all operators but plays and the threshold-0
        # re-based recent EIHO, which work on (batch, 1) columns
        self.need_xs: bool = any(
            not isinstance(op, PlayStep) and not (isinstance(op, BranchStep) and op.fast
                                                  and op.r_zero) for op in ops)
        # the EIHO steps with a detector in Y read its previous value, anchored
        self.need_old_y: bool = any(
            isinstance(op, BranchStep) and op.eiho and op.n_play > 0 for op in ops)
        self.n_f64 = g
        self.n_int: int = i
        self.anchoring = not all(keep_y + keep_f)
        # "last x" (column 0) is anchored when anything is: the fast steps' previous sample
        keep = torch.tensor([not self.anchoring] + keep_y + keep_f + [True])
        self.register_buffer("keep", keep)
        self.held: int = f  # the held command, last column of F
        r = [op.play_r for op in ops if op.n_play > 0]
        r_y = torch.cat([torch.zeros(1, dtype=dtype)] + [t.to(dtype) for t in r])
        # any other column keeps its value (unless it differs from the sample by more than
        # the largest finite value)
        big = torch.finfo(dtype).max
        width = torch.full((f + 1,), big, dtype=dtype)
        width[1:1 + n_y] = r_y
        self.register_buffer("w_started", width)
        self.register_buffer("w_fresh", torch.where(keep, width, torch.zeros_like(width)))
        self.templates = [torch.zeros(1, f + 1, dtype=dtype), torch.zeros(1, i, dtype=torch.long),
                          torch.zeros(1, 1, dtype=torch.bool)]
        if g > 0:
            self.templates.append(torch.zeros(1, g, dtype=torch.float64))

    @torch.jit.export
    def initial_state(self, batch: int) -> list[Tensor]:
        """Fresh state for ``batch`` rows: ``[F (batch, S), I (batch, K) long, started
        (batch, 1) bool]`` (and ``F64 (batch, n)`` with ``"recent"``-rule operators), zeros."""
        return [t.new_zeros([batch] + list(t.shape[1:])) for t in self.templates]

    def _advance(self, x: Tensor, state: list[Tensor]
                 ) -> tuple[Tensor, Tensor, list[Tensor], Tensor, Tensor]:
        """The shared first part of a step: ``(xc, Fc, parts, Y, Yn)``.

        ``Fc`` is the state with every play advanced and a fresh row's anchored columns set
        to the sample, by one ``clamp``; ``parts`` its split into ``[last x, Yn, step
        pieces..., held command]``; ``Y`` the plays before the step, anchored (only when a
        step reads them, else ``Yn``).
        """
        F0, started = state[0], state[2]
        xc = x.unsqueeze(1)
        # a NaN or inf sample runs through (its state and command are discarded later)
        # a where on the bool flag (an arithmetic blend would first convert it to float)
        w = torch.where(started, self.w_started, self.w_fresh) if self.anchoring \
            else self.w_started
        Fc = torch.clamp(F0, xc - w, xc + w)
        parts = Fc.split_with_sizes(self.sizes, 1)
        Yn = parts[1]
        Y = Yn
        if self.need_old_y:
            Y = torch.where(started | self.keep, F0, xc).narrow(1, 1, self.n_y)
        return xc, Fc, parts, Y, Yn

    @torch.jit.export
    def step_explicit(self, x: Tensor, state: list[Tensor]) -> tuple[Tensor, list[Tensor]]:
        """One sample with an explicit state: x (batch,) -> (u (batch,), new state)."""
        F0, I, started = state[0], state[1], state[2]
        F64 = state[3] if self.n_f64 > 0 else F0
        xc, F, parts, Y, Yn = self._advance(x, state)
        xs = xc.select(1, 0) if self.need_xs else x
        feats: list[Tensor] = []
        fl: list[Tensor] = [xc, Yn]
        il: list[Tensor] = []
        gl: list[Tensor] = []
        for op in self.ops:
            op.step(xs, xc, Y, Yn, F, I, F64, started, parts, feats, fl, il, gl)
        if self.sentinel_column:
            feats.append(xc)
        u = torch.clamp(self.head(Yn, feats), self.low, self.high)
        if not self.sentinel:
            u = u + (xc - xc)  # NaN from a NaN or inf sample
        bad = u != u  # a non-finite sample or command (after the clamp only NaN is left)
        fl.append(u)
        # a bad sample leaves the whole state as it was (the held command included)
        F_new = torch.where(bad, F0, torch.cat(fl, 1))
        if self.n_int == 1:  # the counter is the whole of I
            I_new = I + bad
        else:
            I_new = torch.cat([I.narrow(1, 0, 1) + bad, torch.where(
                bad, I.narrow(1, 1, self.n_int - 1), torch.cat(il, 1))], 1)
        new = [F_new, I_new, started >= bad]  # started | not bad
        if self.n_f64 > 0:
            new.append(torch.where(bad, F64, torch.cat(gl, 1)))
        if self.u0_zero:  # the held column is the command (zero before the first valid one)
            return F_new.select(1, self.held), new
        u = torch.where(bad, torch.where(started, F0.narrow(1, self.held, 1), self.u0),
                        u)
        return u.select(1, 0), new

    @torch.jit.export
    def step(self, x_t: Tensor) -> Tensor:
        """Advance the stored state by one sample: x_t (batch,) -> command (batch,)."""
        if x_t.dim() != 1:
            raise ValueError(
                "step expects one sample per row, shape (batch,), got shape " + str(x_t.shape)
            )
        if x_t.shape[0] != self.state[0].shape[0]:
            if self.n_steps != 0:
                raise ValueError(
                    "step: batch " + str(x_t.shape[0]) + " differs from the running batch "
                    + str(self.state[0].shape[0]) + "; call reset() first"
                )
            self.state = self.initial_state(x_t.shape[0])
        if x_t.dtype != self.low.dtype:  # a call even when it would return x_t itself
            x_t = x_t.to(self.low.dtype)
        u, s = self.step_explicit(x_t, self.state)
        self.state = s
        self.n_steps += 1
        return u

    @torch.jit.export
    def reset(self) -> None:
        """Back to the fresh state (the counter too); the next ``step`` may change the batch."""
        self.state = self.initial_state(self.state[0].shape[0])
        self.n_steps = 0

    @torch.jit.export
    def nonfinite_count(self) -> Tensor:
        """Samples held because the input (or the command) was NaN or inf, per row (batch,)."""
        return self.state[1][:, 0]

    def forward(self, x: Tensor) -> Tensor:
        """Commands for a whole sequence from a fresh state: (time,) or (batch, time)."""
        if x.dim() not in (1, 2):
            raise ValueError(
                "x must have shape (time,) or (batch, time), got shape " + str(x.shape)
            )
        xb = x.to(self.low.dtype)
        if x.dim() == 1:
            xb = xb.unsqueeze(0)
        state = self.initial_state(xb.shape[0])
        outs: list[Tensor] = []
        for xt in xb.unbind(1):
            u, state = self.step_explicit(xt, state)
            outs.append(u)
        if len(outs) == 0:
            return x.to(self.low.dtype)
        y = torch.stack(outs, dim=1)
        return y[0] if x.dim() == 1 else y
