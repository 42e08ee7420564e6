"""A deployable, sample-by-sample compensator built from a trained inverse model.

:class:`StreamingCompensator` turns a model into a module that takes the desired output in
physical units, one sample at a time, and returns the saturated actuator command. A model
provides ``streaming_steps(dtype) -> list[OperatorStep]`` (one per-sample step per operator,
see :mod:`torchhys.operator`) and ``streaming_head(dtype)``, a module from the features
``[x, step features...]`` (batch, n) to the command (batch, 1):
:class:`~torchhys.InverseHysteresisNet` (any causal operators) and
:class:`~torchhys.PrandtlIshlinskiiInverse` do. It is written for export (explicit tensor
state, no data-dependent Python control flow): see :mod:`torchhys.deploy.export`.

Safety: the command is saturated to ``[low, high]``; a NaN or inf input sample (or a
command that would not be finite) holds the last valid command, leaves the whole state as it
was and is counted (:meth:`StreamingCompensator.nonfinite_count`). A finite input is clamped
to the training input range widened by a margin (``input_margin``, 5 % of the range by
default) before the model sees it, and counted when it lay outside
(:meth:`StreamingCompensator.out_of_range_count`): the model never extrapolates past what it
was trained on. The command never moves against the model's direction (``direction``: by
default the sign of the target's trend in the input, recorded when the network's
normalization was fitted, where that trend is clear:
:func:`~torchhys.deploy.ranges.default_direction`): while the (clamped) input rises, the
command of a rising compensator does not fall, while it falls the command does not rise, and
while it stays the command stays. On a model that is monotone in
its current input this guard changes nothing; on one that is not, it holds the command where
the model would turn the wrong way.

The state (a published contract: the exported metadata ``state_spec`` repeats it) is a list
of tensors, all zeros when fresh; the steps' blocks are packed by kind, in the order of the
steps and of their ``state_spec``::

    index  name      dtype               shape             columns
    -----  --------  ------------------  ----------------  ------------------------------------
    0      F         compensator dtype   (batch, 1+nF+g)   [held command | float blocks ... |
                                                           last clamped input (guard only)]
    1      I         int64               (batch, 1+nI+c)   [held-sample counter | int64 blocks
                                                           | out-of-range counter (clamp only)]
    2      started   bool                (batch, 1)        a finite sample has arrived
    3      F64       float64             (batch, nG)       [float64 blocks ...] (only if nG > 0)

(``g`` is 1 with the direction guard, ``c`` is 1 with the input clamp, else 0.)

At a row's first finite sample every block column is set to ``start + from_sample * x``
(its :class:`~torchhys.step.StateBlock`) before the steps run; a step with a start of
its own (a cascade) starts from its ``initial_state(x)`` instead.
"""

import math
from collections.abc import Sequence
from typing import Any, Final

import torch
from torch import Tensor, nn

from torchhys._checks import check_choice, check_real
from torchhys._deprecated import moved as _moved
from torchhys.deploy._slots import (
    _KIND_INDEX,
    _model_dtype,
    _Slot,
    check_state,
    checked_step,
    conditions_of,
    layout_rows,
)
from torchhys.deploy._threads import StepLock
from torchhys.deploy.ranges import _check_limits, _condition_bounds, _direction, _input_bounds
from torchhys.deploy.ranges import default_limits as _default_limits
from torchhys.protocols import check_deployable, n_conditions
from torchhys.step import OperatorStep

__all__ = ["COUNTER", "HELD", "STARTED", "STATE_F", "STATE_F64", "STATE_I", "StreamingCompensator"]

# the limits, input range and direction of a model live in torchhys.deploy.ranges; their
# earlier path here still works, with a DeprecationWarning
__getattr__ = _moved(__name__, dict.fromkeys(
    ("DIRECTIONS", "MIN_TREND", "default_direction", "default_input_range", "default_limits"),
    "torchhys.deploy.ranges"))


#: index of each state tensor in the state list
STATE_F, STATE_I, STATE_STARTED, STATE_F64 = 0, 1, 2, 3
#: (tensor, column) of the held command and of the counter of held non-finite samples
HELD = (STATE_F, 0)
COUNTER = (STATE_I, 0)
STARTED = (STATE_STARTED, 0)

#: the class ``StreamingCompensator(..., adapt=...)`` builds (torchhys.deploy.adaptive's)
_ADAPTIVE: list[type] = []


class StreamingCompensator(nn.Module):
    """A causal feedforward compensator, one sample at a time, in physical units.

    Args:
        model: a trained :class:`~torchhys.InverseHysteresisNet` (causal operators only), a
            :class:`~torchhys.PrandtlIshlinskiiInverse`, or any module with
            ``streaming_steps(dtype)`` and ``streaming_head(dtype)``. Parameters are copied.
        limits: ``(low, high)`` saturation of the command; default
            :func:`~torchhys.deploy.ranges.default_limits`.
        initial_command: command held before the first finite input (saturated).
        input_range: ``(low, high)`` of the training input; default: the model's recorded
            range (:func:`~torchhys.deploy.ranges.default_input_range`; none recorded: no clamp).
        input_margin: the input is clamped to ``input_range`` widened by this share of its
            width on each side (default 0.05); None: no clamp.
        direction: ``"auto"`` (default: the model's recorded direction where the training
            data have a clear one, :func:`~torchhys.deploy.ranges.default_direction`; else
            no guard), ``"increasing"``, ``"decreasing"`` (the command never moves against
            the input's direction, resp. with it), or ``"none"`` (no guard).
        adapt: ``"none"`` (default), or ``"rls"`` / ``"nlms"``: the compensator built is an
            :class:`~torchhys.deploy.adaptive.AdaptiveCompensator` (its options then too).

    Methods (all exported):
        ``forward(x)``: x (time,) or (batch, time) -> u of the same shape, from a fresh state
        (does not touch the stored state). ``step(x_t)``: x_t (batch,) -> u_t (batch,),
        advancing the stored state. ``reset()``. ``nonfinite_count()``: (batch,) long.
        ``out_of_range_count()``: finite inputs clamped, (batch,) long (zeros without a
        clamp).
        ``step_explicit(x_t, state) -> (u_t, state)`` and ``initial_state(batch)``: the same
        step with the state passed explicitly (see the module docstring for its layout).

    Raises:
        ValueError: a non-causal operator (``SegmentEIHO``), an uncalibrated
            ``threshold="auto"``, bad ``limits``, ``input_range``, ``input_margin`` or
            ``direction``, a non-finite ``initial_command``.
        TypeError: a model without streaming steps, or a step outside the protocol.
    """

    templates: list[Tensor]
    state: list[Tensor]
    n_steps: int
    sizes: list[list[int]]
    anchor: list[bool]
    # the state layout's named positions (module docstring), constants of the scripted module
    STATE_F: Final[int] = STATE_F
    STATE_I: Final[int] = STATE_I
    STATE_STARTED: Final[int] = STATE_STARTED
    STATE_F64: Final[int] = STATE_F64
    HELD_COLUMN: Final[int] = HELD[1]
    COUNTER_COLUMN: Final[int] = COUNTER[1]
    clamp_input: bool
    guard: bool
    n_conditions: Final[int]
    clamp_conditions: Final[bool]
    # one step at a time: a Python lock in eager mode (not scripted), and in the scripted
    # module a flag and a ticket that tell a step begun while another runs (see step)
    __jit_ignored_attributes__ = ["_step_lock"]
    stepping: bool
    calls: int
    state_names: list[str]
    CONCURRENT: Final[str] = (
        "step: another step of this compensator is running (a call from another thread): "
        "use one compensator per thread, or a lock around its calls; reset() clears this "
        "after a step that failed")

    def __new__(cls, *args: Any, adapt: str = "none", **kwargs: Any) -> "StreamingCompensator":
        """``adapt="rls"`` or ``"nlms"`` (with the adaptive options) builds an
        :class:`~torchhys.deploy.adaptive.AdaptiveCompensator`."""
        if cls is StreamingCompensator and adapt != "none":
            cls = _ADAPTIVE[0]  # torchhys.deploy (its __init__) imports and registers it
        return super().__new__(cls)

    def __init__(
        self, model: nn.Module, *, limits: Sequence[float] | None = None,
        initial_command: float = 0.0, input_range: Sequence[float] | None = None,
        input_margin: float | None = 0.05, direction: str = "auto",
        condition_ranges: Sequence[Sequence[float]] | None = None, adapt: str = "none",
    ) -> None:
        check_choice(adapt, "adapt", ["none", "rls", "nlms"])
        super().__init__()
        check_deployable(model, "model")
        dtype = _model_dtype(model)
        self.n_conditions = n_conditions(model)
        steps = [checked_step(s, i, self.n_conditions)
                 for i, s in enumerate(model.streaming_steps(dtype))]
        self.head = model.streaming_head(dtype)
        low, high = _check_limits(_default_limits(model) if limits is None else limits)
        self.register_buffer("low", torch.tensor(low, dtype=dtype))
        self.register_buffer("high", torch.tensor(high, dtype=dtype))
        u0 = min(max(check_real(initial_command, "initial_command"), low), high)
        self.register_buffer("u0", torch.tensor(u0, dtype=dtype))
        self.register_buffer("zero", torch.zeros((), dtype=dtype))  # the hold test's 0
        # with u0 = +0.0 the fresh state's held column (zeros) already holds the initial command
        self.u0_zero: bool = u0 == 0.0 and math.copysign(1.0, u0) > 0
        bounds = _input_bounds(model, input_range, input_margin)
        self.clamp_input = bounds is not None
        lo_in, hi_in = (-math.inf, math.inf) if bounds is None else bounds
        self.register_buffer("in_low", torch.tensor(lo_in, dtype=dtype))
        self.register_buffer("in_high", torch.tensor(hi_in, dtype=dtype))
        cbounds = _condition_bounds(model, self.n_conditions, condition_ranges, input_margin)
        self.clamp_conditions = cbounds is not None
        n = self.n_conditions
        lo_c, hi_c = (torch.full((n,), -math.inf), torch.full((n,), math.inf)) if (
            cbounds is None) else cbounds
        self.register_buffer("cond_low", lo_c.to(dtype))
        self.register_buffer("cond_high", hi_c.to(dtype))
        self.clamp_input = self.clamp_input or self.clamp_conditions
        sign = _direction(model, direction)
        self.guard = sign != 0
        self.register_buffer("direction", torch.tensor(float(sign), dtype=dtype))
        self._layout(steps, dtype)
        self.state = self.initial_state(1)
        self.n_steps = 0
        self._step_lock = StepLock()
        self.stepping, self.calls = False, 0
        self.state_names = ["F (the float columns)", "I (the int64 counters)",
                            "started", "F64 (the float64 columns)"]

    def _layout(self, steps: list[OperatorStep], dtype: torch.dtype) -> None:
        """Pack the steps' blocks by kind (see the module docstring) and record, for each
        kind, the split sizes and each column's value at a row's first finite sample."""
        sizes: list[list[int]] = [[1], [], [1]]  # float: held command; int64: the counter
        start: list[list[float]] = [[0.0], [], [0.0]]
        sample: list[list[float]] = [[0.0], [], [0.0]]
        slots = []
        for step in steps:
            kinds, pieces = [], []
            for block in step.state_spec:
                k = _KIND_INDEX[block.kind]
                kinds.append(k)
                pieces.append(len(sizes[k]))
                sizes[k].append(block.size)
                start[k] += block.columns("start")
                sample[k] += block.columns("from_sample")
            slots.append(_Slot(step, kinds, pieces))
        self.slots = nn.ModuleList(slots)
        self.has_f64: bool = len(sizes[1]) > 0
        self.has_int: bool = len(sizes[2]) > 1  # int64 blocks besides the counter
        self.n_int: int = sum(sizes[2]) - 1
        # the compensator's own columns after the steps': the last clamped input (guard) and
        # the out-of-range counter (clamp); not anchored (set at a row's first step)
        if self.guard:
            sizes[0].append(1)
            start[0].append(0.0)
            sample[0].append(0.0)
        if self.clamp_input:
            sizes[2].append(1)
            start[2].append(0.0)
            sample[2].append(0.0)
        self.sizes = sizes
        dtypes = (dtype, torch.float64, torch.long)
        # anchoring at the first finite sample: start + from_sample * x, where not all zero
        self.anchor = [any(v != 0.0 for v in start[k] + sample[k]) for k in range(3)]
        for k, name in enumerate(("f", "g", "i")):
            self.register_buffer(f"start_{name}", torch.tensor(start[k], dtype=dtypes[k]))
            self.register_buffer(f"sample_{name}", torch.tensor(sample[k], dtype=dtypes[k]))
        self.templates = [torch.zeros(1, sum(sizes[0]), dtype=dtype),
                          torch.zeros(1, sum(sizes[2]), dtype=torch.long),
                          torch.zeros(1, 1, dtype=torch.bool)]
        if self.has_f64:
            self.templates.append(torch.zeros(1, sum(sizes[1]), dtype=torch.float64))

    def example_inputs(self, batch: int) -> list[tuple[str, Tensor]]:
        """The explicit step's inputs between x and the state, by name (zeros of their shape
        for ``batch`` rows): ``[("conditions", (batch, n))]`` for a conditioned model, else
        none; what the exporters trace and name."""
        if self.n_conditions == 0:
            return []
        return [("conditions", torch.zeros(batch, self.n_conditions, dtype=self.low.dtype))]

    @torch.jit.export
    def initial_state(self, batch: int) -> list[Tensor]:
        """Fresh state for ``batch`` rows (all zeros): ``[F, I, started(, F64)]``."""
        return [t.new_zeros([batch] + list(t.shape[1:])) for t in self.templates]

    def _anchored(self, t: Tensor, started: Tensor, x: Tensor, k: int, start: Tensor,
                  sample: Tensor) -> Tensor:
        """State tensor ``t`` with the rows that have not started set to their first-sample
        values (a row's first finite sample; a non-finite one is discarded later). ``x`` is
        in ``t``'s dtype."""
        if not self.anchor[k]:
            return t
        if k == 2:  # int64 blocks start at constants
            return torch.where(started, t, start)
        return torch.where(started, t, torch.addcmul(start, sample, x))

    @torch.jit.export
    def step_explicit(self, x: Tensor, state: list[Tensor],
                      conditions: Tensor | None = None) -> tuple[Tensor, list[Tensor]]:
        """One sample with an explicit state: x (batch,) (and the conditions (batch,
        n_conditions) of a conditioned model) -> (u (batch,), new state).

        Raises:
            ValueError: ``state`` has another number of tensors than :meth:`initial_state`,
                or a tensor of another dtype or shape (the message names it and what was
                expected);
                conditions missing, given to a model without, or of another shape.
        """
        self._check_state(x, state)
        c = conditions_of(x, conditions, self.n_conditions, self.low.dtype, "step_explicit", 2)
        return self._advance(x, state, c)

    def _check_state(self, x: Tensor, state: list[Tensor]) -> None:
        """ValueError unless ``state`` has the layout's tensors for x's batch."""
        check_state(x, state, self.templates, self.state_names)

    def _advance(self, x: Tensor, state: list[Tensor],
                 conditions: Tensor) -> tuple[Tensor, list[Tensor]]:
        """:meth:`step_explicit` of a state known to be of the layout (conditions (batch,
        n_conditions), or empty without conditions)."""
        features, new, xc, cc = self._features(x, state, conditions)
        return self._finish(x, state, conditions, self.head(features), new, xc, cc)

    def _features(self, x: Tensor, state: list[Tensor], conditions: Tensor
                  ) -> tuple[Tensor, list[list[Tensor]], Tensor, Tensor]:
        """The head's features ``[x, conditions..., step features...]`` (batch, n) of one
        sample, the steps' new blocks by kind, and the clamped x (batch, 1) and conditions."""
        F, I, started = state[self.STATE_F], state[self.STATE_I], state[self.STATE_STARTED]
        G = state[self.STATE_F64] if self.has_f64 else F
        xr = x.unsqueeze(1)
        xc = torch.clamp(xr, self.in_low, self.in_high) if self.clamp_input else xr
        xs = xc  # what a step of several inputs and the head see: x and the conditions
        cc = conditions
        if self.n_conditions > 0:
            if self.clamp_conditions:
                cc = torch.clamp(conditions, self.cond_low, self.cond_high)
            xs = torch.cat([xc, cc], 1)
        split_int = self.has_int or self.clamp_input
        parts = [
            self._anchored(F, started, xc, 0, self.start_f, self.sample_f).split_with_sizes(
                self.sizes[0], 1),
            self._anchored(G, started, xc.double(), 1, self.start_g, self.sample_g
                           ).split_with_sizes(self.sizes[1], 1) if self.has_f64 else [F],
            self._anchored(I, started, xc, 2, self.start_i, self.sample_i).split_with_sizes(
                self.sizes[2], 1) if split_int else [I],
        ]
        new: list[list[Tensor]] = [[], [], []]
        features = [xs]
        for slot in self.slots:
            features.append(slot(xs if slot.conditioned else xc, parts, new, started))
        return torch.cat(features, 1), new, xc, cc

    def _finish(self, x: Tensor, state: list[Tensor], conditions: Tensor, u: Tensor,
                new: list[list[Tensor]], xc: Tensor, cc: Tensor
                ) -> tuple[Tensor, list[Tensor]]:
        """The command (batch,) and the new state from the head's output ``u`` (batch, 1)
        and the steps' new blocks: the hold, the limits, the guard and the counters."""
        F, I, started = state[self.STATE_F], state[self.STATE_I], state[self.STATE_STARTED]
        G = state[self.STATE_F64] if self.has_f64 else F
        xr = x.unsqueeze(1)
        split_int = self.has_int or self.clamp_input
        # anything but a finite sample with a finite command holds the whole state (a
        # non-finite sample may still give a finite command through a saturating activation);
        # t - t is 0 exactly where t is finite (NaN for NaN and +/-inf): cheaper than isfinite.
        # (TorchScript: compared with a Python 0 the interpreter would wrap the 0 into a new
        # tensor at every step; self.zero is a constant of the frozen module.)
        if self.n_conditions > 0:  # a non-finite condition holds too
            bad = (xr - xr) + (u - u) + (conditions - conditions).sum(1, keepdim=True) != self.zero
        else:
            bad = (xr - xr) + (u - u) != self.zero
        u = torch.clamp(u, self.low, self.high)
        if self.guard:
            # the command may not move against the input's direction: d (u - held) has the
            # sign of x - previous x (d = +1 rising, -1 falling), and is 0 while the input
            # stays (the first sample of a row is free)
            d = self.direction
            held_u = F.narrow(1, self.HELD_COLUMN, 1)
            s = xc - F.narrow(1, F.shape[1] - 1, 1)
            v, vp = u * d, held_u * d
            g = torch.where(s > self.zero, torch.maximum(v, vp),
                            torch.where(s < self.zero, torch.minimum(v, vp), vp)) * d
            u = torch.where(started, g, u)
            F_new = torch.where(bad, F, torch.cat([u] + new[0] + [xc], 1))
        else:
            F_new = torch.where(bad, F, torch.cat([u] + new[0], 1))
        if self.u0_zero:  # the held column, zero when fresh, is the command to send
            u_out = F_new.select(1, self.HELD_COLUMN)
        else:
            held = F.narrow(1, self.HELD_COLUMN, 1)
            u_out = torch.where(bad, torch.where(started, held, self.u0), u).squeeze(1)
        if split_int:
            pieces = [I.narrow(1, self.COUNTER_COLUMN, 1) + bad]
            if self.has_int:
                pieces.append(torch.where(bad, I.narrow(1, 1, self.n_int), torch.cat(new[2], 1)))
            if self.clamp_input:  # finite samples outside the clamp's bounds
                outside = torch.ne(xr, xc) & torch.eq(xr - xr, self.zero)
                if self.clamp_conditions:  # a finite condition outside its bounds
                    c_out = torch.ne(conditions, cc) & torch.eq(conditions - conditions,
                                                                 self.zero)
                    outside = outside | (c_out.sum(1, keepdim=True) > 0)
                pieces.append(I.narrow(1, I.shape[1] - 1, 1) + outside)
            I_new = torch.cat(pieces, 1)
        else:  # the counter is all of I
            I_new = I + bad
        started_new = torch.ge(started, bad)  # started or not bad (for bools a >= b is a | ~b)
        if self.has_f64:
            return u_out, [F_new, I_new, started_new,
                           torch.where(bad, G, torch.cat(new[1], 1))]
        return u_out, [F_new, I_new, started_new]

    @torch.jit.export
    def step(self, x_t: Tensor, conditions: Tensor | None = None) -> Tensor:
        """Advance the stored state by one sample: x_t (batch,) (and the conditions (batch,
        n_conditions) of a conditioned model) -> command (batch,).

        Threads: in Python (not scripted) a lock makes the steps of several threads run one
        at a time. The scripted module holds no lock: use one per thread (``step_explicit``
        with a state of each thread's own is safe); a step begun while another runs is
        found in most cases and raises ``RuntimeError`` (:attr:`CONCURRENT`), leaving the
        state to the other step.
        """
        if torch.jit.is_scripting():
            return self._step(x_t, conditions)
        return self._locked(x_t, True, conditions)

    @torch.jit.unused
    def _locked(self, x_t: Tensor, step: bool, conditions: Tensor | None = None) -> Tensor:
        with self._step_lock:
            try:
                return self._step(x_t, conditions) if step else self._reset(x_t)
            except BaseException:
                self.stepping = False  # under the lock no other step runs: a failed one ended
                raise

    def _step(self, x_t: Tensor, conditions: Tensor | None) -> Tensor:
        if x_t.dim() != 1:
            raise ValueError(
                "step expects one sample per row, shape (batch,), got shape " + str(x_t.shape)
            )
        c = self._step_inputs(x_t, conditions)
        if self.stepping:
            raise RuntimeError(self.CONCURRENT)
        self.stepping = True  # read before the state is: no read while another step writes
        ticket = self.calls + 1
        self.calls = ticket
        if x_t.shape[0] != self.state[0].shape[0]:
            if self.n_steps != 0:
                self.stepping = False
                raise ValueError(
                    "step: batch " + str(x_t.shape[0]) + " differs from the running batch "
                    + str(self.state[0].shape[0]) + "; call reset() first"
                )
            self.state = self.initial_state(x_t.shape[0])
        u, s = self._advance(x_t.to(self.low.dtype), self.state, c)
        if self.calls != ticket:  # a step begun meanwhile: that one writes the state
            raise RuntimeError(self.CONCURRENT)
        self.state = s
        self.n_steps += 1
        self.stepping = False
        return u

    def _step_inputs(self, x_t: Tensor, conditions: Tensor | None) -> Tensor:
        """The step's inputs besides x, checked: the conditions (batch, n) or empty."""
        return conditions_of(x_t, conditions, self.n_conditions, self.low.dtype, "step", 2)

    @torch.jit.export
    def reset(self) -> None:
        """Back to the fresh state (the counter too); the next ``step`` may change the batch."""
        if torch.jit.is_scripting():
            self._reset(self.zero)
        else:
            self._locked(self.zero, False)

    def _reset(self, x: Tensor) -> Tensor:
        self.state = self.initial_state(self.state[0].shape[0])
        self.n_steps, self.stepping = 0, False
        return x

    @torch.jit.export
    def nonfinite_count(self) -> Tensor:
        """Samples held because the input (or the command) was NaN or inf, per row (batch,)."""
        return self.state[self.STATE_I][:, self.COUNTER_COLUMN]

    @torch.jit.export
    def out_of_range_count(self) -> Tensor:
        """Finite input samples outside the clamp's bounds (clamped before the model saw
        them), per row (batch,); zeros without a clamp."""
        I = self.state[self.STATE_I]
        if self.clamp_input:
            return I[:, I.shape[1] - 1]
        return torch.zeros_like(I[:, self.COUNTER_COLUMN])

    def forward(self, x: Tensor, conditions: Tensor | None = None) -> Tensor:
        """Commands for a whole sequence from a fresh state: x (time,) or (batch, time); the
        conditions of a conditioned model (time, n_conditions) or (batch, time,
        n_conditions)."""
        if x.dim() not in (1, 2):
            raise ValueError(
                "x must have shape (time,) or (batch, time), got shape " + str(x.shape)
            )
        xb = x.to(self.low.dtype)
        c = conditions_of(x, conditions, self.n_conditions, self.low.dtype, "forward",
                          x.dim() + 1)
        if x.dim() == 1:
            xb = xb.unsqueeze(0)
            c = c.unsqueeze(0) if self.n_conditions > 0 else c
        state = self.initial_state(xb.shape[0])
        outs: list[Tensor] = []
        for t, xt in enumerate(xb.unbind(1)):
            ct = c[:, t] if self.n_conditions > 0 else c
            u, state = self._advance(xt, state, ct)
            outs.append(u)
        if len(outs) == 0:
            return x.to(self.low.dtype)
        y = torch.stack(outs, dim=1)
        return y[0] if x.dim() == 1 else y

    def layout(self) -> list[tuple[int, str, str, int, int]]:
        """The state layout as rows ``(tensor index, kind, block name, first column,
        columns)``, the compensator's own columns included (for docs and loaders)."""
        return layout_rows(self.slots, self.guard, self.clamp_input)
