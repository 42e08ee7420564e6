"""Export a trained compensator for deployment: TorchScript, or torch.export + AOTInductor.

Both formats wrap a :class:`~torchhys.deploy.streaming.StreamingCompensator`: the saved artefact
takes the desired output in physical units and returns the saturated command, with NaN/inf
inputs held and counted. Neither needs torchhys to load.

* :func:`to_torchscript`: a ``torch.jit`` module with ``forward(x)`` (whole sequence from a
  fresh state), ``step(x_t)`` (state kept inside), ``reset()``, ``nonfinite_count()`` and
  ``out_of_range_count()``;
  loads with ``torch.jit.load`` (Python) or ``torch::jit::load`` (C++).
* :func:`to_aoti`: an AOTInductor package (``.pt2``) of the explicit-state step
  ``(x_t, *state) -> (u_t, *state)`` (``(x_t, conditions, *state)`` for a model with
  operating conditions); load it with :func:`load_aoti` or
  ``torch::inductor::AOTIModelPackageLoader`` (C++).

Both carry the same metadata (:func:`metadata`; the package's metadata, or the TorchScript
file's extra files of the same names), all strings:

    state_spec  the fresh state, ``"dtype:d0,d1;dtype:d0,d1;..."``, all zeros
                (:func:`state_spec_string`); its layout: :mod:`torchhys.deploy.streaming`
    n_state     number of state tensors
    counter     ``"tensor:column"`` of the counter of held non-finite samples
    held        ``"tensor:column"`` of the last valid command
    low, high   the command's saturation limits
    input_low, input_high
                the bounds the input is clamped to (``-inf``/``inf``: no clamp)
    out_of_range
                ``"tensor:column"`` of the counter of clamped inputs (``""``: no clamp)
    direction   ``1`` (the command never falls while the input rises), ``-1`` (never rises),
                ``0`` (no direction guard)
    dtype       the sample's and the command's dtype
    batch       the batch the state_spec is written for (static in an AOTI package)

A conditioned compensator's (``docs/conditions.md``) adds :data:`CONDITION_KEYS`:
``n_conditions``, and ``condition_low``, ``condition_high`` (the clamp's bounds of each
condition, comma-separated).

An adaptive compensator's (``adapt="rls"`` or ``"nlms"``,
:class:`~torchhys.deploy.adaptive.AdaptiveCompensator`) step takes the last sample's pair
after x (and the conditions): ``(x_t, [conditions,] measured_prev, applied_prev, *state)``,
both (batch,), NaN for none (no update); its metadata adds :data:`ADAPT_KEYS`:

    adapt       ``rls`` or ``nlms``
    n_weights   the readout's number of weights m
    weights     the index of the state tensor W (batch, m): the normalized weights minus
                the offline fit's; the readout's weights are ``(w0 + W) * inv_scale``
    covariance  the index of RLS's covariance P (batch, m*m) (``""`` for NLMS)
    adapt_counts
                the index of the counters (batch, 3): updates applied, pairs skipped,
                updates refused
    w0, inv_scale, bound
                the offline normalized weights, the regressors' inverse scales and the
                weights' box about w0 (each m values, comma-separated)
    forgetting, adapt_bound, dead_zone, excitation, nlms_step, initial_covariance
                the options (``adapt_bound`` recovered from ``bound``, to the dtype's
                precision)
"""

from __future__ import annotations

import io
import os
import threading
import warnings
from typing import Any

import torch
from torch import Tensor, nn

from torchhys._atomic import atomic_write_files
from torchhys._checks import check_choice, check_int
from torchhys.deploy._slots import AdaptiveStepper, FileAdaptation, file_conditions, file_pair
from torchhys.deploy.adaptive import AdaptiveCompensator
from torchhys.deploy.streaming import COUNTER, HELD, STATE_I, StreamingCompensator

__all__ = [
    "ADAPT_KEYS", "CONDITION_KEYS", "AOTIStepper", "load_aoti", "load_torchscript", "metadata",
    "state_spec_string", "to_aoti", "to_torchscript",
]

_DTYPE_NAMES = {torch.bool: "bool", torch.long: "int64", torch.float32: "float32",
                torch.float64: "float64"}
_NAME_DTYPES = {v: k for k, v in _DTYPE_NAMES.items()}


#: defaults of the options that build a compensator (those of StreamingCompensator)
_DEFAULTS: dict[str, Any] = {"limits": None, "input_range": None, "input_margin": 0.05,
                             "direction": "auto"}


#: the adaptive compensator's options and their defaults (``adapt="none"``: the static
#: compensator; :class:`~torchhys.deploy.adaptive.AdaptiveCompensator`)
ADAPT_DEFAULTS: dict[str, Any] = {"adapt": "none", "forgetting": 0.995, "adapt_bound": 0.5,
                                  "dead_zone": 0.0, "excitation": 1e-3, "nlms_step": 0.2,
                                  "initial_covariance": 1.0}


def _compensator(
    model: nn.Module, limits: tuple[float, float] | None, initial_command: float,
    options: dict[str, Any],
) -> StreamingCompensator:
    """The compensator of ``model`` with these options (those of :data:`ADAPT_DEFAULTS`
    among them build an adaptive one), or ``model`` itself when it is one."""
    options = dict(options)
    adapt = {k: options.pop(k) for k in ADAPT_DEFAULTS if k in options}
    if isinstance(model, StreamingCompensator):
        given = [k for k, v in {"limits": limits, **options}.items() if v != _DEFAULTS[k]]
        given += [k for k, v in adapt.items() if v != ADAPT_DEFAULTS[k]]
        if given:
            raise ValueError(f"{', '.join(given)}: fixed when the StreamingCompensator is "
                             "built; pass the model instead")
        return model
    check_choice(adapt.get("adapt", "none"), "adapt", ["none", "rls", "nlms"])
    if adapt.get("adapt", "none") != "none":
        return AdaptiveCompensator(model, limits=limits, initial_command=initial_command,
                                   **{**ADAPT_DEFAULTS, **adapt}, **options)
    return StreamingCompensator(model, limits=limits, initial_command=initial_command,
                                **options)


def adapt_options(adapt: str, forgetting: float, adapt_bound: float, dead_zone: float,
                  excitation: float, nlms_step: float, initial_covariance: float
                  ) -> dict[str, Any]:
    """The exporters' adaptive keywords as the options of :func:`_compensator` (those of
    :data:`ADAPT_DEFAULTS`), the defaults left out (a built compensator takes none)."""
    given = {"adapt": adapt, "forgetting": forgetting, "adapt_bound": adapt_bound,
             "dead_zone": dead_zone, "excitation": excitation, "nlms_step": nlms_step,
             "initial_covariance": initial_covariance}
    return {k: v for k, v in given.items() if v != ADAPT_DEFAULTS[k]}


def _check_path(path: str | os.PathLike) -> str:
    """``path`` as a str, if a file can be written there (checked before any compile)."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    path = os.fspath(path)
    parent = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(parent):
        raise ValueError(f"the directory of path {path!r} does not exist")
    if os.path.isdir(path):
        raise ValueError(f"path {path!r} is a folder; give the file to write")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"path {path!r}: the folder {parent!r} is not writable")
    return path


def _write(path: str, data: bytes) -> None:
    """Write an export's bytes to ``path`` atomically (:mod:`torchhys._atomic`): on an error
    the previous file at ``path`` is left whole, and the OSError names ``path``."""
    write_outputs([(path, data)])


def write_outputs(files: list[tuple[str | os.PathLike, bytes]]) -> None:
    """Write an export's files atomically, all complete before the first replaces its old
    version (:func:`torchhys._atomic.atomic_write_files`). An OSError (a full disk, no
    permission) leaves every old file whole and is raised naming the first target."""
    try:
        atomic_write_files(files, tag="export")
    except OSError as err:
        first = os.fspath(files[0][0])
        reason = err.strerror or str(err)
        raise OSError(err.errno, f"{reason} (nothing was replaced: the previous file is "
                      "left as it was)", first) from err


def to_torchscript(
    model: nn.Module, path: str | os.PathLike, *, limits: tuple[float, float] | None = None,
    initial_command: float = 0.0, input_range: tuple[float, float] | None = None,
    input_margin: float | None = 0.05, direction: str = "auto", adapt: str = "none",
    forgetting: float = 0.995, adapt_bound: float = 0.5, dead_zone: float = 0.0,
    excitation: float = 1e-3, nlms_step: float = 0.2, initial_covariance: float = 1.0,
) -> torch.jit.ScriptModule:
    """Script the streaming compensator of ``model`` and save it to ``path``.

    ``torch.jit.script`` is deprecated in torch 2.13 (its successor is ``torch.export``, see
    :func:`to_aoti`). TorchScript is kept because it is what many C++ controllers load
    today (``torch::jit::load``), so exactly that ``DeprecationWarning`` is caught around
    the scripting call; every other warning still reaches the caller.

    Args:
        model: an :class:`~torchhys.InverseHysteresisNet` with causal operators, a
            :class:`~torchhys.PrandtlIshlinskiiInverse`, a composition of operators and
            recurrent layers (:func:`torchhys.compose.compose`), any model with streaming
            steps, or a built :class:`~torchhys.deploy.streaming.StreamingCompensator`.
        path: output file (conventionally ``.pt``), written atomically: an old file there
            is replaced whole or, on an error (a full disk), left as it was.
        limits: ``(low, high)`` command saturation; default: the training output range
            (:func:`~torchhys.deploy.ranges.default_limits`).
        initial_command: command held until the first finite input.
        input_range, input_margin, direction: the input clamp and the direction guard, as
            :class:`~torchhys.deploy.streaming.StreamingCompensator` (defaults: its defaults, the
            model's recorded training input range with a 5 % margin and its direction).
        adapt: ``"none"`` (the static compensator), ``"rls"`` or ``"nlms"``: the
            :class:`~torchhys.deploy.adaptive.AdaptiveCompensator`, whose ``step(x_t,
            conditions=None, measured_prev=None, applied_prev=None)`` adapts the readout.
        forgetting, adapt_bound, dead_zone, excitation, nlms_step, initial_covariance: its
            options (used with ``adapt`` rls or nlms; defaults :data:`ADAPT_DEFAULTS`).

    Returns:
        The scripted module (also saved). Its methods: ``forward(x)`` x (time,) or
        (batch, time) -> same shape; ``step(x_t)`` (batch,) -> (batch,); ``reset()``;
        ``nonfinite_count()`` (batch,); ``out_of_range_count()`` (batch,);
        ``step_explicit(x_t, state)``; ``initial_state(b)``.

    Raises:
        ValueError, TypeError: see :class:`~torchhys.deploy.streaming.StreamingCompensator`; a
            missing output directory.
    """
    path = _check_path(path)
    comp = _compensator(model, limits, initial_command,
                        {"input_range": input_range, "input_margin": input_margin,
                         "direction": direction, **adapt_options(
                             adapt, forgetting, adapt_bound, dead_zone, excitation,
                             nlms_step, initial_covariance)}).eval()
    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message=r"`torch\.jit\.script` is deprecated", category=DeprecationWarning
        )
        scripted = torch.jit.script(comp)
    # to memory first: a full disk then fails in Python, not inside torch's writer
    _write(path, scripted.save_to_buffer(_extra_files=metadata(comp)))
    return scripted


def load_torchscript(path: str | os.PathLike) -> torch.jit.ScriptModule:
    """Load a file written by :func:`to_torchscript` (``torch.jit.load``, CPU).

    ``torch.jit.load`` is deprecated in torch 2.13 like ``torch.jit.script``; exactly that
    ``DeprecationWarning`` is caught here, for the same reason. Plain ``torch.jit.load``
    works as well (no torchhys needed). The module's :func:`metadata` is attached as the
    dict ``module.torchhys_metadata`` (Python attribute, not scripted).
    """
    files = dict.fromkeys((*_METADATA_KEYS, *CONDITION_KEYS, *ADAPT_KEYS), "")
    with warnings.catch_warnings():
        warnings.filterwarnings(
            "ignore", message=r"`torch\.jit\.load` is deprecated", category=DeprecationWarning
        )
        module = torch.jit.load(os.fspath(path), map_location="cpu", _extra_files=files)
    module.torchhys_metadata = {k: v.decode() if isinstance(v, bytes) else v
                                for k, v in files.items()
                                if k in _METADATA_KEYS or v not in ("", b"")}
    return module


def state_spec_string(comp: StreamingCompensator, batch: int = 1) -> str:
    """The fresh state as ``"dtype:d0,d1;dtype:d0;..."`` (all zeros), for C++ loaders."""
    parts = []
    for t in comp.initial_state(batch):
        parts.append(_DTYPE_NAMES[t.dtype] + ":" + ",".join(str(d) for d in t.shape))
    return ";".join(parts)


_METADATA_KEYS = ("state_spec", "n_state", "counter", "held", "low", "high", "input_low",
                  "input_high", "out_of_range", "direction", "dtype", "batch")
#: the metadata keys a conditioned compensator adds: the number of conditions and the
#: clamp's bounds of each (comma-separated; -inf/inf without a clamp)
CONDITION_KEYS = ("n_conditions", "condition_low", "condition_high")
#: the metadata keys an adaptive compensator adds (the module docstring)
ADAPT_KEYS = ("adapt", "n_weights", "weights", "covariance", "adapt_counts", "w0", "inv_scale",
              "bound", "forgetting", "adapt_bound", "dead_zone", "excitation", "nlms_step",
              "initial_covariance")


def _floats(t: Tensor) -> str:
    return ",".join(repr(float(v)) for v in t.flatten())


def _adapt_metadata(comp: StreamingCompensator) -> dict[str, str]:
    """The :data:`ADAPT_KEYS` of an adaptive compensator ({} for a static one)."""
    if not isinstance(comp, AdaptiveCompensator):
        return {}
    n, w = len(comp.templates), 2 * comp.k
    w0 = comp.w0.double()
    scale = torch.clamp(w0.abs(), min=float(w0.square().mean().sqrt()))
    ratio = comp.bound.double() / scale
    digits = 15 if comp.low.dtype == torch.float64 else 7
    bound = float(f"{float(ratio.median()) if bool((scale > 0).all()) else 0.0:.{digits}g}")
    return {"adapt": "rls" if comp.rls else "nlms", "n_weights": str(comp.m),
            "weights": str(w), "covariance": str(w + 1) if comp.rls else "",
            "adapt_counts": str(n - 1), "w0": _floats(comp.w0),
            "inv_scale": _floats(comp.inv_scale), "bound": _floats(comp.bound),
            "forgetting": repr(comp.forgetting), "adapt_bound": repr(bound),
            "dead_zone": repr(comp.dead_zone), "excitation": repr(comp.excitation),
            "nlms_step": repr(comp.nlms_step), "initial_covariance": repr(comp.p0)}


def metadata(comp: StreamingCompensator, batch: int = 1) -> dict[str, str]:
    """The exported metadata of a compensator (see the module docstring), all strings."""
    state = comp.initial_state(batch)
    oor = (f"{STATE_I}:{state[STATE_I].shape[1] - 1}" if comp.clamp_input else "")
    return {
        "state_spec": state_spec_string(comp, batch), "n_state": str(len(state)),
        "counter": f"{COUNTER[0]}:{COUNTER[1]}", "held": f"{HELD[0]}:{HELD[1]}",
        "low": repr(float(comp.low)), "high": repr(float(comp.high)),
        "input_low": repr(float(comp.in_low)), "input_high": repr(float(comp.in_high)),
        "out_of_range": oor, "direction": str(int(comp.direction)),
        "dtype": _DTYPE_NAMES[comp.low.dtype], "batch": str(batch),
        **({} if comp.n_conditions == 0 else {
            "n_conditions": str(comp.n_conditions),
            "condition_low": ",".join(repr(float(v)) for v in comp.cond_low),
            "condition_high": ",".join(repr(float(v)) for v in comp.cond_high)}),
        **_adapt_metadata(comp),
    }


def _position(text: str) -> tuple[int, int]:
    tensor, column = text.split(":")
    return int(tensor), int(column)


def _parse_state_spec(spec: str) -> list[Tensor]:
    out = []
    for part in spec.split(";"):
        name, dims = part.split(":")
        shape = [int(d) for d in dims.split(",") if d]
        out.append(torch.zeros(shape, dtype=_NAME_DTYPES[name]))
    return out


def _aoti_defaults(dtype: torch.dtype) -> dict[str, Any]:
    """AOTInductor options of :func:`to_aoti`: in float32, the network's two small matrix
    products as generated C++ (Inductor's CPP GEMM template) instead of calls into the BLAS
    library, whose per-call overhead dominates at batch 1 (about 1.5 us of a 6 us step). The
    template has no float64 version."""
    if dtype != torch.float32:
        return {}
    return {"max_autotune": True, "max_autotune_gemm_backends": "CPP"}


class _ExplicitStep(nn.Module):
    def __init__(self, comp: StreamingCompensator) -> None:
        super().__init__()
        self.comp = comp

        self.names = [name for name, _ in comp.example_inputs(1)]

    def forward(self, x: Tensor, *inputs: Tensor) -> tuple[Tensor, ...]:
        """``(x, *state)``, or ``(x, *example inputs, *state)``: ``(x, conditions, *state)``
        for a conditioned model, ``(x, [conditions,] measured_prev, applied_prev, *state)``
        for an adaptive one (:meth:`StreamingCompensator.example_inputs`)."""
        k = len(self.names)
        u, new = self.comp.step_explicit(x, list(inputs[k:]),
                                         **dict(zip(self.names, inputs[:k], strict=True)))
        return (u, *new)


def to_aoti(
    model: nn.Module, path: str | os.PathLike, *, limits: tuple[float, float] | None = None,
    initial_command: float = 0.0, input_range: tuple[float, float] | None = None,
    input_margin: float | None = 0.05, direction: str = "auto",
    batch: int = 1, inductor_configs: dict[str, Any] | None = None, adapt: str = "none",
    forgetting: float = 0.995, adapt_bound: float = 0.5, dead_zone: float = 0.0,
    excitation: float = 1e-3, nlms_step: float = 0.2, initial_covariance: float = 1.0,
) -> str:
    """Compile the explicit-state step with ``torch.export`` + AOTInductor into a package.

    The package runs ``(x_t (batch,), *state) -> (u_t (batch,), *state)``; a conditioned
    model's (``n_conditions > 0``, ``docs/conditions.md``) runs ``(x_t (batch,), conditions
    (batch, n_conditions), *state) -> (u_t (batch,), *state)``, and its metadata adds
    :data:`CONDITION_KEYS`. An adaptive one's (``adapt``) takes ``measured_prev`` and
    ``applied_prev`` (batch,) after them, and its metadata adds :data:`ADAPT_KEYS`. The
    fresh state is all zeros; its shapes and dtypes, the
    counter's position and the limits are in the package metadata (:func:`metadata`).
    Compiling takes a minute or more on a small CPU.

    Args:
        model, limits, initial_command, input_range, input_margin, direction: as
            :func:`to_torchscript`.
        path: output package (a name ending in ``.pt2``), written atomically: an old file
            there is replaced whole or, on an error, left as it was.
        adapt, forgetting, adapt_bound, dead_zone, excitation, nlms_step,
            initial_covariance: as :func:`to_torchscript`.
        batch: batch size the package is compiled for (static).
        inductor_configs: extra AOTInductor options; they override the defaults
            (in float32 ``max_autotune=True, max_autotune_gemm_backends="CPP"``: generated
            matrix products, for latency at small batch).

    Returns:
        The package path.
    """
    path = _check_path(path)
    if not path.endswith(".pt2"):
        raise ValueError(f"path {path!r}: the name of an AOTI package must end in .pt2")
    check_int(batch, "batch", minimum=1)
    comp = _compensator(model, limits, initial_command,
                        {"input_range": input_range, "input_margin": input_margin,
                         "direction": direction, **adapt_options(
                             adapt, forgetting, adapt_bound, dead_zone, excitation,
                             nlms_step, initial_covariance)}).eval()
    state = comp.initial_state(batch)
    x = torch.zeros(batch, dtype=comp.low.dtype)
    # the inputs between x and the state: the conditions, the adaptive pair
    extra = [t for _, t in comp.example_inputs(batch)]
    with torch.no_grad():
        ep = torch.export.export(_ExplicitStep(comp), (x, *extra, *state), strict=False)
    configs = {**_aoti_defaults(comp.low.dtype), "aot_inductor.metadata": metadata(comp, batch),
               **(inductor_configs or {})}
    buffer = io.BytesIO()
    torch._inductor.aoti_compile_and_package(ep, package_path=buffer, inductor_configs=configs)
    _write(path, buffer.getvalue())
    return path


class AOTIStepper(AdaptiveStepper):
    """Python runner of an AOTI package from :func:`to_aoti`: ``step``, ``reset``, counter;
    for an adaptive package ``adapted_weights()``, ``updates_count()``, ``skipped_count()``
    and ``refused_count()``. Safe across threads: a lock makes ``step`` and ``reset`` run one
    at a time.

    Args:
        path: the ``.pt2`` package.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.runner = torch._inductor.aoti_load_package(os.fspath(path))
        meta = self.runner.get_metadata()
        self.metadata = {k: meta[k] for k in (*_METADATA_KEYS, *CONDITION_KEYS, *ADAPT_KEYS)
                         if k in meta}
        self.adaptation = FileAdaptation(self.metadata)
        self.n_conditions = int(meta.get("n_conditions", "0"))
        self.spec = meta["state_spec"]
        self.counter = _position(meta["counter"])
        oor = meta.get("out_of_range", "")
        self.out_of_range = _position(oor) if oor else None
        self.low, self.high = float(meta["low"]), float(meta["high"])
        self._lock = threading.Lock()
        self.reset()
        self.batch = int(self.state[0].shape[0])

    def reset(self) -> None:
        """Back to the fresh (all-zero) state."""
        with self._lock:
            self.state = _parse_state_spec(self.spec)

    def step(self, x_t: Tensor, conditions: Tensor | None = None,
             measured_prev: Tensor | None = None, applied_prev: Tensor | None = None) -> Tensor:
        """One sample, x_t (batch,) (and, for a package with conditions, their values
        (batch, n_conditions); for an adaptive package the last sample's measured response
        and applied command (batch,), None: no update) -> command (batch,).

        The compiled kernels index their inputs with the strides seen at export (dense,
        row-major) and do not check them at run time, so the sample and the conditions are
        made contiguous: a strided view such as ``x[:, t]`` would otherwise be read as
        ``x[0, t:t + batch]``.

        Raises:
            ValueError: ``x_t`` is not of shape ``(batch,)`` with the compiled batch;
                conditions missing, given to a package without, or of another shape; a
                member of the pair of another shape, or given to a static package.
        """
        if x_t.dim() != 1 or x_t.shape[0] != self.batch:
            raise ValueError(
                f"step expects shape ({self.batch},) (the compiled batch), got shape "
                f"{tuple(x_t.shape)}"
            )
        dtype = self.state[0].dtype
        extra = file_conditions(conditions, self.n_conditions, self.batch, dtype, "package")
        extra += file_pair(measured_prev, applied_prev, self.adaptation.adaptive, self.batch,
                           dtype, "package")
        with self._lock:  # the state read, stepped and replaced by one thread at a time
            out = self.runner(x_t.to(dtype).contiguous(), *extra, *self.state)
            self.state = [s.contiguous() for s in out[1:]]
        return out[0]

    def nonfinite_count(self) -> Tensor:
        """Samples held because the input was NaN or inf, per row (the metadata's
        ``counter`` position)."""
        return self.state[self.counter[0]][:, self.counter[1]]

    def out_of_range_count(self) -> Tensor:
        """Finite samples clamped to the training input range, per row (the metadata's
        ``out_of_range`` position; zeros for a package without a clamp)."""
        if self.out_of_range is None:
            return torch.zeros_like(self.nonfinite_count())
        return self.state[self.out_of_range[0]][:, self.out_of_range[1]]


def load_aoti(path: str | os.PathLike) -> AOTIStepper:
    """Load a package written by :func:`to_aoti` (see :class:`AOTIStepper`)."""
    return AOTIStepper(path)
