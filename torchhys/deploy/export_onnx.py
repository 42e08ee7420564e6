"""Export a trained compensator as ONNX: the explicit-state step, for ONNX Runtime.

:func:`to_onnx` writes one ``.onnx`` file holding the step of a
:class:`~torchhys.deploy.streaming.StreamingCompensator` with its state passed explicitly, the
same function as an AOTI package (:func:`torchhys.deploy.export.to_aoti`)::

    inputs   x (batch,), state_0, ..., state_{k-1}
    outputs  u (batch,), new_state_0, ..., new_state_{k-1}   (the same order, shapes, dtypes)

A conditioned model's file has the input ``conditions`` (batch, n) after x; an adaptive
compensator's (``adapt="rls"`` or ``"nlms"``) ``measured_prev`` and ``applied_prev`` (batch,)
after those (the last sample's response and applied command, NaN: no update), and its
metadata the ``ADAPT_KEYS`` of :mod:`torchhys.deploy.export`.

The caller keeps the state: it starts from the metadata's ``initial_state`` (all zeros) and
feeds each step's new states to the next. The state tensors, their dtypes (the compensator's
float dtype, ``int64``, ``bool`` and, for some operators, ``float64``) and their layout are
those of :mod:`torchhys.deploy.streaming`; the file's inputs have exactly the dtypes of
``state_spec`` (a ``bool`` state is an ONNX ``tensor(bool)``). The batch is static.

The model's ``metadata_props`` hold the keys of :func:`torchhys.deploy.export.metadata` (all
strings: ``state_spec``, ``n_state``, ``counter``, ``held``, ``low``, ``high``,
``input_low``, ``input_high``, ``out_of_range``, ``direction``, ``dtype``, ``batch``) and

    initial_state     the fresh state of one row as JSON: a list of k nested lists, one per
                      state tensor, shape (1, columns) (the row to repeat for a larger batch)
    torchhys_version  the version that wrote the file

Needs the ``onnx`` extra (``pip install "torchhys[onnx]"``: onnx and onnxscript to export,
onnxruntime to run); ``import torchhys`` does not import them.

The graph is made by the ``torch.export``-based exporter (``torch.onnx.export(...,
dynamo=True)``), with a few aten operations written here (:func:`_translations`): Python
numbers kept in float64 (the exporter rounds them to float32), ``copysign``,
``searchsorted``, ``sinh`` and ``asinh`` (float32 only in ONNX Runtime). An operation the
exporter cannot write, or one ONNX Runtime has no kernel for, is a ``ValueError`` at export
that names it (and the step that uses it). Agreement with the TorchScript file, measured over
1e4 samples with turning points, ties, runs of signed zeros, out-of-range samples, NaN and
inf (``tests/test_export_onnx.py``): float64 within 1e-12 of the command's scale (at most
2e-13 seen), float32 within 1e-4 (at most 7.3e-5 seen: the float32 roundings of the two
runtimes' sums and of their ``exp``).

ONNX Runtime's ``Where`` returns +0 where it selects a -0 from its first operand (the
state held over a non-finite sample is one such selection): a state column holding -0.0 may
come back as +0.0. The commands do not change: where a step reads a zero's sign
(``copysign`` of the last move in the re-based EIHO), it chooses between anchors equal up to
that sign; the parity tests feed runs of -0.0 and +0.0 samples beside NaN samples.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import re
import threading
import warnings
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._checks import check_int
from torchhys._version import __version__
from torchhys.deploy._onnx_norms import norm_translations
from torchhys.deploy._slots import AdaptiveStepper, FileAdaptation, file_conditions, file_pair
from torchhys.deploy.export import (
    _METADATA_KEYS,
    ADAPT_KEYS,
    CONDITION_KEYS,
    _check_path,
    _compensator,
    _ExplicitStep,
    _parse_state_spec,
    _position,
    _write,
    adapt_options,
    metadata,
)

__all__ = ["ONNX_METADATA_KEYS", "ONNXStepper", "load_onnx", "onnx_metadata", "to_onnx"]

_INSTALL = 'pip install "torchhys[onnx]"'
#: the metadata keys of an ONNX file: those of the libtorch formats and two more
ONNX_METADATA_KEYS = (*_METADATA_KEYS, "initial_state", "torchhys_version")
# (a conditioned compensator's file has the CONDITION_KEYS of torchhys.deploy.export too)


def _require(*modules: str) -> None:
    """Import ``modules`` or raise an ImportError that names the extra to install."""
    missing = []
    for name in modules:
        try:
            __import__(name)
        except ImportError:
            missing.append(name)
    if missing:
        raise ImportError(f"ONNX export and loading need {', '.join(missing)}: {_INSTALL}")


def _translations() -> dict[Any, Any]:
    """ONNX functions that replace the exporter's for some aten operations.

    * ``scalar_tensor``: the exporter's writes a float32 constant and casts it, so every
      Python number in a float64 step (``b / mu0``, a series' ``1 / 3``) would be rounded to
      float32; here the constant is written in its dtype. (The constants below are float64
      cast to their operand's dtype, for the same reason.)
    * ``copysign`` (ONNX has none; without it the exporter decomposes it into
      ``prims.signbit``, which has none either): a sign test, see the module docstring.
    * ``searchsorted`` (none in the exporter): the count of the sorted values below the
      sample (``right``: at most it), as a broadcast comparison summed over the last axis.
    * ``sinh`` and ``asinh`` (ONNX Runtime runs them in float32 only): ``sinh`` as its series
      below 0.1 and ``(e^t - e^-t) / 2`` above, ``asinh`` as ``log1p(t + t^2 / (1 +
      sqrt(1 + t^2)))`` with an accurate ``log1p``; both odd (``-0`` kept), within a few ulp
      of libm.
    * layer norm and eval-mode batch norm in primitive ops, their ``eps`` in float64 (ONNX's
      ``LayerNormalization`` and ``BatchNormalization`` take a float32 one), see
      :mod:`torchhys.deploy._onnx_norms`.
    """
    import numpy as np
    from onnxscript import ir
    from onnxscript import opset18 as op

    def const(value: float, like):
        """``value`` in the dtype of ``like``, from a float64 constant."""
        return op.CastLike(op.Constant(value=ir.tensor(np.array(value, dtype=np.float64))), like)

    def scalar_tensor(s: float, dtype: int = -1, layout: str = "", device: str = "",
                      pin_memory: bool = False):
        kind = ir.DataType.FLOAT if dtype is None or int(dtype) == -1 else ir.DataType(dtype)
        return op.Constant(value=ir.tensor(np.array(s, dtype=kind.numpy())))

    def signbit(b):
        zero = const(0.0, b)
        negative_zero = op.And(op.Equal(b, zero), op.Less(op.Div(const(1.0, b), b), zero))
        return op.Or(op.Less(b, zero), negative_zero)

    def copysign(a, b):
        # |a| times +-1: exact, and a zero keeps its sign (ONNX Runtime's Where returns +0
        # where it selects a -0 from its first operand)
        sign = op.Where(signbit(op.CastLike(b, a)), const(-1.0, a), const(1.0, a))
        return op.Mul(op.Abs(a), sign)

    def copysign_scalar(a, b: float):
        return copysign(a, const(b, a))

    def searchsorted(sorted_sequence, values, out_int32: bool = False, right: bool = False,
                     side: str = "", sorter=None):
        if sorter is not None:
            raise ValueError("searchsorted with a sorter has no ONNX translation")
        seq = op.Unsqueeze(sorted_sequence, op.Constant(value_ints=[-2]))  # (..., 1, n)
        v = op.Unsqueeze(values, op.Constant(value_ints=[-1]))  # (..., m, 1)
        # a NaN sample counts every value (torch sorts NaN last)
        above = op.Greater(seq, v) if right or side == "right" else op.GreaterOrEqual(seq, v)
        count = op.ReduceSum(op.Cast(op.Not(above), to=ir.DataType.INT64),
                             op.Constant(value_ints=[-1]), keepdims=0)
        return op.Cast(count, to=ir.DataType.INT32) if out_int32 else count

    def sinh(x):
        t = op.Abs(x)
        x2 = op.Mul(x, x)
        series = const(1.0 / math.factorial(11), x)
        for k in (9, 7, 5, 3, 1):  # x (1 + x^2/3! + ... + x^10/11!), odd as it stands
            series = op.Add(const(1.0 / math.factorial(k), x), op.Mul(x2, series))
        # e^t / 2 - e^-t / 2 as h (h / 2) - 1 / (2 h^2), h = e^(t/2): finite up to sinh's
        # own overflow (e^t alone overflows a little earlier)
        half = const(0.5, x)
        h = op.Exp(op.Mul(t, half))
        wide = op.Sub(op.Mul(h, op.Mul(h, half)), op.Div(half, op.Mul(h, h)))
        # the series second: Where keeps a -0 of its second operand, not of its first
        return op.Where(op.GreaterOrEqual(t, const(0.1, x)), copysign(wide, x),
                        op.Mul(x, series))

    def asinh(x):
        t = op.Abs(x)
        one = const(1.0, x)
        t2 = op.Mul(t, t)
        y = op.Add(t, op.Div(t2, op.Add(one, op.Sqrt(op.Add(one, t2)))))
        u = op.Add(one, y)  # log1p(y) = log(u) y / (u - 1), exact where u rounds to 1
        log1p = op.Where(op.Equal(u, one), y, op.Div(op.Mul(op.Log(u), y), op.Sub(u, one)))
        # where t^2 overflows (beyond 1e154 in float64), log t + log 2 to the last bit
        big = op.Add(op.Log(t), const(math.log(2.0), x))
        return copysign(op.Where(op.IsInf(t2), big, log1p), x)

    return {torch.ops.aten.scalar_tensor.default: scalar_tensor,
            torch.ops.prims.signbit.default: signbit, torch.ops.aten.signbit.default: signbit,
            torch.ops.aten.copysign.Tensor: copysign,
            torch.ops.aten.copysign.Scalar: copysign_scalar,
            torch.ops.aten.searchsorted.Tensor: searchsorted,
            torch.ops.aten.sinh.default: sinh, torch.ops.aten.asinh.default: asinh,
            **norm_translations(const)}


def onnx_metadata(comp: nn.Module, batch: int = 1) -> dict[str, str]:
    """The ``metadata_props`` of :func:`to_onnx` for a built compensator (module docstring)."""
    state = [t.tolist() for t in comp.initial_state(1)]
    return {**metadata(comp, batch), "initial_state": json.dumps(state),
            "torchhys_version": __version__}


def to_onnx(
    model: nn.Module, path: str | os.PathLike, *, limits: tuple[float, float] | None = None,
    initial_command: float = 0.0, input_range: tuple[float, float] | None = None,
    input_margin: float | None = 0.05, direction: str = "auto", batch: int = 1,
    opset: int | None = None, adapt: str = "none", forgetting: float = 0.995,
    adapt_bound: float = 0.5, dead_zone: float = 0.0, excitation: float = 1e-3,
    nlms_step: float = 0.2, initial_covariance: float = 1.0,
) -> str:
    """Export the explicit-state step of the compensator of ``model`` as an ONNX file.

    Args:
        model, limits, initial_command, input_range, input_margin, direction: as
            :func:`torchhys.deploy.export.to_torchscript` (a model, or a built
            :class:`~torchhys.deploy.streaming.StreamingCompensator` with the defaults here).
        path: output file (conventionally ``.onnx``); the weights are inside it. Written
            atomically: an old file there is replaced whole or, on an error, left as it was.
        batch: rows per step (static).
        opset: the ONNX opset (default: the exporter's).
        adapt, forgetting, adapt_bound, dead_zone, excitation, nlms_step,
            initial_covariance: as :func:`torchhys.deploy.export.to_torchscript`
            (``adapt`` rls or nlms: the inputs ``measured_prev`` and ``applied_prev``).

    Returns:
        The path written.

    Raises:
        ImportError: onnx or onnxscript is missing (``pip install "torchhys[onnx]"``).
        ValueError, TypeError: see :class:`~torchhys.deploy.streaming.StreamingCompensator`; a
            missing output directory; a bad ``batch`` or ``opset``.
    """
    path = _check_path(path)
    check_int(batch, "batch", minimum=1)
    if opset is not None:
        check_int(opset, "opset", minimum=1)
    _require("onnx", "onnxscript")
    comp = _compensator(model, limits, initial_command,
                        {"input_range": input_range, "input_margin": input_margin,
                         "direction": direction, **adapt_options(
                             adapt, forgetting, adapt_bound, dead_zone, excitation,
                             nlms_step, initial_covariance)}).eval()
    state = comp.initial_state(batch)
    x = torch.zeros(batch, dtype=comp.low.dtype)
    names = [f"state_{i}" for i in range(len(state))]
    # the inputs between x and the state: the conditions, the adaptive pair
    extra = comp.example_inputs(batch)
    inputs = (x, *(t for _, t in extra), *state)
    with torch.no_grad(), _quiet_exporter():
        program = torch.export.export(_ExplicitStep(comp).eval(), inputs, strict=False)
    meta = onnx_metadata(comp, batch)
    try:
        proto = _export_program(program, inputs, opset, ["x", *(n for n, _ in extra), *names],
                                meta, optimize=True)
        _check_runs(proto)
    except ValueError as err:
        # onnxscript's optimizer (0.7.2) can drop the shared bounds of two clamps of one
        # value (the conditions' clamp on an adaptive compensator's two paths), leaving a
        # node input that nothing defines: that graph is written unoptimized
        if "is not a graph input, initializer, or output" not in str(err):
            raise
        proto = _export_program(program, inputs, opset, ["x", *(n for n, _ in extra), *names],
                                meta, optimize=False)
        _check_runs(proto)
    _write(path, proto.SerializeToString())  # atomic: a full disk leaves the old file
    return path


def _export_program(program: Any, inputs: tuple[Tensor, ...], opset: int | None,
                    input_names: list[str], meta: dict[str, str], optimize: bool) -> Any:
    """The ONNX model proto of the exported ``program`` with the metadata ``meta``; an
    operation without a translation is a one-line ValueError (:func:`_unsupported`)."""
    outputs = ["u", *(f"new_{n}" for n in input_names if n.startswith("state_"))]
    with torch.no_grad(), _quiet_exporter():
        try:
            onnx_program = torch.onnx.export(
                program, inputs, dynamo=True, opset_version=opset, input_names=input_names,
                output_names=outputs, custom_translation_table=_translations(),
                verbose=False, optimize=optimize,
            )
        except Exception as err:
            message = _unsupported(err)
            if message is None:
                raise
            raise ValueError(message) from None
    proto = onnx_program.model_proto
    for key, value in meta.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    return proto


@contextlib.contextmanager
def _quiet_exporter():
    """The exporter's own notices off (the optional torchvision operators it does not find,
    a deprecation inside its pytree code); the caller's warnings still pass."""
    registry = logging.getLogger("torch.onnx._internal.exporter._registration")
    level = registry.level
    registry.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r".*LeafSpec", category=FutureWarning)
            yield
    finally:
        registry.setLevel(level)


def _unsupported(err: BaseException) -> str | None:
    """One line naming the operation without an ONNX translation and, where the exporter's
    traceback holds its graph node, the step module and the source line that use it; None
    when ``err`` is another failure."""
    text, node = "", None
    e: BaseException | None = err
    while e is not None:
        text += str(e)
        tb = e.__traceback__
        while tb is not None:  # the node being translated, a local of the exporter's frames
            candidate = tb.tb_frame.f_locals.get("node")
            if isinstance(candidate, torch.fx.Node) and candidate.op == "call_function":
                node = candidate
            tb = tb.tb_next
        e = e.__cause__ or e.__context__
    found = re.search(r"No ONNX function found for <OpOverload\(op='([\w.]+)', "
                      r"overload='(\w+)'\)>", text)
    if found is None:
        return None
    where = ""
    stack = node.meta.get("nn_module_stack") if node is not None else None
    if stack:
        path, kind = list(stack.values())[-1]
        kind = kind if isinstance(kind, str) else f"{kind.__module__}.{kind.__qualname__}"
        where = f" (from {path} ({kind})"
        line = re.findall(r'File "([^"]+)", line (\d+), in (\w+)',
                          node.meta.get("stack_trace") or "")
        if line:
            file, number, function = line[-1]
            where += f" at {os.path.basename(file)}:{number} in {function}"
        where += ")"
    return (f"no ONNX translation for {found[1]}.{found[2]}{where}: the ONNX exporter cannot "
            "write this operation; export the compensator in another format")


def _check_runs(proto: Any) -> None:
    """Open the model in ONNX Runtime, where it is installed: an operation it has no kernel
    for (in this dtype) is reported now rather than when the file is deployed."""
    try:
        import onnxruntime as ort
    except ImportError:
        return
    try:
        ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    except Exception as err:  # onnxruntime's own error types
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"ONNX Runtime {ort.__version__} cannot run the exported step: "
                         f"{first}") from None


class ONNXStepper(AdaptiveStepper):
    """Python runner of a file from :func:`to_onnx` over ONNX Runtime: ``step``, ``reset``,
    the counters (for an adaptive file ``adapted_weights()``, ``updates_count()``,
    ``skipped_count()`` and ``refused_count()`` too). The state is kept as torch tensors
    (``state``), in the file's layout. Safe across threads: a lock makes ``step`` and
    ``reset`` run one at a time.

    Args:
        path: the ``.onnx`` file.
        threads: ONNX Runtime's intra-op threads (default 1: one small step gains nothing
            from more).
    """

    def __init__(self, path: str | os.PathLike, threads: int = 1) -> None:
        _require("onnxruntime")
        import onnxruntime as ort

        check_int(threads, "threads", minimum=1)
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        self.session = ort.InferenceSession(os.fspath(path), options,
                                            providers=["CPUExecutionProvider"])
        meta = self.session.get_modelmeta().custom_metadata_map
        missing = [k for k in ("state_spec", "counter", "low", "high") if k not in meta]
        if missing:
            raise ValueError(f"{os.fspath(path)}: not a torchhys ONNX compensator (its "
                             f"metadata lacks {', '.join(missing)})")
        self.metadata = {k: meta[k] for k in (*ONNX_METADATA_KEYS, *CONDITION_KEYS,
                                              *ADAPT_KEYS) if k in meta}
        self.adaptation = FileAdaptation(self.metadata)
        self.spec = meta["state_spec"]
        self.counter = _position(meta["counter"])
        oor = meta.get("out_of_range", "")
        self.out_of_range = _position(oor) if oor else None
        self.low, self.high = float(meta["low"]), float(meta["high"])
        self.input_names = [i.name for i in self.session.get_inputs()]
        self._lock = threading.Lock()
        self.reset()
        self.batch = int(self.state[0].shape[0])
        self.dtype = self.state[0].dtype
        self.n_conditions = int(meta.get("n_conditions", "0"))

    def reset(self) -> None:
        """Back to the fresh (all-zero) state."""
        with self._lock:
            self.state = _parse_state_spec(self.spec)

    def step(self, x_t: Tensor, conditions: Tensor | None = None,
             measured_prev: Tensor | None = None, applied_prev: Tensor | None = None) -> Tensor:
        """One sample, x_t (batch,) (and, for a file with conditions, their values
        (batch, n_conditions); for an adaptive file the last sample's measured response and
        applied command (batch,), None: no update) -> command (batch,).

        Raises:
            ValueError: ``x_t`` is not of shape ``(batch,)`` with the exported batch;
                conditions missing, given to a file without, or of another shape; a member
                of the pair of another shape, or given to a static file.
        """
        x_t = torch.as_tensor(x_t)
        if x_t.dim() != 1 or x_t.shape[0] != self.batch:
            raise ValueError(f"step expects shape ({self.batch},) (the exported batch), got "
                             f"shape {tuple(x_t.shape)}")
        x_t = x_t.to(self.dtype).contiguous()
        extra = file_conditions(conditions, self.n_conditions, self.batch, self.dtype, "file")
        extra += file_pair(measured_prev, applied_prev, self.adaptation.adaptive, self.batch,
                           self.dtype, "file")
        with self._lock:  # the state read, stepped and replaced by one thread at a time
            feed = {name: t.numpy() for name, t in
                    zip(self.input_names, [x_t, *extra, *self.state], strict=True)}
            out = self.session.run(None, feed)
            self.state = [torch.from_numpy(a) for a in out[1:]]
        return torch.from_numpy(out[0])

    def nonfinite_count(self) -> Tensor:
        """Samples held because the input was NaN or inf, per row (the metadata's
        ``counter`` position)."""
        return self.state[self.counter[0]][:, self.counter[1]]

    def out_of_range_count(self) -> Tensor:
        """Finite samples clamped to the training input range, per row (zeros for a file
        without a clamp)."""
        if self.out_of_range is None:
            return torch.zeros_like(self.nonfinite_count())
        return self.state[self.out_of_range[0]][:, self.out_of_range[1]]


def load_onnx(path: str | os.PathLike, threads: int = 1) -> ONNXStepper:
    """Load a file written by :func:`to_onnx` (see :class:`ONNXStepper`)."""
    return ONNXStepper(path, threads)
