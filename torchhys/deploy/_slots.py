"""The compensator's pieces that are not its step: one step's place in the packed state
(:class:`_Slot`) and the dtype helpers (see :mod:`torchhys.deploy.streaming`)."""

# no `from __future__ import annotations`: TorchScript reads _Slot's class annotations
from typing import Final

import torch
from torch import Tensor, nn

from torchhys.step import STATE_KINDS, OperatorStep, check_step, custom_start

#: position of each block kind in the per-kind lists (the order of STATE_KINDS)
_KIND_INDEX = {kind: i for i, kind in enumerate(STATE_KINDS)}


class _Slot(nn.Module):
    """One step and where its blocks are in the compensator's split state (kind, piece).
    A step with a start of its own (:func:`~torchhys.step.custom_start`) starts from
    its ``initial_state(x)`` in the rows that have not started. A step of several inputs
    (``conditioned``) is given ``[x, conditions]``, a step of one input x alone."""

    kinds: list[int]
    pieces: list[int]
    custom: Final[bool]
    conditioned: Final[bool]

    def __init__(self, step: OperatorStep, kinds: list[int], pieces: list[int]) -> None:
        super().__init__()
        self.step = step
        self.kinds, self.pieces = kinds, pieces
        self.custom = custom_start(step)
        self.conditioned = step.n_inputs > 1

    def forward(self, x: Tensor, parts: list[list[Tensor]], new: list[list[Tensor]],
                started: Tensor) -> Tensor:
        state: list[Tensor] = []
        for j in range(len(self.kinds)):
            state.append(parts[self.kinds[j]][self.pieces[j]])
        if self.custom:
            start = self.step.initial_state(x)
            for j in range(len(self.kinds)):
                state[j] = torch.where(started, state[j], start[j].to(state[j].dtype))
        features, out = self.step(x, state)
        for j in range(len(self.kinds)):
            new[self.kinds[j]].append(out[j])
        return features



def _dtype_name(dtype: torch.dtype) -> str:
    """The name of a state dtype, for messages (a scripted dtype is a number)."""
    if dtype == torch.float32 or dtype == torch.float64:
        return "float32" if dtype == torch.float32 else "float64"
    return "int64" if dtype == torch.int64 else "bool" if dtype == torch.bool else "another"


def _model_dtype(model: nn.Module) -> torch.dtype:
    for t in (*model.parameters(), *model.buffers()):
        if t.is_floating_point():
            return t.dtype
    return torch.get_default_dtype()


def conditions_of(x: Tensor, conditions: Tensor | None, n: int, dtype: torch.dtype, where: str,
                  dims: int) -> Tensor:
    """A compensator's conditions checked against x: (batch, n) for a sample (``dims`` 2),
    (batch, time, n) for a sequence (3), in ``dtype``; an empty tensor for a model without
    conditions (``n`` 0). ``where`` names the method in the messages."""
    if conditions is None:
        if n > 0:
            raise ValueError(where + ": this compensator takes " + str(n) + " condition(s) "
                             "per sample: pass conditions of shape (batch, "
                             + ("time, " if dims == 3 else "") + str(n) + ")")
        return x.new_zeros([0])
    if n == 0:
        raise ValueError(where + ": conditions given, but the model takes none "
                         "(n_conditions is 0)")
    want = list(x.shape) + [n]
    if list(conditions.shape) != want:
        raise ValueError(where + ": conditions must have shape " + str(want) + " (x's "
                         "shape and one column per condition), got "
                         + str(list(conditions.shape)))
    return conditions.to(dtype)


def file_conditions(conditions: object, n: int, batch: int, dtype: torch.dtype,
                    kind: str) -> list[Tensor]:
    """The conditions a loaded exported step (an AOTI package, an ONNX file: ``kind``)
    takes beside x, checked: ``[conditions (batch, n)]`` contiguous in ``dtype``, or ``[]``
    for a step without conditions (``n`` 0, none given)."""
    if n == 0 and conditions is None:
        return []
    if conditions is None or n == 0:
        raise ValueError(f"step: conditions given, but the {kind} takes none" if n == 0
                         else f"step: this {kind} takes {n} condition(s): pass conditions of "
                         f"shape ({batch}, {n})")
    c = torch.as_tensor(conditions)
    if tuple(c.shape) != (batch, n):
        raise ValueError(f"step: conditions must have shape ({batch}, {n}), got "
                         f"{tuple(c.shape)}")
    return [c.to(dtype).contiguous()]


def layout_rows(slots: nn.ModuleList, guard: bool, clamp_input: bool
                ) -> list[tuple[int, str, str, int, int]]:
    """:meth:`~torchhys.deploy.streaming.StreamingCompensator.layout` of a compensator of
    these steps (``slots``) and own columns: rows ``(tensor index, kind, block name, first
    column, columns)``, the tensors numbered F 0, I 1, started 2, F64 3."""
    STATE_F, STATE_I, STATE_STARTED, STATE_F64 = 0, 1, 2, 3  # as in streaming.py
    rows = [(STATE_F, "float", "held command", 0, 1),
            (STATE_I, "int64", "held-sample counter", 0, 1),
            (STATE_STARTED, "bool", "started", 0, 1)]
    col = {"float": 1, "float64": 0, "int64": 1}
    tensor = {"float": STATE_F, "float64": STATE_F64, "int64": STATE_I}
    for i, slot in enumerate(slots):
        for block in slot.step.state_spec:
            rows.append((tensor[block.kind], block.kind,
                         f"step {i} ({type(slot.step).__name__}): {block.name}",
                         col[block.kind], block.size))
            col[block.kind] += block.size
    if guard:
        rows.append((STATE_F, "float", "last clamped input (direction guard)",
                     col["float"], 1))
    if clamp_input:
        rows.append((STATE_I, "int64", "out-of-range counter", col["int64"], 1))
    return rows


def check_state(x: Tensor, state: list[Tensor], templates: list[Tensor],
                state_names: list[str]) -> None:
    """ValueError unless ``state`` has the tensors of ``templates`` (dtype, columns) for x's
    batch (a compensator's ``step_explicit``; the message names the tensor)."""
    if len(state) != len(templates):
        raise ValueError("step_explicit: state has " + str(len(state)) + " tensors, "
                         "expected " + str(len(templates)) + " (initial_state)")
    for i in range(len(templates)):
        if state[i].dtype != templates[i].dtype:
            raise ValueError("step_explicit: state[" + str(i) + "], " + state_names[i]
                             + ", has dtype " + _dtype_name(state[i].dtype) + ", expected "
                             + _dtype_name(templates[i].dtype))
        want = templates[i].shape[1]
        if state[i].dim() != 2 or state[i].shape[0] != x.shape[0] or state[i].shape[1] != want:
            raise ValueError("step_explicit: state[" + str(i) + "], " + state_names[i]
                             + ", has shape " + str(list(state[i].shape)) + ", expected ["
                             + str(x.shape[0]) + ", " + str(want) + "] (x's batch and the "
                             "layout's columns)")


def checked_step(step: object, i: int, n_conditions: int) -> OperatorStep:
    """Streaming step ``i`` checked to be of the protocol, of one input or of
    ``1 + n_conditions`` (a TypeError naming it otherwise)."""
    if n_conditions == 0:
        return check_step(step, f"streaming step {i}")
    step = check_step(step, f"streaming step {i}", n_inputs=None)
    m, n = step.n_inputs, n_conditions
    if m != 1 and m != 1 + n:
        raise TypeError(f"streaming step {i} ({type(step).__name__}) takes {m} input "
                        f"columns, expected 1 (x) or {1 + n} (x and the {n} "
                        "condition(s))")
    return step


def file_pair(measured_prev: object, applied_prev: object, adaptive: bool, batch: int,
              dtype: torch.dtype, kind: str) -> list[Tensor]:
    """The last sample's pair a loaded exported step (``kind``: package, file) takes after
    x and the conditions, checked: ``[measured_prev, applied_prev]`` (batch,) contiguous in
    ``dtype``, NaN for a member not given (no update); ``[]`` for a static step (none
    given)."""
    given = [(n, v) for n, v in (("measured_prev", measured_prev),
                                 ("applied_prev", applied_prev)) if v is not None]
    if not adaptive:
        if given:
            raise ValueError(f"step: {given[0][0]} given, but the {kind} does not adapt "
                             "(exported with adapt='none')")
        return []
    out = []
    for name, value in (("measured_prev", measured_prev), ("applied_prev", applied_prev)):
        if value is None:
            out.append(torch.full((batch,), float("nan"), dtype=dtype))
            continue
        t = torch.as_tensor(value)
        if tuple(t.shape) != (batch,):
            raise ValueError(f"step: {name} must have shape ({batch},), got {tuple(t.shape)}")
        out.append(t.to(dtype).contiguous())
    return out


class FileAdaptation:
    """The readout's adaptation of a loaded exported step, from its metadata (the keys
    ``ADAPT_KEYS`` of :mod:`torchhys.deploy.export`): where the weights and the counters
    are in the state. ``adaptive`` is False for a static file."""

    def __init__(self, meta: dict[str, str]) -> None:
        self.adaptive = bool(meta.get("adapt", ""))
        if self.adaptive:
            self.weights, self.counts = int(meta["weights"]), int(meta["adapt_counts"])
            self.w0 = torch.tensor([float(v) for v in meta["w0"].split(",")],
                                   dtype=torch.float64)
            self.inv_scale = torch.tensor([float(v) for v in meta["inv_scale"].split(",")],
                                          dtype=torch.float64)

    def weights_of(self, state: list[Tensor]) -> Tensor:
        """The readout's current weights (batch, m) in the readout's units: ``(w0 +
        state[weights]) * inv_scale`` in the state's dtype."""
        self._need()
        W = state[self.weights]
        return (self.w0.to(W.dtype) + W) * self.inv_scale.to(W.dtype)

    def count(self, state: list[Tensor], column: int) -> Tensor:
        """A column of the adaptation's counters (0 applied, 1 skipped, 2 refused)."""
        self._need()
        return state[self.counts][:, column]

    def _need(self) -> None:
        if not self.adaptive:
            raise ValueError("the file does not adapt (exported with adapt='none'): it has "
                             "no adapted weights or adaptation counters")


class AdaptiveStepper:
    """The adaptation's readers of a loaded exported step (a mixin of the steppers that
    keep ``state`` and ``adaptation``, a :class:`FileAdaptation`)."""

    state: list[Tensor]
    adaptation: FileAdaptation

    def adapted_weights(self) -> Tensor:
        """The readout's current weights (batch, n_weights), in the readout's units."""
        return self.adaptation.weights_of(self.state)

    def updates_count(self) -> Tensor:
        """Updates applied, per row."""
        return self.adaptation.count(self.state, 0)

    def skipped_count(self) -> Tensor:
        """Pairs skipped (measured_prev or applied_prev missing, NaN or inf), per row."""
        return self.adaptation.count(self.state, 1)

    def refused_count(self) -> Tensor:
        """Updates refused by the direction rule, per row."""
        return self.adaptation.count(self.state, 2)
