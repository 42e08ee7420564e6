"""The entry of the C generator: :func:`to_c` checks its arguments, builds the compensator in
the C step's dtype, exports its step and writes the two files (:mod:`torchhys.deploy.c`)."""

from __future__ import annotations

import copy
import os
import re
from pathlib import Path
from typing import Any

import torch
from torch import nn

from torchhys.deploy.c._files import files, state_members
from torchhys.deploy.c._graph import translate
from torchhys.deploy.c._writer import Writer
from torchhys.deploy.export import ADAPT_DEFAULTS, _compensator, _ExplicitStep, write_outputs
from torchhys.deploy.streaming import StreamingCompensator
from torchhys.protocols import check_deployable

_C_KEYWORDS = frozenset(
    "auto break case char const continue default do double else enum extern float for goto "
    "if inline int long register restrict return short signed sizeof static struct switch "
    "typedef union unsigned void volatile while _Bool _Complex _Imaginary".split())


DEFAULT_PREFIX = "torchhys_comp"


def check_prefix(prefix: object) -> str:
    """``prefix`` if it is a C identifier fit for the generated names, else ValueError."""
    if not (isinstance(prefix, str) and re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", prefix)
            and prefix not in _C_KEYWORDS and not prefix.startswith("__")):
        raise ValueError(f"prefix must be a C identifier (letters, digits, '_', not starting "
                         f"with a digit or '__', not a keyword), got {prefix!r}")
    return prefix


def _check_out_dir(out_dir: object) -> Path:
    if not isinstance(out_dir, (str, os.PathLike)):
        raise TypeError(f"out_dir must be a str or os.PathLike, got {type(out_dir).__name__}")
    path = Path(out_dir)
    if not path.is_dir():
        raise ValueError(f"out_dir {os.fspath(out_dir)!r} is not an existing folder")
    if not os.access(path, os.W_OK | os.X_OK):
        raise ValueError(f"out_dir {os.fspath(out_dir)!r} is not writable")
    return path


def _build(model: nn.Module, dtype: torch.dtype, limits: Any, initial_command: float,
           options: dict[str, Any]) -> StreamingCompensator:
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}")
    if isinstance(model, StreamingCompensator):
        if model.low.dtype != dtype:
            raise ValueError(f"dtype {dtype} differs from the StreamingCompensator's "
                             f"{model.low.dtype}: pass the model instead")
    elif any(t.is_floating_point() and t.dtype != dtype
             for t in (*check_deployable(model, "model").parameters(), *model.buffers())):
        model = copy.deepcopy(model).to(dtype)
    return _compensator(model, limits, initial_command, options).eval()


def to_c(
    model: nn.Module, out_dir: str | os.PathLike, *, prefix: str = DEFAULT_PREFIX,
    dtype: torch.dtype = torch.float64, limits: tuple[float, float] | None = None,
    initial_command: float = 0.0, input_range: tuple[float, float] | None = None,
    input_margin: float | None = 0.05, direction: str = "auto", adapt: str = "none",
    forgetting: float = 0.995, adapt_bound: float = 0.5, dead_zone: float = 0.0,
    excitation: float = 1e-3, nlms_step: float = 0.2, initial_covariance: float = 1.0,
) -> tuple[Path, Path]:
    """Write the compensator of ``model`` as C99: ``out_dir/PREFIX.h`` and ``PREFIX.c``.

    Args:
        model: an :class:`~torchhys.InverseHysteresisNet` with causal operators, a
            :class:`~torchhys.PrandtlIshlinskiiInverse`, a composition of operators and
            recurrent layers (:func:`torchhys.compose.compose`), any model with streaming
            steps, or a built :class:`~torchhys.deploy.streaming.StreamingCompensator` (then
            in ``dtype``).
        out_dir: an existing folder. The two files are written atomically: both are
            complete on the disk before either replaces an old file of its name; on an error
            (a full disk) the old pair is left as it was.
        prefix: the C prefix of every name (a C identifier).
        dtype: ``torch.float64`` or ``torch.float32``: the C step's real type (a model in
            another dtype is copied and converted, as ``model.to(dtype)``).
        limits, initial_command, input_range, input_margin, direction: as
            :func:`torchhys.deploy.export.to_torchscript`.
        adapt: ``"none"`` (the static step ``PREFIX_step``), ``"rls"`` or ``"nlms"``: the
            adaptive step ``PREFIX_step_adapt(s, desired, [conditions,] measured_prev,
            applied_prev)`` of :class:`~torchhys.deploy.adaptive.AdaptiveCompensator`, with
            ``PREFIX_N_WEIGHTS``, ``PREFIX_weights`` (the readout's current weights) and the
            counters ``PREFIX_updates_count``, ``PREFIX_skipped_count`` and
            ``PREFIX_refused_count``.
        forgetting, adapt_bound, dead_zone, excitation, nlms_step, initial_covariance: the
            adaptive compensator's options (used with ``adapt`` rls or nlms).

    Returns:
        ``(header_path, source_path)``.

    Shapes:
        The C step: ``x`` (one sample, the desired output in physical units) -> the command
        (one sample); batch 1, the state in the caller's ``PREFIX_state``.

    Raises:
        ValueError: a bad ``prefix``, ``dtype`` or ``out_dir``; an operation in the step
            without a C template (the message names it and the step it came from); see
            :class:`~torchhys.deploy.streaming.StreamingCompensator` for the other options.
        TypeError: see :class:`~torchhys.deploy.streaming.StreamingCompensator`.
    """
    prefix, folder = check_prefix(prefix), _check_out_dir(out_dir)
    adaptive = {"adapt": adapt, "forgetting": forgetting, "adapt_bound": adapt_bound,
                "dead_zone": dead_zone, "excitation": excitation, "nlms_step": nlms_step,
                "initial_covariance": initial_covariance}
    given = {k: v for k, v in adaptive.items() if v != ADAPT_DEFAULTS[k]}
    comp = _build(model, dtype, limits, initial_command,
                  {"input_range": input_range, "input_margin": input_margin,
                   "direction": direction, **given})
    state = comp.initial_state(1)
    inputs = comp.example_inputs(1)
    with torch.no_grad():
        ep = torch.export.export(_ExplicitStep(comp),
                                 (torch.zeros(1, dtype=dtype), *(t for _, t in inputs),
                                  *state), strict=False)
    w = Writer(prefix)
    u, outputs = translate(ep, w, state_members(comp, len(state)),
                           inputs=[name for name, _ in inputs])
    options = {"dtype": str(dtype).replace("torch.", ""), "limits": limits,
               "initial_command": initial_command, "input_range": input_range,
               "input_margin": input_margin, "direction": direction}
    if adapt != "none":
        options.update(adaptive)
    header, source = files(prefix, w, model, comp, state, u, outputs, options)
    h_path, c_path = folder / f"{prefix}.h", folder / f"{prefix}.c"
    # both complete on the disk before either replaces its old version
    write_outputs([(h_path, header.encode()), (c_path, source.encode())])
    return h_path, c_path
